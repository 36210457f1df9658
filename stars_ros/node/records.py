"""What the ranker node keeps on disk, without ROS: the state store beside the bags (people,
their ratings and the journal of accepted feedback, ``stars_ros.state``) and the MCAP
recording, the log of record (``stars_ros.recording``). Each has its own thread, so the
disk never holds up the rankings; feedback reaches the bag once the store has committed it."""
from __future__ import annotations

import json
from typing import Callable, Mapping

from stars_ros import recording
from stars_ros.errors import StoreError
from stars_ros.node.parameters import topic_qos
from stars_ros.state import StateStore

DISK_FAILING = '; ranking goes on, feedback is kept in memory until the disk works'


class NodeRecords:
    """The store and the recording of one node in ``params['record_folder']`` (neither
    when it is empty).

    Args:
        params (dict): the node's parameter values (``node.parameters.PARAMETERS``).
        topics (Mapping): each of ``TOPICS`` -> its resolved name, as the bag names it.
        node_name (str): the node's fully qualified name (its folder, the bag's metadata).
        custom (dict): more of the bag's metadata (the checkpoint served, its fingerprint).
        report (callable): ``report(kind, detail)`` of a disk problem (stars/errors).
        logger: takes ``info`` and ``warning`` lines.
        now (callable): ROS time in ns, which messages are logged at.
        markers_type (optional): the ``recording.MessageType`` of stars/markers, None when
            the node publishes no markers.
    """

    def __init__(self, params: dict, topics: Mapping[str, str], node_name: str, custom: dict,
                 report: Callable[[str, str], None], logger, now: Callable[[], int], markers_type=None):
        self.params, self.topics, self._report, self.logger, self._now = params, topics, report, logger, now
        folder = params['record_folder']
        self.folder = recording.node_folder(folder, node_name) if folder else None
        self.recorder = None
        self.consent = None  # node.consent.Consent: whose id may reach the bag (None: everyone's)
        self.withheld = lambda data: False  # names someone being erased (the owner's): not for the bag
        self.left_out = 0  # messages left out because they named someone being erased
        self.store = self._open_store(node_name)  # first: StoreLockedError when another node holds the folder
        self.recorder = self._start_recorder(node_name, custom, markers_type)

    @property
    def bag(self) -> str:
        """The name of the bag being written ('' when nothing is recorded)."""
        return self.recorder.name if self.recorder is not None else ''

    def _open_store(self, node_name: str):
        if self.folder is None:
            return None
        store = StateStore(self.folder, node_name, lambda text: self._report('recording', text + DISK_FAILING),
                           self.logger.info, self.params['flush_interval'], on_feedback_committed=self._committed,
                           on_progress=self.logger.info)
        for imported in store.imported:
            self.logger.info(f'imported {imported} into {store.path} (the files are kept as they were)')
        return store

    def _start_recorder(self, node_name: str, custom: dict, markers_type):
        if self.folder is None:
            self.logger.warning('record_folder is empty: scenes, rankings and feedback are not recorded')
            return None
        try:
            for bag in recording.abandoned_bags(self.folder):
                self.logger.warning(f'recovered {bag} left by a hard kill: {recording.recover(bag)}')
        except (OSError, ValueError, StoreError) as error:
            self._report('recording', f'could not recover old bags in {self.folder}: {error}')
        qos = {self.topics[topic]: recording.qos_profile(depth, latched)
               for topic, (depth, latched) in topic_qos(self.params).items()
               if topic != 'stars/markers' or markers_type is not None}
        types = {} if markers_type is None else {self.topics['stars/markers']: markers_type}
        recorder = recording.Recorder(
            self.folder, qos, rotation_bytes=self.params['rotation_bytes'],
            flush_interval=self.params['flush_interval'], custom={'node': node_name, **custom},
            on_event=self._on_recorder_event, types=types)
        if recorder.error is None:
            self.logger.info(f'recording to {recorder.path}')
        return recorder

    def _on_recorder_event(self, level: str, text: str):
        if level == 'error':
            self._report('recording', text + DISK_FAILING)
        else:
            self.logger.info(text)

    def record(self, topic: str, text: str, log_time: int | None = None):
        """Record ``text`` on ``topic`` (one of ``TOPICS``) at ``log_time`` (default: now),
        without the id of a person who may not be stored (``without_strangers``); nothing
        that names a person being erased."""
        if self.recorder is not None:
            text = self.without_strangers(topic, text)
            if text is not None and not self._names_someone_erased(text.encode()):
                self.recorder.write(self.topics[topic], text, self._now() if log_time is None else log_time)

    def _names_someone_erased(self, data: bytes) -> bool:
        """True (and counted) when ``data`` names a person whose erase runs (``withheld``)."""
        if self.withheld(data):
            self.left_out += 1
            return True
        return False

    def without_strangers(self, topic: str, text: str) -> str | None:
        """``text`` as the bag may keep it under store_policy 'consented': a scene request,
        ranking or question request of a person not on the consent list without its
        ``user_id``; their stars/user_id, and the warning that names them as an unknown
        user, not at all (None)."""
        consent = self.consent
        if consent is None or not consent.restricted:
            return text
        if topic == 'stars/user_id':
            return text if not text.strip() or consent.allows(text.strip()) else None
        if topic not in ('stars/scene', 'stars/ranking', 'stars/question_request', 'stars/errors'):
            return text
        try:
            payload = json.loads(text)
        except ValueError:
            return text
        if not isinstance(payload, dict):
            return text
        if topic == 'stars/errors':
            return None if payload.get('kind') == 'unknown_user' else text
        if isinstance(payload.get('user_id'), str) and not consent.allows(payload['user_id']):
            del payload['user_id']
            return json.dumps(payload, separators=(',', ':'))
        return text

    def record_markers(self, data: bytes, stamp: int):
        """Record a stars/markers array (its CDR bytes), if ``record_markers`` says so."""
        if (self.recorder is not None and self.params['record_markers']
                and not self._names_someone_erased(data)):
            self.recorder.write_encoded(self.topics['stars/markers'], data, stamp)

    def _committed(self, entry: dict):
        """Feedback the store committed (its thread): into the bag, the log of record."""
        if self.recorder is not None:
            self.recorder.write_feedback(entry['topic'], entry['data'], entry['log_time'])

    def status(self) -> tuple:
        """(what fails on disk or None, the diagnostics' values of the recording)."""
        recorder, store = self.recorder, self.store
        failure = (recorder and recorder.error) or (store and store.error)
        return failure, {'recording': 'off' if recorder is None else (failure or str(recorder.path)),
                         'feedback_not_on_disk': 0 if store is None else store.uncommitted_feedback,
                         'not_recorded_while_forgetting': self.left_out}

    def close(self, before_store_closes: Callable[[], None], before_recording_closes: Callable[[], None]):
        """``before_store_closes()`` (write what waits for the store), then close the store,
        whose commits reach the bag before the bag closes, then ``before_recording_closes()``
        (send what waited for those commits), then close the recording."""
        if self.store is not None:
            before_store_closes()
            for entry in self.store.close():
                self.logger.error(f'feedback that could not be stored: {entry}')
        before_recording_closes()
        if self.recorder is not None:
            self.recorder.close()
            self.logger.info(f'recording closed: {self.recorder.path}')
