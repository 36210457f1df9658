"""The owner of a person in the ranker node, without ROS (``Personalisation``): everything
the node holds about a person is held here or indexed from here, and the node core, fleet
intake, forget, retention and restore reach a person only through it.

It holds the one model served (a ``stack.ServingStack``: the predictor with its overlay of folded-in
people, the ``FoldIn`` with its caches of their rows, the ``Uncertainty``), swapped whole by
``use`` at a reload; each person's history (bounded: histories.FeedbackHistories) and peers'
ratings (``fleet``), the ratings their served model was solved from, what waits to be
solved, written, announced or sent once durable (``outgoing``), peers' messages being
checked, the scene requests that feedback is matched against (``scene_memory``), the person
served now (stars/user_id), the strangers reported once, and the tombstones. It indexes the
holders outside it: the authenticator's replay memory, the state store it writes, and what
the node gives it in ``holders`` (its problem reports). ``forget_person`` is the one call
that reaches every one of them (docs/privacy.md).

Accepted feedback on a scene the node ranked is added to that user's history, and the user
waits in ``pending``. The node calls ``solve_next`` when no scene waits, one user per turn,
so the ranking of others waits for at most one solve (timings in docs/personalisation.md); a
person with many ratings whose rows are not built yet (restored after a restart) has them
built ``PREPARE_ROWS`` a turn. The result goes into the predictor's overlay (swapped whole):
the person's own next rankings use it at once.

This is the one writer of a person (``stars_ros.state``; ``keeping``): each change of a
person's ratings queues one write, with the feedback entry that brought it (one write per
feedback), which the store's own thread commits. What others see of a served model waits for
that commit (``publish_when_durable``). With fleet sharing, peers' ratings join a user's own
and the model is solved from the union.

One thread (the node's executor) calls ``Personalisation``.
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import os
from typing import Callable, Mapping

from stars_ros.personalisation import fleet
from stars_ros import messages
from stars_ros.errors import StarsError, UnknownActionError
from stars_ros.personalisation.foldin import FoldIn, rating_from_feedback
from stars_ros.personalisation.histories import FeedbackHistories
from stars_ros.personalisation.keeping import Keeping
from stars_ros.personalisation.outgoing import Outgoing
from stars_ros.personalisation.scene_memory import SCENE_MEMORY, SceneMemory
from stars_ros.personalisation.stack import ServingStack, serving_stack
from stars_ros.state.forgotten import folder_secret
from stars_ros.state import Forgotten, PersonWriter, Rating, UserModel, check_ratings, mentions

PREPARE_ROWS = 8  # ratings' scenes encoded per call of solve_next: bounds how long one holds the executor
MAX_STRANGERS_REMEMBERED = 10000


@dataclasses.dataclass
class PeerIntake:
    """New ratings of one peer message, checked one scene per executor turn: ``encoded`` of
    them so far."""

    user_id: str
    peer: str
    ratings: list
    encoded: int = 0


class Personalisation(Keeping):
    """The owner of the people the node serves: their fold-in into the model served, and
    everything else the node holds of them (see the module docstring).

    Args:
        predictor (Predictor): the model served; ``use`` replaces it on a reload.
        max_ratings (int): most recent ratings per user kept and solved from.
        max_users (int): folded-in users kept; beyond, the one who rated least recently goes.
        report (callable): ``report(kind, detail)``, called for each problem.
        logger (optional): gets ``info`` and ``warning`` lines (default: this module's logger).
        store (state.PersonWriter, optional): where people persist; None: nothing does.
        scene_memory (int, optional): scene requests remembered for feedback.
        origin (str, optional): the node's name, which its ratings carry.
        sharing (bool, optional): fleet sharing: solve each user from their own and their
            peers' ratings (``fleet``), each scene encoded on its own.
        authenticator (feedback_auth.FeedbackAuthenticator, optional): feedback is signed
            (the node has checked it): each rating keeps its signed message and is named by
            its MAC, and a peer's rating is taken only when it passes ``check_rating``.
        after_person_read (callable, optional): called after a person restored from the
            store has their ratings read (the ranker process moves them out of the garbage
            collector's generations then: ``gc.freeze``).
        holders (Mapping, optional): what else holds something of a person, by name:
            ``forget(named) -> entries removed``, ``named`` a ``state.mentions``; each is
            called by ``forget_person``.
    """

    def __init__(self, predictor, max_ratings: int, max_users: int, report: Callable[[str, str], None],
                 logger=None, store: PersonWriter | None = None, scene_memory: int = SCENE_MEMORY, origin: str = '',
                 sharing: bool = False, authenticator=None,
                 after_person_read: Callable[[], None] | None = None,
                 holders: Mapping[str, Callable[[Callable[[bytes], bool]], int]] | None = None):
        self.histories = FeedbackHistories(max_ratings, max_users)
        self.peers = fleet.PeerRatings(max_ratings, max_users)
        if after_person_read is not None:
            self.histories.after_read = self.peers.after_read = after_person_read
        self.origin, self.sharing, self.authenticator = origin, sharing, authenticator
        self.holders = dict(holders or {})
        self.scenes = SceneMemory(scene_memory)
        self.pending = collections.OrderedDict()  # users to re-solve, longest waiting first
        self.to_announce = collections.OrderedDict()  # users whose model peers are to be sent again
        self.intake = collections.deque()  # PeerIntake: peers' ratings being checked, oldest first
        self.solved_from = {}  # user -> the ratings their served model was solved from
        self.written = {}  # user -> sequence number of their latest write to the store
        self.unsaved = set()  # users whose served model the store does not hold yet
        self.outgoing = Outgoing()  # models waiting to be sent once durable; people whose erase runs
        self.served_user = None  # the person stars/user_id says is served now
        self._strangers_reported = set()  # unknown users reported once per checkpoint
        self.forgotten = self._with_fleet_keys(Forgotten(None))  # the tombstones of people erased (the store's,
        # once restored)
        self._report = report
        self._logger = logger or logging.getLogger(__name__)
        self.store = store
        self.serving = self._serving(predictor)

    @property
    def predictor(self):
        """The Predictor served (with its overlay of folded-in people)."""
        return self.serving.predictor

    @property
    def foldin(self) -> FoldIn | None:
        return self.serving.foldin

    @property
    def uncertainty(self):
        return self.serving.uncertainty

    def _serving(self, predictor) -> ServingStack:
        """``predictor``'s stack (``stack.serving_stack``), the fold-in reading the h of restored
        people's scenes from the store (not with fleet sharing, which encodes each scene on its
        own so that peers' models agree to the last bit); no fold-in (and a warning) for a model
        without users."""
        from_store = self.store is not None and not self.sharing
        stack = serving_stack(predictor, scene_by_scene=self.sharing, stored=(
            lambda scenes: self.store.encodings(scenes, predictor.fingerprint)) if from_store else None)
        if stack.foldin is None:
            self._logger.warning(f'no online fold-in with this checkpoint: {stack.no_foldin}')
        return stack

    def use(self, predictor) -> None:
        """Serve ``predictor`` from now on (a reload), the one place the model changes. Users
        the new checkpoint was refit on keep only the feedback it did not absorb; everyone with
        a history left waits to be re-solved against the new model."""
        self.serving = self._serving(predictor)
        self._strangers_reported = set()  # who is a stranger depends on the model
        absorbed = predictor.metadata.get('provenance', {}).get('refit', {}).get('ratings_per_user', {})
        had = set(self.histories.users())
        for user_id in [*self.histories.absorb(absorbed), *self.peers.users()]:
            self.pending[user_id] = None
        if self.store is not None:
            self.store.set_fingerprint(predictor.fingerprint)
            for user_id in had & set(absorbed):
                if user_id in self.histories or user_id in self.peers:
                    self._save(user_id)
                else:
                    self._forget_stored(user_id)

    # -- what the node core asks -----------------------------------------------------------
    def scene_received(self, scene_id: str, request) -> None:
        """Remember a scene request (its text or ``Twin``) for the feedback that will name it."""
        self.scenes.received(scene_id, request)

    def scene_ranked(self, scene_id: str, request, predictor, h, plain=None) -> None:
        """Keep what ranking a remembered request computed (``SceneMemory.ranked``)."""
        self.scenes.ranked(scene_id, request, predictor, h, plain)

    def recent_scenes(self, count: int) -> list:
        return self.scenes.recent(count)

    def is_forgotten(self, user_id: str) -> bool:
        """True for a person forgotten here or by a fleet peer: nothing of theirs is taken."""
        return user_id in self.forgotten

    def first_report_of_stranger(self, user_id: str) -> bool:
        """True the first time (per checkpoint) ``user_id`` is ranked as a stranger."""
        if user_id in self._strangers_reported:
            return False
        if len(self._strangers_reported) >= MAX_STRANGERS_REMEMBERED:
            self._strangers_reported.clear()
        self._strangers_reported.add(user_id)
        return True

    def waiting(self) -> dict:
        """How many peer messages wait to be checked, people to be solved, models to be
        announced and models to be sent once durable."""
        return {'intake': len(self.intake), 'solve': len(self.pending), 'announce': len(self.to_announce),
                'durable': int(bool(self.outgoing))}

    def next_to_announce(self) -> str:
        return self.to_announce.popitem(last=False)[0]

    def publish_when_durable(self, user_id: str, send: Callable[[str], None],
                             wake: Callable[[], None]) -> None:
        """``send`` the stars/user_model payload of ``user_id``'s served model once the store
        has committed the ratings it was solved from (nobody sees a model a hard kill could
        take back): now without a store; else it waits in ``outgoing`` (``models_to_send``)
        and ``wake`` is called from the store's thread."""
        message = self.model_message(user_id)
        if message is None:
            return
        payload = messages.dumps(message)
        if self.store is None:
            send(payload)
            return

        def committed():  # on the store's thread, or on this one if it is committed already
            self.outgoing.committed(user_id, payload)
            wake()
        self.store.when_committed(self.durable_after(user_id), committed)

    def models_to_send(self) -> list:
        """The payloads of models now durable, those of people being erased left out."""
        return self.outgoing.take()

    # -- feedback ------------------------------------------------------------------------
    def add_feedback(self, feedback, max_bytes: int = messages.DEFAULT_MAX_BYTES, stamp: int = 0,
                     journal: tuple[dict, str] | None = None) -> str | None:
        """Add the rating ``feedback`` (messages.Feedback) gives, received at ``stamp`` (ROS
        time, ns), to its user's history and queue the user for a solve; returns instead why
        it cannot be folded in (the node reports that as ``unknown_scene``). ``journal``
        (the feedback entry and its recording) is written with the user's new rating, in one
        write; refused, it is written alone."""
        if feedback.user_id in self.forgotten:  # neither journaled nor folded in: nothing of theirs is kept
            return 'feedback of a person who was forgotten here: not stored, not folded in'
        rating = self._rating(feedback, max_bytes)
        if isinstance(rating, str):
            self.record_feedback(journal)
            return rating
        signed = feedback.signed if self.authenticator is not None else None
        self._keep_solved_from(feedback.user_id)
        rating = dataclasses.replace(rating, rating_id=signed['auth']['mac'] if signed else fleet.new_rating_id(),
                                     stamp=stamp, origin=self.origin, feedback=signed or rating.feedback)
        self._forget(self.histories.add(feedback.user_id, rating))
        self.pending[feedback.user_id] = None
        self._save(feedback.user_id, journal)
        return None

    def _rating(self, feedback, max_bytes: int) -> Rating | str:
        """The Rating ``feedback`` gives, or why it cannot be folded in."""
        remembered, encoded = self.scenes.get(feedback.scene_id)
        if remembered is None:
            return (f"feedback for scene '{feedback.scene_id}', which this node has not ranked (or no longer "
                    'remembers): recorded, not folded in')
        try:  # parsed again: it passed before, unless max_message_bytes was lowered since
            request = messages.parse_scene_request(remembered, max_bytes)
        except messages.BadMessage as error:
            return f"feedback for scene '{feedback.scene_id}' not folded in: its request no longer passes: {error}"
        rating = rating_from_feedback(feedback, request, self.predictor)
        if not isinstance(rating, str) and encoded is not None and self.foldin is not None \
                and encoded[0] is self.foldin.predictor and not self.sharing:  # h from ranking it: the
            # solve need not encode (a shared rating is encoded alone, as its peers encode it)
            index = request.labels.index(feedback.candidate) if request.ranks_scenes else 0
            plain = encoded[2]
            self.foldin.remember([rating.scene], encoded[1][index:index + 1],
                                 plain=None if plain is None else plain[index:index + 1])
        return rating

    def add_peer_ratings(self, user_id: str, entries: list, peer: str = '') -> bool:
        """Stage the ``ratings`` of a peer's stars/user_model message (fleet sharing) that this
        node does not hold yet; True when some wait in ``intake`` (call ``take_in_next``).
        UnknownActionError, and nothing is staged, when one names an action the model lacks;
        OutOfScaleError when one's score lies outside the checkpoint's rating scale;
        with signed feedback, BadMessage ``auth`` when the message carries no ratings or one
        of the new ones fails ``check_rating``."""
        foldin = self.foldin
        if foldin is None:
            return False
        if user_id in self.forgotten:
            raise messages.BadMessage('forgotten', 'a model of a person who was forgotten here: refused, nothing '
                                      'taken in')
        if self.authenticator is not None and not entries:
            raise messages.BadMessage('auth', 'it carries no ratings: with feedback_key_file set, a peer model is '
                                      'taken only with the signed ratings it was solved from')
        held = self._held(user_id)
        try:
            new = list({e['id']: Rating.from_json(e) for e in entries if e['id'] not in held}.values())
        except OverflowError:  # an integer the schema takes but no float holds: refused, not a crash
            raise messages.BadMessage('non_finite', 'a rating holds a number too large for a float') from None
        check_ratings(new, self.predictor.rating_scale, user_id)
        for rating in new if self.authenticator is not None else ():
            refusal = self.authenticator.check_rating(user_id, rating)
            if refusal is not None:
                raise messages.BadMessage('auth', refusal)
        if not new:
            return False
        for rating in new:
            if rating.action not in foldin.actions:
                raise UnknownActionError(f"rating '{rating.rating_id}' is of action '{rating.action}'; this model "
                                         f'knows {list(foldin.actions)}')
        self.intake.append(PeerIntake(user_id, peer, new))
        return True

    def take_in_next(self) -> tuple[str, str] | None:
        """Encode the next staged peer rating's scene (one forward pass per call, so rankings
        wait for at most one); once every rating of a message has passed, they join the
        user's and the user waits to be re-solved. Returns (kind, why) when a message is
        refused (a scene the model cannot encode): then none of its ratings is kept."""
        staged = self.intake[0]
        if self.foldin is None:
            self.intake.popleft()
            return None
        try:
            self.foldin.encode([staged.ratings[staged.encoded].scene])
        except StarsError as error:
            self.intake.popleft()
            return messages.error_kind(error), (f"user model of '{staged.user_id}' from {staged.peer} refused, nothing "
                                       f'taken in: {error}')
        staged.encoded += 1
        if staged.encoded == len(staged.ratings):
            self.intake.popleft()
            held = self._held(staged.user_id)
            new = [r for r in staged.ratings if r.rating_id not in held]  # another message may have brought them
            if new:
                self._keep_solved_from(staged.user_id)
                self._forget(self.peers.add(staged.user_id, new))
                self.pending[staged.user_id] = None
                self._save(staged.user_id)
        return None

    def _held(self, user_id: str) -> set:
        return self.peers.known(user_id) | {r.rating_id for r in self.histories.ratings(user_id)}

    def ratings(self, user_id: str) -> list:
        """The ratings ``user_id``'s model is solved from: their history, and with fleet
        sharing the union with their peers' ratings (``fleet.solve_set``)."""
        own = self.histories.ratings(user_id)
        if not self.sharing:
            return own
        return fleet.solve_set(own, self.peers.ratings(user_id), self.histories.max_ratings)

    def announce_all(self) -> None:
        """Send every folded-in user's model to peers again (one joined): ``to_announce``."""
        if self.sharing:
            self.to_announce.update(dict.fromkeys(self.predictor.user_models))

    def model_message(self, user_id: str) -> dict | None:
        """The stars/user_model message of ``user_id``'s served model (None: none served);
        with fleet sharing, with the ratings it was solved from."""
        model = self.predictor.user_model(user_id)
        if model is None:
            return None
        if not self.sharing:
            return messages.user_model_payload(user_id, model, self.predictor.fingerprint)
        self._keep_solved_from(user_id)
        return messages.user_model_payload(user_id, model, self.predictor.fingerprint, self.origin,
                                           self.solved_from[user_id])

    def _keep_solved_from(self, user_id: str) -> None:
        """A model restored from the store was solved from the ratings restored with it:
        note them before they change (read now if they were not yet)."""
        if user_id not in self.solved_from and self.predictor.user_model(user_id) is not None:
            self.solved_from[user_id] = self.ratings(user_id)

    # -- the solve -----------------------------------------------------------------------
    def solve_next(self, min_ratings: int = 1, regularisation: float = 0.0) -> tuple[str, UserModel] | None:
        """Re-solve the user who has waited longest from their history against the current
        model (the Gaussian posterior; a positive ``regularisation``: the ridge override):
        (user_id, the model now served for them), or None when there was nothing to solve
        (no one waiting, no fold-in with this model, fewer than ``min_ratings``) or when the
        one waiting longest still has ratings to encode (``PREPARE_ROWS`` a call: a person
        restored with hundreds of ratings does not hold the executor for a whole encoding)."""
        if not self.pending:
            return None
        user_id = self.pending.popitem(last=False)[0]
        foldin = self.foldin
        ratings = self.ratings(user_id)
        if foldin is None or not ratings or len(ratings) < min_ratings:
            return None
        try:
            if not foldin.prepare(ratings, PREPARE_ROWS):
                self.pending[user_id] = None  # more of their rows next time, first in line again
                self.pending.move_to_end(user_id, last=False)
                return None
        except StarsError:
            pass  # the solve below finds the ratings it cannot use
        try:
            model = foldin.fit(ratings, user_id, regularisation)
        except StarsError:
            ratings = self._drop_unusable(foldin, user_id, ratings)
            if not ratings:
                return None
            model = foldin.fit(ratings, user_id, regularisation)
        self.solved_from[user_id] = ratings
        self.predictor.set_user_model(user_id, model)
        self.to_announce.pop(user_id, None)  # the solve's own message carries it
        self.unsaved.add(user_id)  # written with their next write or at flush: one write per feedback
        return user_id, model

    def _drop_unusable(self, foldin: FoldIn, user_id: str, ratings: list) -> list:
        """Ratings of an action or a scene the model does not take (a reload changed it) leave
        the history and the peers' ratings, each reported."""
        unusable = []
        self._keep_solved_from(user_id)
        for rating in ratings:
            try:
                foldin.action_index([rating.action])
                foldin.encode([rating.scene])
            except StarsError as error:
                unusable.append(rating)
                self._report(messages.error_kind(error), f"feedback of '{user_id}' not folded in: {error}")
        self.histories.discard(user_id, unusable)
        self.peers.discard(user_id, unusable)
        self._save(user_id)
        return self.ratings(user_id)

    def _forget(self, evicted: list) -> None:
        """Users pushed out by max_users go back to the checkpoint's row."""
        for user_id in evicted:
            self.predictor.set_user_model(user_id, None)
            self.peers.drop(user_id)
            self.solved_from.pop(user_id, None)
            self.unsaved.discard(user_id)
            self._report('user_models', f"folded-in user '{user_id}' dropped: more than fold_in_max_users = "
                         f'{self.histories.max_users} users rated more recently (their feedback stays in '
                         'the MCAP log for the offline refit)')
            self._forget_stored(user_id)


    # -- forget ------------------------------------------------------------------------------
    def forget_person(self, user_id: str) -> dict:
        """Erase ``user_id`` from every holder in memory and mark them forgotten, so their
        feedback and peers' models of them are refused from now on; {what: entries removed}:
        their history, peers' ratings, served model, what waits to be solved, written or
        announced, peers' messages being checked, the scene requests that name them, the
        fold-in's rows of their ratings, the authenticator's replay memory, the person
        served, the strangers reported, and each of ``holders``. Their erase is marked as
        running (``erase_begins``) until ``erase_ends``. The store's and the bags' part is
        ``recording.erasure.forget``'s, which the caller runs next with ``erase_stored``."""
        named = mentions(user_id)
        intake = [staged for staged in self.intake if staged.user_id == user_id]
        rated = [*self.histories.ratings(user_id), *self.peers.ratings(user_id),
                 *self.solved_from.get(user_id, ()), *(r for staged in intake for r in staged.ratings)]
        removed = {'ratings': self.histories.drop(user_id), 'peer_ratings': len(self.peers.ratings(user_id)),
                   'model': int(self.predictor.user_model(user_id) is not None),
                   'scene_requests': self.scenes.forget(named), 'peer_messages_in_intake': len(intake),
                   'replay_memory': (0 if self.authenticator is None
                                     else self.authenticator.forget_person(user_id)),
                   'fold_in_rows': 0 if self.foldin is None else self.foldin.forget_rows(rated)}
        removed.update({what: forget(named) for what, forget in self.holders.items()})
        self.peers.drop(user_id)
        self.predictor.set_user_model(user_id, None)
        for kept in (self.pending, self.to_announce, self.solved_from, self.written):
            kept.pop(user_id, None)
        self.unsaved.discard(user_id)
        self._strangers_reported.discard(user_id)
        if self.served_user == user_id:
            self.served_user = None
        for staged in intake:
            self.intake.remove(staged)
        if self.forgotten.secret is None and self.store is not None:
            self.forgotten = self._with_fleet_keys(Forgotten(folder_secret(self.store.folder, create=True),
                                                             self.forgotten.tags))
        if self.forgotten.secret is None:  # nothing recorded: remembered in memory only, with a secret of this run
            self.forgotten = self._with_fleet_keys(Forgotten(os.urandom(32), self.forgotten.tags))
        self.forgotten.add(user_id)
        return removed

    def erase_begins(self, user_id: str) -> None:
        """An erase of ``user_id`` runs: their models are held back, no message naming them is recorded."""
        self.outgoing.erase_begins(user_id)

    def erase_ends(self, user_id: str) -> int:
        """One erase of ``user_id`` ended: the models of theirs held back are dropped; how many."""
        return self.outgoing.erase_ends(user_id)

    def names_someone_erased(self, data: bytes) -> bool:
        """True when ``data`` names a person whose erase runs (the recording leaves it out)."""
        return self.outgoing.names_someone_erased(data)

    def known_people(self) -> set:
        """Every id this node holds something of: in memory (histories, peers' ratings,
        served models, what waits, the person served) and in the state store."""
        known = {*self.histories.users(), *self.peers.users(), *self.predictor.user_models, *self.pending,
                 *(staged.user_id for staged in self.intake), *({self.served_user} - {None})}
        return known | (set() if self.store is None else self.store.known_people())
