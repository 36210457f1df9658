"""The ranker's forgets and retention, without ROS (docs/privacy.md): a person erased from
memory at once (``Personalisation.forget_person``, the one call that reaches every holder),
then from the state store and every bag on the erasing thread (``node.erasing``,
``recording.erasure``) while the node serves; a forget told to and taken from fleet peers
(``fleet_forget``); the retention pass that erases what is older than ``retention_days``.
``RankerCore`` makes one ``Forgetting`` and hands its calls here."""
from __future__ import annotations

from typing import Callable, Mapping

from stars_ros import messages
from stars_ros.errors import StarsError
from stars_ros.node import fleet_forget
from stars_ros.node.erasing import Erase, Erasing
from stars_ros.recording import erasure

RETENTION_TIMEOUT = 600  # s a retention pass waits for the state store's erase


class Forgetting:
    """Forgets and retention of one node.

    Args:
        params (dict): the node's parameters, read at each use.
        topics (Mapping): each of ``TOPICS`` -> its resolved name.
        personalisation (Personalisation): the owner of people.
        records (NodeRecords): the node's store and recording.
        report (callable): the node's ``report(kind, detail, topic)``.
        send (callable): ``send(topic, text)`` publishes and records a message.
        logger: takes ``info`` lines.
        now (callable): ROS time in ns.
        wake (callable): called from the erasing thread when an erase is done (call ``finish_erases``).
        authenticator (optional): the feedback keys, which sign and check fleet forgets.
    """

    def __init__(self, params: dict, topics: Mapping[str, str], personalisation, records, report: Callable,
                 send: Callable[[str, str], None], logger, now: Callable[[], int], wake: Callable[[], None],
                 authenticator=None):
        self.params, self.topics = params, topics
        self.personalisation, self.records = personalisation, records
        self._report, self._send, self.logger, self._now, self._wake = report, send, logger, now, wake
        self.authenticator = authenticator
        self._erasing = None  # node.erasing's thread, started by the first erase

    def begin_forget(self, user_id: str, tell_fleet: bool = True,
                     then: Callable[[dict | None, BaseException | None], None] | None = None) -> Erase | None:
        """Erase ``user_id`` everywhere this node keeps them (docs/privacy.md): now, the
        intent record and memory (``Personalisation.forget_person``; from here their feedback
        and peers' models of them are refused and no message naming them is recorded); then,
        on the erasing thread while the node serves, the state store and every bag of the
        record folder (``recording.erasure.forget``), leaving a tombstone. When that is done,
        the next ``finish_erases`` drops their models waiting to go out, tells peers with fleet
        sharing and ``tell_fleet`` (``fleet_forget``), and calls ``then(removed, error)``:
        {place: {what: removed}}, or the OSError / StoreError / TimeoutError that stopped it
        (a re-run, or the next start, finishes it). Returns the erase (None without a record
        folder: all done now). ValueError for an empty id, OSError when the intent record
        cannot be written: nothing is forgotten then."""
        if not user_id:
            raise ValueError('user_id is empty: an empty id names nobody')
        folder = self.records.folder
        if folder is not None:
            erasure.record_intent(folder, user_id)
        removed = {'memory': self.personalisation.forget_person(user_id)}
        then = then or self._report_failed_forget
        if folder is None:
            self._forget_finished(user_id, tell_fleet, removed, then, {}, None)
            return None
        self.personalisation.erase_begins(user_id)
        recorder, erase_stored = self.records.recorder, self.personalisation.erase_stored
        return self._erase_in_background(
            lambda: erasure.forget(folder, user_id, erase_stored, recorder, in_child=True),
            lambda result, error: self._forget_finished(user_id, tell_fleet, removed, then, result, error))

    def forget_person(self, user_id: str, tell_fleet: bool = True) -> dict:
        """``begin_forget``, waited for: what it removed where (its errors raised)."""
        outcome = {}
        erase = self.begin_forget(user_id, tell_fleet, lambda removed, error: outcome.update(removed=removed,
                                                                                             error=error))
        if erase is not None:
            erase.done.wait()
            self.finish_erases()
        if outcome['error'] is not None:
            raise outcome['error']
        return outcome['removed']

    def _forget_finished(self, user_id: str, tell_fleet: bool, removed: dict, then: Callable, result, error):
        """The executor's end of a forget (``begin_forget``): models committed before the
        erase (whose commit it waited for), not sent yet, are never sent now."""
        dropped = self.personalisation.erase_ends(user_id)
        if error is not None:
            then(None, error)
            return
        removed['memory']['models_to_send'] = dropped
        removed.update(result)
        if tell_fleet and self.params['fleet_sharing']:
            self._tell_fleet_forgotten(user_id)
        then(removed, None)

    def _report_failed_forget(self, removed: dict | None, error: BaseException | None) -> None:
        if error is not None:  # the intent record stays: the next start finishes it
            self._report('recording', f'a forget could not finish (the next start finishes it): {error}',
                         self.topics['stars/forget_person'])

    def _erase_in_background(self, run: Callable[[], dict], then: Callable) -> Erase:
        """``run()`` on the erasing thread (``node.erasing``), then ``then(result, error)`` at a
        ``finish_erases``."""
        if self._erasing is None:
            self._erasing = Erasing(self._wake)
        return self._erasing.submit(Erase(run, then))

    def finish_erases(self) -> None:
        """Run the executor's end of every erase the erasing thread has done."""
        if self._erasing is not None:
            for erase in self._erasing.finished():
                erase.then(erase.result, erase.error)

    def finish_interrupted(self) -> None:
        """Finish the forgets a kill interrupted (their intent records in the record folder)."""
        if self.records.folder is not None and erasure.interrupted(self.records.folder):
            finished = erasure.finish_interrupted(self.records.folder, self.personalisation.erase_stored,
                                                  self.records.recorder)
            self.logger.info(f'finished {len(finished)} forget(s) a kill had interrupted')

    def close(self, wait: float) -> bool:
        """Wait up to ``wait`` s for an erase that runs; False when one still does."""
        return self._erasing is None or self._erasing.close(wait)

    # -- fleet forget ------------------------------------------------------------------------
    def _tell_fleet_forgotten(self, user_id: str) -> None:
        """Send peers the stars/forget_person message of ``user_id`` (no id in it), and record it."""
        self._send('stars/forget_person', messages.dumps(fleet_forget.forget_message(
            user_id, self.personalisation.origin, self.authenticator, self._now())))

    def accept_forget_message(self, text: str) -> int:
        """A peer's stars/forget_person message (fleet sharing): everyone this node holds
        whom it names is forgotten here through ``begin_forget`` (not told again), and its
        tag is kept as a tombstone, so their models and feedback are refused from now on;
        how many were forgotten. A bad or unsigned one (with feedback keys) is reported
        and changes nothing; this node's own is ignored."""
        topic = self.topics['stars/forget_person']
        try:
            payload = fleet_forget.parse_forget_message(text, self.params['max_message_bytes'],
                                                        self.authenticator)
        except messages.BadMessage as error:
            self._report(error.kind, f'{error}; nobody forgotten', topic)
            return 0
        if payload['origin'] == self.personalisation.origin:
            return 0
        named = fleet_forget.named_in(payload, self.personalisation.known_people(), self.authenticator)
        self.personalisation.keep_fleet_tombstone(fleet_forget.tombstone_of(payload, self.authenticator))
        for user_id in named:
            try:
                self.begin_forget(user_id, tell_fleet=False)
            except OSError as error:  # the intent record could not be written: nothing forgotten yet
                self._report('recording', f"a forget from {payload['origin']} could not begin: {error}",
                             topic)
        self.logger.info(f"forget from {payload['origin']}: {len(named)} person(s) held here being "
                         'forgotten, its tombstone kept')
        return len(named)

    # -- retention ---------------------------------------------------------------------------
    def apply_retention(self, in_background: bool = False) -> dict:
        """Erase every rating older than ``retention_days`` (0: none) from memory
        and the state store (``Personalisation.apply_retention``: ``StateStore.erase_older``,
        its journal too) and the bags (``recording.erasure.erase_older``: every message
        logged before then); {place: {what: removed}}. Run at start, and by the node's timer
        with ``in_background``: the bags' part then runs on the erasing thread, after the
        forgets before it (what it removed is logged then, not returned). A disk that refuses
        is reported, and the next pass erases what this one left."""
        days = self.params['retention_days']
        if days <= 0:
            return {}
        cutoff = self._now() - int(days * 86400e9)
        removed = {}
        try:
            removed.update(self.personalisation.apply_retention(cutoff, RETENTION_TIMEOUT))
        except (OSError, StarsError, TimeoutError) as error:
            self._retention_finished(days, removed, None, error)
            return removed
        folder, recorder = self.records.folder, self.records.recorder
        if folder is None:
            self._retention_finished(days, removed, {}, None)
        elif in_background:
            self._erase_in_background(
                lambda: {'bags': erasure.erase_older(folder, cutoff, recorder)},
                lambda result, error: self._retention_finished(days, removed, result, error))
        else:
            try:
                bags = erasure.erase_older(folder, cutoff, recorder)
                self._retention_finished(days, removed, {'bags': bags}, None)
            except OSError as error:
                self._retention_finished(days, removed, None, error)
        return removed

    def _retention_finished(self, days: float, removed: dict, result: dict | None,
                            error: BaseException | None):
        removed.update(result or {})
        if error is not None:
            self._report('recording', f'retention pass not finished (the next one goes on): {error}')
        if any(any(counts.values()) for counts in removed.values()):
            self.logger.info(f'retention_days = {days:g}: erased {removed}')
