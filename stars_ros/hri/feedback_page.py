"""The touchscreen page's logic, without ROS or HTTP: whom it asks, what it shows, what an
answer sends, and what it refuses.

``stars_ros.ros.feedback_page`` feeds it the topics (``on_served_person`` from the bridge's
stars/served_person or ``on_user_id`` from stars/user_id, ``on_scene``, ``on_question``,
``on_ranking``, ``on_error``) and says when a ranker's end of stars/question_request,
stars/question or stars/errors joins (``on_ranker_joined``); the web server
(``stars_ros.hri.feedback_server``) feeds it the person's taps (``answer``, ``skip``,
``next``). Each returns the messages to publish as (topic, payload);
a bad request raises ``Refusal``, whose kind and message go back to the page and out on
stars/errors. The page sees ``view()``: never a key, never another person's question.

Through the bridge (``via_bridge``) an answer goes out on stars/person_feedback keyed by the
served person's ROS4HRI id, and the bridge drops an anonymous person's (docs/hri.md), and under
store_policy consented that of a person not on the consent list: the page says their answer
will not be kept, and why (stars/served_person's ``kept``). Without it, an answer is feedback
on stars/feedback for the user id on stars/user_id. With a signing key, answers are signed
here, server-side.

A question the ranker cannot choose yet (``no_question`` on stars/errors: it has seen no scene
to ask about) is asked for again at the served person's next ranking, and the page says why
it waits meanwhile; a request sent before the ranker's endpoints had matched the page's
(the page started while someone is served) is sent again when they match, and one that two
of the person's rankings overtook unanswered (the request, its answer or its error lost) at
the second.
"""
from __future__ import annotations

import collections
import hmac
import json
import math
from dataclasses import dataclass
from typing import Callable

from stars_ros import feedback_auth, messages

# the question request of an anonymous person: they have no user id, and the ranker answers
# any id it does not know with the population prior, so no person is named
ANONYMOUS_ASKER = 'anonymous-visitor'
RANKINGS_UNANSWERED = 2  # the served person's rankings that overtake a request before it is sent again
SCENES_KEPT = 256  # scene requests remembered to draw the scene a question names
PLACEMENT_WORDS = {'stay': 'stay where it is', 'left_50cm': 'move 50 cm to its left',
                   'right_50cm': 'move 50 cm to its right', 'back_50cm': 'move 50 cm back',
                   'ahead_50cm': 'move 50 cm ahead', 'left_100cm': 'move 1 m to its left',
                   'right_100cm': 'move 1 m to its right', 'back_100cm': 'move 1 m back'}
ACTION_WORDS = {'navigate': 'move through the room'}


class Refusal(Exception):
    """A request the page refuses: ``kind`` (the stars/errors kind), ``status`` (HTTP)."""

    def __init__(self, kind: str, message: str, status: int):
        super().__init__(message)
        self.kind, self.status = kind, status


@dataclass(frozen=True)
class PageSettings:
    """``rating_scale`` (low, high) of the served model; ``steps`` rating buttons across it;
    ``via_bridge``: answers go to the bridge as person feedback; ``posts_per_second`` and
    ``burst``: the most taps taken (a token bucket), more are refused as a flood; ``token``:
    what every request must carry ('' none); ``signing_key``: (key id, secret) or None."""

    rating_scale: tuple = (0.0, 1.0)
    steps: int = 5
    via_bridge: bool = True
    posts_per_second: float = 2.0
    burst: int = 5
    token: str = ''
    signing_key: tuple | None = None

    def __post_init__(self):
        low, high = self.rating_scale
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError(f'the rating scale must be two finite numbers, low < high, got {self.rating_scale}')
        if self.steps < 2:
            raise ValueError(f'steps must be at least 2, got {self.steps}')
        if not self.posts_per_second > 0 or self.burst < 1:
            raise ValueError('posts_per_second must be positive and burst at least 1')


def in_words(question: dict) -> str:
    """The question's action or placement as a person reads it."""
    if 'candidate' in question:
        label = question['candidate']
        return PLACEMENT_WORDS.get(label, label.replace('_', ' '))
    return ACTION_WORDS.get(question['action'], question['action'].replace('_', ' '))


