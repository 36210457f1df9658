"""Online personalisation for the ranker node, without ROS: which feedback becomes a rating,
the users waiting to be re-solved, the per-user solve, eviction, carrying users across a
checkpoint reload, and the scene memory that feedback is matched against.

Accepted feedback on a scene the node ranked (its request text and the h its ranking
computed, remembered in a bounded LRU map, ``SceneMemory``: strings and arrays cost the
garbage collector little, parsed JSON would cost it much more) is added to that user's
history (bounded: foldin.FeedbackHistories), and the user waits in ``pending``. The node
calls ``solve_next`` when no scene waits, one user per turn, so the ranking of others waits
for at most one solve (timings in docs/personalisation.md). The result goes into the
predictor's overlay (swapped whole) and into the state file (``user_state``), which a
restart with the same checkpoint restores.

One thread (the node's executor) calls ``Personalisation``; only its state writer's thread
reads it besides.
"""
from __future__ import annotations

import collections
import logging
from pathlib import Path
from typing import Callable

from . import messages, user_state
from .errors import StarsError
from .foldin import FeedbackHistories, FoldIn, Rating, UserModel, rating_from_feedback
from .serving import error_kind

SCENE_MEMORY = 4096  # scene requests remembered for feedback (least recently received go)


class SceneMemory:
    """The latest ``size`` scene requests by scene id: the request text and, once it is
    ranked, the predictor that ranked it and the h of its scenes (so feedback on them is
    folded in without encoding them again)."""

    def __init__(self, size: int = SCENE_MEMORY):
        self.size = size
        self._scenes = collections.OrderedDict()  # scene_id -> [text, (predictor, h) once ranked]

    def __len__(self) -> int:
        return len(self._scenes)

    def received(self, scene_id: str, text: str) -> None:
        self._scenes[scene_id] = [text, None]
        self._scenes.move_to_end(scene_id)
        if len(self._scenes) > self.size:
            self._scenes.popitem(last=False)

    def ranked(self, scene_id: str, text: str, predictor, h) -> None:
        """Keep the h [len(graphs), dim] that ranking ``text`` computed, unless a newer
        request took its scene id since."""
        remembered = self._scenes.get(scene_id)
        if remembered is not None and remembered[0] is text:
            remembered[1] = (predictor, h)

    def get(self, scene_id: str) -> tuple:
        """(request text, (predictor, h) or None); (None, None) for a scene not remembered."""
        return tuple(self._scenes.get(scene_id, (None, None)))


