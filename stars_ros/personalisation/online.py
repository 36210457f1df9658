"""Online personalisation for the ranker node, without ROS: which feedback becomes a rating,
the users waiting to be re-solved, the per-user solve, eviction, carrying users across a
checkpoint reload, and the scene memory that feedback is matched against.

Accepted feedback on a scene the node ranked (its request text and the h its ranking
computed, remembered in a bounded LRU map, ``SceneMemory``: strings and arrays cost the
garbage collector little, parsed JSON would cost it much more) is added to that user's
history (bounded: histories.FeedbackHistories), and the user waits in ``pending``. The node
calls ``solve_next`` when no scene waits, one user per turn, so the ranking of others waits
for at most one solve (timings in docs/personalisation.md); a person with many ratings whose
rows are not built yet (restored after a restart) has them built ``PREPARE_ROWS`` a turn. The result goes into the
predictor's overlay (swapped whole): the person's own next rankings use it at once.

This module is the one writer of a person (``stars_ros.state``): each change of a person's
ratings queues one write, with the feedback entry that brought it (one write per feedback),
which the store's own thread commits. A solved model is written with that person's next
write, and at ``flush`` (a clean shutdown); a restart with the same checkpoint serves the
stored model when it was solved from exactly the stored ratings and solves anyone else
again. ``durable_after(user)`` is the write the served model of a person was solved from:
what others see of the model waits for its commit. With fleet sharing (``fleet``), peers'
ratings join a user's own and the model is solved from the union.

One thread (the node's executor) calls ``Personalisation``.
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import os
from typing import Callable

from stars_ros.personalisation import fleet
from stars_ros import messages
from stars_ros.errors import StarsError, UnknownActionError
from stars_ros.personalisation.foldin import FoldIn, rating_from_feedback
from stars_ros.personalisation.histories import FeedbackHistories
from stars_ros.personalisation.stack import serving_stack
from stars_ros.state.forgotten import folder_secret
from stars_ros.state import Forgotten, PersonUpdate, PersonWriter, Rating, UserModel, check_ratings, mentions

SCENE_MEMORY = 4096  # scene requests remembered for feedback (least recently received go)
PREPARE_ROWS = 8  # ratings' scenes encoded per call of solve_next: bounds how long one holds the executor


class SceneMemory:
    """The latest ``size`` scene requests by scene id: the request (its text, or a typed
    request's ``messages.Twin``; ``messages.parse_scene_request`` takes either) and, once it
    is ranked, the predictor that ranked it and the h of its scenes (so feedback on them is
    folded in without encoding them again)."""

    def __init__(self, size: int = SCENE_MEMORY):
        self.size = size
        self._scenes = collections.OrderedDict()  # scene_id -> [request, (predictor, h) once ranked]

    def __len__(self) -> int:
        return len(self._scenes)

    def received(self, scene_id: str, request) -> None:
        self._scenes[scene_id] = [request, None]
        self._scenes.move_to_end(scene_id)
        if len(self._scenes) > self.size:
            self._scenes.popitem(last=False)

    def ranked(self, scene_id: str, request, predictor, h, plain=None) -> None:
        """Keep the h [len(graphs), dim] that ranking ``request`` computed (and the plain
        encoder's scores, ``Scored.plain``, where it computed them), unless a newer request took
        its scene id since."""
        remembered = self._scenes.get(scene_id)
        if remembered is not None and remembered[0] is request:
            remembered[1] = (predictor, h, plain)

    def recent(self, count: int) -> list:
        """[(scene_id, request, (predictor, h, plain) or None)] of the ``count`` latest, newest first."""
        latest = []
        for scene_id in reversed(self._scenes):
            if len(latest) == count:
                break
            latest.append((scene_id, *self._scenes[scene_id]))
        return latest

    def get(self, scene_id: str) -> tuple:
        """(request, (predictor, h, plain) or None); (None, None) for a scene not remembered."""
        return tuple(self._scenes.get(scene_id, (None, None)))

    def forget(self, named: Callable[[bytes], bool]) -> int:
        """Let go of the requests whose text ``named`` finds a person in; how many."""
        gone = [scene_id for scene_id, (request, _) in self._scenes.items()
                if named(messages.text_of(request).encode('utf-8'))]
        for scene_id in gone:
            del self._scenes[scene_id]
        return len(gone)


@dataclasses.dataclass
class PeerIntake:
    """New ratings of one peer message, checked one scene per executor turn: ``encoded`` of
    them so far."""

    user_id: str
    peer: str
    ratings: list
    encoded: int = 0


class Personalisation:
    """Fold-in of the users who give feedback, for the model the node serves.

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
    """

    def __init__(self, predictor, max_ratings: int, max_users: int, report: Callable[[str, str], None],
                 logger=None, store: PersonWriter | None = None, scene_memory: int = SCENE_MEMORY, origin: str = '',
                 sharing: bool = False, authenticator=None, after_person_read: Callable[[], None] | None = None):
        self.histories = FeedbackHistories(max_ratings, max_users)
        self.peers = fleet.PeerRatings(max_ratings, max_users)
        if after_person_read is not None:
            self.histories.after_read = self.peers.after_read = after_person_read
        self.origin, self.sharing, self.authenticator = origin, sharing, authenticator
        self.scenes = SceneMemory(scene_memory)
        self.pending = collections.OrderedDict()  # users to re-solve, longest waiting first
        self.to_announce = collections.OrderedDict()  # users whose model peers are to be sent again
        self.intake = collections.deque()  # PeerIntake: peers' ratings being checked, oldest first
        self.solved_from = {}  # user -> the ratings their served model was solved from
        self.written = {}  # user -> sequence number of their latest write to the store
        self.unsaved = set()  # users whose served model the store does not hold yet
        self.forgotten = self._with_fleet_keys(Forgotten(None))  # the tombstones of people erased (the store's,
        # once restored)
        self._report = report
        self._logger = logger or logging.getLogger(__name__)
        self.store = store
        self.predictor, self.foldin, self.uncertainty = self._serving_stack(predictor)

    def _serving_stack(self, predictor) -> tuple:
        """(predictor, fold-in, uncertainty) of ``predictor`` (``stack.serving_stack``), the fold-in
        reading the h of restored people's scenes from the store (not with fleet sharing, which
        encodes each scene on its own so that peers' models agree to the last bit); no fold-in
        nor uncertainty (and a warning) for a model without users."""
        from_store = self.store is not None and not self.sharing
        stack = serving_stack(predictor, scene_by_scene=self.sharing, stored=(
            lambda scenes: self.store.encodings(scenes, predictor.fingerprint)) if from_store else None)
        if stack.foldin is None:
            self._logger.warning(f'no online fold-in with this checkpoint: {stack.no_foldin}')
        return stack.predictor, stack.foldin, stack.uncertainty

    def use(self, predictor) -> None:
        """Serve ``predictor`` from now on (a reload). Users the new checkpoint was refit on
        keep only the feedback it did not absorb; everyone with a history left waits to be
        re-solved against the new model."""
        self.predictor, self.foldin, self.uncertainty = self._serving_stack(predictor)
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

    def record_feedback(self, journal: tuple[dict, str] | None) -> None:
        """Journal feedback that changes nobody (not folded in)."""
        if self.store is not None and journal is not None:
            self.store.write_person(None, [journal])

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

    # -- the state store ---------------------------------------------------------------
    def _update(self, user_id: str) -> PersonUpdate:
        """What the store is to hold of ``user_id`` now: ``solved`` when their served model
        was solved from exactly their ratings as they are."""
        ratings, dropped = self.histories.ratings(user_id), self.histories.dropped(user_id)
        solved_from = self.solved_from.get(user_id)
        solved = solved_from is not None and [r.rating_id for r in solved_from] == [
            r.rating_id for r in self.ratings(user_id)]
        peer_ratings = self.peers.ratings(user_id)
        encoded = None if self.foldin is None or self.sharing else self.foldin.take_encodings(
            [r.scene for r in (*ratings, *peer_ratings)])
        return PersonUpdate(user_id, self.predictor.user_model(user_id), self.predictor.fingerprint, ratings, dropped,
                            peer_ratings, solved, encoded)

    def _save(self, user_id: str, journal: tuple[dict, str] | None = None) -> None:
        """Write ``user_id`` as they are now, with the feedback entry that changed them."""
        if self.store is not None:
            self.written[user_id] = self.store.write_person(self._update(user_id), [journal] if journal else [])
            self.unsaved.discard(user_id)

    def _forget_stored(self, user_id: str) -> None:
        self.written.pop(user_id, None)
        if self.store is not None:
            self.store.forget_person(user_id)

    def forget_person(self, user_id: str) -> dict:
        """Erase ``user_id`` from memory (history, peers' ratings, served model, what waits
        to be solved, written or announced, peers' ratings being checked, the scene requests
        that name them) and mark them forgotten, so their feedback and peers' models of them
        are refused from now on; {what: entries removed}. The store's and the bags' part is
        ``recording.erasure.forget``'s, which the caller runs next with ``erase_stored``."""
        intake = [staged for staged in self.intake if staged.user_id == user_id]
        removed = {'ratings': self.histories.drop(user_id), 'peer_ratings': len(self.peers.ratings(user_id)),
                   'model': int(self.predictor.user_model(user_id) is not None),
                   'scene_requests': self.scenes.forget(mentions(user_id)), 'peer_messages_in_intake': len(intake),
                   'replay_memory': 0 if self.authenticator is None else self.authenticator.forget_person(user_id)}
        self.peers.drop(user_id)
        self.predictor.set_user_model(user_id, None)
        for kept in (self.pending, self.to_announce, self.solved_from, self.written):
            kept.pop(user_id, None)
        self.unsaved.discard(user_id)
        for staged in intake:
            self.intake.remove(staged)
        if self.forgotten.secret is None and self.store is not None:
            self.forgotten = self._with_fleet_keys(Forgotten(folder_secret(self.store.folder, create=True),
                                                             self.forgotten.tags))
        if self.forgotten.secret is None:  # nothing recorded: remembered in memory only, with a secret of this run
            self.forgotten = self._with_fleet_keys(Forgotten(os.urandom(32), self.forgotten.tags))
        self.forgotten.add(user_id)
        return removed

    def erase_stored(self, user_id: str, timeout: float = 600) -> dict:
        """Erase ``user_id`` from the state store, their tombstone kept (``StateStore.erase_person``):
        {table: rows removed}, once committed; {} with nothing recorded."""
        return {} if self.store is None else self.store.erase_person(user_id).result(timeout)

    def _with_fleet_keys(self, forgotten: Forgotten) -> Forgotten:
        """``forgotten`` checking fleet tombstones with the feedback keys (``state.forgotten``)."""
        forgotten.fleet_keys = {} if self.authenticator is None else dict(self.authenticator.keys)
        return forgotten

    def keep_fleet_tombstone(self, kept: str) -> None:
        """A fleet peer forgot someone (``forgotten.fleet_tombstone``): refused here from now
        on, and after a restart when the store keeps it."""
        self.forgotten.tags.add(kept)
        if self.store is not None:
            self.store.keep_tombstone(kept)

    def known_people(self) -> set:
        """Every id this node holds something of in memory: histories, peers' ratings,
        served models, what waits."""
        return {*self.histories.users(), *self.peers.users(), *self.predictor.user_models, *self.pending,
                *(staged.user_id for staged in self.intake)}

    def apply_retention(self, cutoff: int, timeout: float) -> dict:
        """Retention (``retention_days``): every rating, own or a peer's, stamped before
        ``cutoff`` (ROS time, ns) leaves memory; a person left with some is re-solved and
        written as they are now, one left with none goes back to the checkpoint. Every
        person held is read (a Deferred one too). Then the store erases what is older still
        (``StateStore.erase_older``, its journal too; waited for up to ``timeout`` s).
        {'memory': {what: entries removed}, 'state_store': {table: rows removed}}."""
        removed = {'ratings': 0, 'peer_ratings': 0, 'people': 0}
        for user_id in {*self.histories.users(), *self.peers.users()}:
            own = [r for r in self.histories.ratings(user_id) if r.stamp < cutoff]
            shared = [r for r in self.peers.ratings(user_id) if r.stamp < cutoff]
            if not own and not shared:
                continue
            removed['ratings'] += len(own)
            removed['peer_ratings'] += len(shared)
            self.histories.discard(user_id, own)
            self.peers.discard(user_id, shared)
            if self.histories.ratings(user_id) or self.peers.ratings(user_id):
                self.solved_from.pop(user_id, None)
                self.pending[user_id] = None
                self._save(user_id)
                continue
            removed['people'] += 1
            self.histories.drop(user_id)
            self.peers.drop(user_id)
            self.predictor.set_user_model(user_id, None)
            for kept in (self.pending, self.to_announce, self.solved_from):
                kept.pop(user_id, None)
            self.unsaved.discard(user_id)
            self._forget_stored(user_id)
        if self.store is None:
            return {'memory': removed}
        return {'memory': removed, 'state_store': self.store.erase_older(cutoff).result(timeout)}

    def durable_after(self, user_id: str) -> int:
        """The store's write that ``user_id``'s served model waits for before anyone else may
        see it: the latest write of their ratings (0: nothing in flight)."""
        return self.written.get(user_id, 0)

    def flush(self) -> None:
        """Write every served model the store does not hold yet (a clean shutdown), so that
        the restart serves them without solving again."""
        for user_id in list(self.unsaved):
            if user_id in self.histories or user_id in self.peers:
                self._save(user_id)
        self.unsaved.clear()

    def restore(self) -> None:
        """Folded-in users of the last run, if they were solved against the served
        checkpoint: their models now, their ratings read when first used. A stored model
        solved from the ratings stored with it is served as it was (mean and covariance);
        anyone else waits to be solved again."""
        if self.store is None:
            return
        self.forgotten = self._with_fleet_keys(self.store.forgotten())
        people, problem = self.store.load(self.predictor.fingerprint)
        if problem is not None:
            self._report('user_models', problem)
        if not people:
            return
        evicted = set(self.histories.restore({p.user_id: (p.ratings, p.dropped) for p in people if p.ratings}))
        if self.authenticator is not None:  # a replay across a restart is still a replay
            self.authenticator.remember(self.store.signed_feedback())
        evicted.update(self.peers.restore({p.user_id: p.peer_ratings for p in people if p.peer_ratings}))
        current = self.predictor.fingerprint
        restored = {p.user_id: p.model for p in people
                    if p.user_id not in evicted and p.model is not None and p.fingerprint == current}
        self.predictor.set_user_models(restored)
        self.pending.update(dict.fromkeys(p.user_id for p in people if p.user_id not in evicted and not (
            p.user_id in restored and p.solved and p.model.covariance is not None)))
        for user_id in evicted:  # beyond fold_in_max_users now: gone, as an eviction would take them
            self.peers.drop(user_id)
            self._forget_stored(user_id)
        self._logger.info(f'restored {len(restored)} folded-in users from {self.store.path}'
                          + (f' ({len(self.pending)} to solve again)' if self.pending else ''))
