"""The owner of people's side toward the state store (``Personalisation`` is a ``Keeping``):
what one write of a person holds, the journal of feedback that changes nobody, restoring the
people of the last run, writing the models not yet written at a clean shutdown, retention,
and the store's part of a forget. Only this class (with ``online``) calls the store's writes
of a person (test/test_rooms.py checks it)."""
from __future__ import annotations

from stars_ros.state import Forgotten, PersonUpdate


class Keeping:
    """The store-facing methods of ``online.Personalisation``, whose attributes they use."""

    def record_feedback(self, journal: tuple[dict, str] | None) -> None:
        """Journal feedback that changes nobody (not folded in)."""
        if self.store is not None and journal is not None:
            self.store.write_person(None, [journal])

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
        return PersonUpdate(user_id, self.predictor.user_model(user_id), self.predictor.fingerprint, ratings,
                            dropped, peer_ratings, solved, encoded)

    def _save(self, user_id: str, journal: tuple[dict, str] | None = None) -> None:
        """Write ``user_id`` as they are now, with the feedback entry that changed them."""
        if self.store is not None:
            feedback = [journal] if journal else []
            self.written[user_id] = self.store.write_person(self._update(user_id), feedback)
            self.unsaved.discard(user_id)

    def _forget_stored(self, user_id: str) -> None:
        self.written.pop(user_id, None)
        if self.store is not None:
            self.store.forget_person(user_id)

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
            if self.foldin is not None:
                self.foldin.forget_rows([*own, *shared])
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
        evicted = set(self.histories.restore({p.user_id: (p.ratings, p.dropped)
                                              for p in people if p.ratings}))
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