class FeedbackPage:
    """The page's state (module docstring). Not thread-safe: the caller holds one lock.

    Args:
        settings (PageSettings): see there.
        now (callable): ROS time in ns (signing stamps, the flood bucket).
    """

    def __init__(self, settings: PageSettings, now: Callable[[], int]):
        self.settings, self._now = settings, now
        self.version = 0  # grows with every change the page should show
        self.person_id, self.anonymous = None, False  # via the bridge: whom it serves
        self.kept = True  # via the bridge: whether the served person's answers are kept
        self.user_id = None  # whose questions are asked (None: nobody served)
        self.question, self.question_number, self.pending = None, 0, None
        self.phase = 'waiting'  # waiting (no question), question, thanks
        self.outcome = None  # after an answer: what the robot does now, from the next ranking
        self._awaiting_ranking = False
        self._asked = False  # a question request is out, not yet answered by a question
        self._overtaken = 0  # the served person's rankings since it went out
        self.no_question = False  # the ranker could not choose one yet: asked again at the next ranking
        self._scenes = collections.OrderedDict()  # scene_id -> scene request payload
        self._bucket, self._bucket_at = float(settings.burst), None

    # -- the topics ---------------------------------------------------------------------
    def on_served_person(self, text: str) -> list:
        """stars/served_person from the bridge: ``{"person_id": id or null, "anonymous", "kept"}``
        (``kept`` false: the bridge will drop their answers, e.g. not on the consent list)."""
        payload = json.loads(text)
        messages.check('served_person', payload)  # msg_schemas/served_person.schema.json
        person_id, anonymous = payload['person_id'], payload['anonymous']
        self.person_id, self.anonymous = person_id, anonymous and person_id is not None
        kept = not self.anonymous and payload.get('kept', True)
        if kept != self.kept:
            self.kept = kept
            self.version += 1
        asker = None if self.person_id is None else ANONYMOUS_ASKER if self.anonymous else self.person_id
        return self._serve(asker)

    def on_user_id(self, user_id: str) -> list:
        """stars/user_id ('' nobody), when answers go to the ranker directly."""
        return self._serve(user_id or None)

    def on_scene(self, text: str) -> None:
        """Remember a stars/scene request, to draw the scene a question names."""
        request = json.loads(text)
        if isinstance(request, dict) and isinstance(request.get('scene_id'), str):
            self._scenes[request['scene_id']] = request
            self._scenes.move_to_end(request['scene_id'])
            while len(self._scenes) > SCENES_KEPT:
                self._scenes.popitem(last=False)

    def on_question(self, text: str) -> None:
        """stars/question: the served person's becomes the one shown (or, after an answer,
        the one the "next" button shows)."""
        question = json.loads(text)
        messages.check('question', question)
        if self.user_id is None or question['user_id'] != self.user_id:
            return
        self._asked = self.no_question = False
        self.question_number += 1
        question = {**question, 'number': self.question_number}
        if self.phase == 'thanks':
            self.pending = question
        else:
            self.question, self.phase = question, 'question'
        self.version += 1

    def on_ranking(self, text: str) -> list:
        """stars/ranking: after an answer, the served person's next one says what the robot
        does now and how sure the model is; while no question is shown, after a
        ``no_question`` or a request it overtook twice, it asks again (module docstring)."""
        if not (self._awaiting_ranking or self.phase == 'waiting'):
            return []
        ranking = json.loads(text)
        ranked_for = ranking.get('user_id') if isinstance(ranking, dict) else None
        if ranked_for != (None if self.anonymous else self.user_id) or not ranking.get('ranking'):
            return []
        if self.phase == 'waiting' and self.question is None:
            self._overtaken += self._asked
            if not self._asked or self._overtaken >= RANKINGS_UNANSWERED:
                return self._ask()
        if not self._awaiting_ranking:
            return []
        first = ranking['ranking'][0]
        self.outcome = {'words': in_words(first if 'candidate' in first else {'action': first['action']}),
                        'score': first['score'], 'score_sd': first.get('score_sd')}
        self._awaiting_ranking = False
        self.version += 1
        return []

    def on_error(self, text: str) -> None:
        """stars/errors: a ``no_question`` while a request is out is the ranker's answer to it
        (its errors name no person): the page says it waits for a scene, and asks again at the
        served person's next ranking."""
        error = json.loads(text)
        if not (isinstance(error, dict) and error.get('kind') == 'no_question' and self._asked):
            return
        self._asked, self.no_question = False, True
        self.version += 1

    def on_ranker_joined(self) -> list:
        """A ranker's stars/question_request subscription, or stars/question or stars/errors
        publisher, matched the page's: a request sent before, or its answer, could have been
        lost, so one is sent again while the page waits for a question."""
        if self.phase != 'waiting' or self.question is not None:
            return []
        return self._ask()

    # -- the person's taps --------------------------------------------------------------
    def check_token(self, given: str | None) -> None:
        if self.settings.token and not hmac.compare_digest((given or '').encode(), self.settings.token.encode()):
            raise Refusal('token', 'wrong or missing page token: open the address with ?token=... as configured '
                          '(token_file)', 403)

    def answer(self, body) -> list:
        """A tap on a rating: ``{"question": number, "score": value}``; the feedback to send."""
        question = self._current(body)
        score = body.get('score')
        if isinstance(score, bool) or not isinstance(score, (int, float)):
            raise Refusal('schema', '"score" must be a number', 400)
        low, high = self.settings.rating_scale
        try:
            score = float(score)  # an integer too large for a float is off every scale
        except OverflowError:
            score = math.inf
        if not low <= score <= high:  # NaN too
            raise Refusal('out_of_scale', f'score {score:g} is outside the rating scale [{low:g}, {high:g}]', 422)
        fields = {'user_id': self.person_id if self.settings.via_bridge else self.user_id,
                  'scene_id': question['scene_id'], 'score': score}
        fields['candidate' if 'candidate' in question else 'action'] = question.get('candidate', question['action'])
        if self.settings.signing_key is not None and not self.anonymous:
            key_id, secret = self.settings.signing_key
            fields = feedback_auth.sign(fields, key_id, secret, self._now(), self.settings.rating_scale)
        messages.parse_feedback(messages.dumps(fields))  # the message the ranker will parse
        if self.settings.via_bridge:
            fields = {'person_id': fields.pop('user_id'), **fields}
        self.question, self.phase, self.outcome, self._awaiting_ranking = None, 'thanks', None, True
        self.version += 1
        topic = 'stars/person_feedback' if self.settings.via_bridge else 'stars/feedback'
        return [(topic, messages.dumps(fields)), *self._ask()]

    def skip(self, body) -> list:
        """A tap on "skip": nothing is sent about the question; the next one is asked for."""
        self._current(body)
        self.question, self.phase = None, 'waiting'
        self.version += 1
        return self._ask()

    def next(self) -> list:
        """After the thanks, the question that came meanwhile, or a request for one."""
        self.check_flood()
        self.phase, self.outcome, self._awaiting_ranking = 'waiting', None, False
        if self.pending is not None:
            self.question, self.pending, self.phase = self.pending, None, 'question'
        self.version += 1
        return [] if self.question is not None else self._ask()

    def check_flood(self) -> None:
        """Take one tap from the bucket; Refusal 'flood' when it is empty."""
        now = self._now()
        if self._bucket_at is not None:
            self._bucket = min(self.settings.burst,
                               self._bucket + (now - self._bucket_at) * 1e-9 * self.settings.posts_per_second)
        self._bucket_at = now
        if self._bucket < 1:
            raise Refusal('flood', f'too many posts: at most {self.settings.posts_per_second:g} a second '
                          f'(bursts of {self.settings.burst}); wait a moment', 429)
        self._bucket -= 1

    # -- what the page shows ------------------------------------------------------------
    def scene_of(self, number: int) -> tuple | None:
        """(scene graph, candidate graph or None) of question ``number`` when it is shown and
        its scene was seen on stars/scene; None otherwise."""
        question = self.question
        if question is None or question['number'] != number:
            return None
        request = self._scenes.get(question['scene_id'])
        if request is None:
            return None
        if 'candidate' not in question:
            return (request['graph'], None) if 'graph' in request else None
        candidates = {c.get('candidate'): c.get('graph') for c in request.get('candidates') or ()}
        if question['candidate'] not in candidates:
            return None
        return next(iter(candidates.values())), candidates[question['candidate']]

    def view(self) -> dict:
        """What the page shows now (JSON)."""
        low, high = self.settings.rating_scale
        steps = self.settings.steps
        question = None
        if self.question is not None:
            question = {'number': self.question['number'], 'words': in_words(self.question),
                        'has_picture': self.scene_of(self.question['number']) is not None}
        not_kept = None if self.kept else 'anonymous' if self.anonymous else 'consent'
        return {'version': self.version, 'phase': self.phase, 'served': self.user_id is not None,
                'anonymous': self.anonymous, 'not_kept': not_kept, 'question': question,
                'pending': self.pending is not None, 'no_question': self.no_question,
                'outcome': self.outcome,
                'scale': [round(low + (high - low) * k / (steps - 1), 6) for k in range(steps)]}

    # -- inside -------------------------------------------------------------------------
    def _serve(self, asker: str | None) -> list:
        if asker == self.user_id:
            return []
        self.user_id, self.question, self.pending, self.outcome = asker, None, None, None
        self.phase, self._awaiting_ranking, self.no_question = 'waiting', False, False
        self.version += 1
        return self._ask()

    def _ask(self) -> list:
        self._asked, self._overtaken = self.user_id is not None, 0
        if self.user_id is None:
            return []
        return [('stars/question_request', messages.dumps({'user_id': self.user_id}))]

    def _current(self, body) -> dict:
        """The question ``body`` answers, once the flood bucket lets the tap through."""
        self.check_flood()
        if not isinstance(body, dict) or set(body) - {'question', 'score'}:
            raise Refusal('schema', 'expected a JSON object of "question" (and "score" for an answer)', 400)
        number = body.get('question')
        if isinstance(number, bool) or not isinstance(number, int):
            raise Refusal('schema', '"question" must be the number of the question shown', 400)
        if self.question is None or number != self.question['number']:
            shown = 'no question' if self.question is None else f"question {self.question['number']}"
            raise Refusal('stale', f'question {number} is no longer asked (now: {shown}); the page shows the '
                          'current one', 409)
        return self.question