class Personalisation:
    """Fold-in of the users who give feedback, for the model the node serves.

    Args:
        predictor (Predictor): the model served; ``use`` replaces it on a reload.
        max_ratings (int): most recent ratings per user kept and solved from.
        max_users (int): folded-in users kept; beyond, the one who rated least recently goes.
        report (callable): ``report(kind, detail)``, called for each problem.
        logger (optional): gets ``info`` and ``warning`` lines (default: this module's logger).
        state_path (Path, optional): the state file (``user_state``); None: nothing persists.
        flush_interval (float, optional): at most one write of the state file per this many seconds.
        scene_memory (int, optional): scene requests remembered for feedback.
    """

    def __init__(self, predictor, max_ratings: int, max_users: int, report: Callable[[str, str], None],
                 logger=None, state_path: Path | None = None, flush_interval: float = 1.0,
                 scene_memory: int = SCENE_MEMORY):
        self.histories = FeedbackHistories(max_ratings, max_users)
        self.scenes = SceneMemory(scene_memory)
        self.pending = collections.OrderedDict()  # users to re-solve, longest waiting first
        self._report = report
        self._logger = logger or logging.getLogger(__name__)
        self.predictor, self.foldin = predictor, self._fold_in_model(predictor)
        self.state_path = state_path
        self._writer = None if state_path is None else user_state.StateWriter(
            state_path, self.state, flush_interval, lambda text: report('recording', text))

    def _fold_in_model(self, predictor) -> FoldIn | None:
        """The FoldIn of ``predictor``; None (and a warning) for a model without users."""
        try:
            return FoldIn(predictor)
        except StarsError as error:
            self._logger.warning(f'no online fold-in with this checkpoint: {error}')
            return None

    def use(self, predictor) -> None:
        """Serve ``predictor`` from now on (a reload). Users the new checkpoint was refit on
        keep only the feedback it did not absorb; everyone with a history left waits to be
        re-solved against the new model."""
        self.predictor, self.foldin = predictor, self._fold_in_model(predictor)
        absorbed = predictor.metadata.get('provenance', {}).get('refit', {}).get('ratings_per_user', {})
        for user_id in self.histories.absorb(absorbed):
            self.pending[user_id] = None

    # -- feedback ------------------------------------------------------------------------
    def add_feedback(self, feedback, max_bytes: int = messages.DEFAULT_MAX_BYTES) -> str | None:
        """Add the rating ``feedback`` (messages.Feedback) gives to its user's history and
        queue the user for a solve; returns instead why it cannot be folded in (the node
        reports that as ``unknown_scene``)."""
        rating = self._rating(feedback, max_bytes)
        if isinstance(rating, str):
            return rating
        self._forget(self.histories.add(feedback.user_id, rating))
        self.pending[feedback.user_id] = None
        return None

    def _rating(self, feedback, max_bytes: int) -> Rating | str:
        """The Rating ``feedback`` gives, or why it cannot be folded in."""
        text, encoded = self.scenes.get(feedback.scene_id)
        if text is None:
            return (f"feedback for scene '{feedback.scene_id}', which this node has not ranked (or no longer "
                    'remembers): recorded, not folded in')
        try:  # parsed again: it passed before, unless max_message_bytes was lowered since
            request = messages.parse_scene_request(text, max_bytes)
        except messages.BadMessage as error:
            return f"feedback for scene '{feedback.scene_id}' not folded in: its request no longer passes: {error}"
        rating = rating_from_feedback(feedback, request, self.predictor.actions)
        if not isinstance(rating, str) and encoded is not None and self.foldin is not None \
                and encoded[0] is self.foldin.predictor:  # h from ranking it: the solve need not encode
            index = request.labels.index(feedback.candidate) if request.ranks_scenes else 0
            self.foldin.remember([rating.scene], encoded[1][index:index + 1])
        return rating

    # -- the solve -----------------------------------------------------------------------
    def solve_next(self, min_ratings: int = 1, regularisation: float = 1.0) -> tuple[str, UserModel] | None:
        """Re-solve the user who has waited longest from their history against the current
        model: (user_id, the model now served for them), or None when there was nothing to
        solve (no one waiting, no fold-in with this model, fewer than ``min_ratings``)."""
        if not self.pending:
            return None
        user_id = self.pending.popitem(last=False)[0]
        foldin = self.foldin
        ratings = self.histories.ratings(user_id)
        if foldin is None or not ratings or len(ratings) < min_ratings:
            return None
        try:
            model = foldin.fit(ratings, user_id, regularisation)
        except StarsError:
            ratings = self._drop_unusable(foldin, user_id, ratings)
            if not ratings:
                return None
            model = foldin.fit(ratings, user_id, regularisation)
        self.predictor.set_user_model(user_id, model)
        self._save()
        return user_id, model

    def _drop_unusable(self, foldin: FoldIn, user_id: str, ratings: list) -> list:
        """Ratings whose scene the model cannot encode leave the history, each reported."""
        unusable = []
        for rating in ratings:
            try:
                foldin.encode([rating.scene])
            except StarsError as error:
                unusable.append(rating)
                self._report(error_kind(error), f"feedback of '{user_id}' not folded in: {error}")
        self.histories.discard(user_id, unusable)
        return self.histories.ratings(user_id)

    def _forget(self, evicted: list) -> None:
        """Users pushed out by max_users go back to the checkpoint's row."""
        for user_id in evicted:
            self.predictor.set_user_model(user_id, None)
            self._report('user_models', f"folded-in user '{user_id}' dropped: more than fold_in_max_users = "
                         f'{self.histories.max_users} users rated more recently (their feedback stays in '
                         'the MCAP log for the offline refit)')
        if evicted:
            self._save()

    # -- the state file ------------------------------------------------------------------
    def state(self) -> dict:
        """The state file's content: every folded-in user, model and history."""
        histories = self.histories.snapshot()
        predictor = self.predictor
        return user_state.to_dict(predictor.fingerprint, predictor.user_models, histories)

    def restore(self) -> None:
        """Folded-in users of the last run, if they were solved against the served checkpoint."""
        try:
            state = None if self.state_path is None else user_state.load(self.state_path, self.predictor.fingerprint)
        except user_state.UserStateError as error:
            self._report('user_models', str(error))
            return
        if state is None:
            return
        evicted = set(self.histories.restore(state.histories))
        self.predictor.set_user_models({u: m for u, m in state.models.items() if u not in evicted})
        self._logger.info(f'restored {len(state.models)} folded-in users from {self.state_path}')

    def _save(self) -> None:
        if self._writer is not None:
            self._writer.request()

    def close(self) -> None:
        """Write the state file once more if an update is not on disk yet (clean shutdown)."""
        if self._writer is not None:
            self._writer.close()
