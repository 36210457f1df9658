"""The ranker node: personalised rankings of robot actions (or candidate scenes) per scene.

Subscribes ``stars/scene``, ``stars/user_id`` (transient local) and ``stars/feedback``;
publishes ``stars/ranking``, ``stars/errors``, ``stars/user_model`` and ``/diagnostics``;
serves ``~/reload``. See README.md ("The ranker node") and docs/personalisation.md. Run with
``ros2 run stars_ros ranker`` or ``python -m stars_ros.ranker --ros-args -p checkpoint:=PATH``.

Threads: the executor thread does the serving. A scene callback takes every request
already waiting on stars/scene, validates and queues them (beyond ``queue_depth`` waiting
they are refused as ``overload``), and scores up to ``max_batch`` of them in one pass with
one model snapshot; a guard condition brings the executor back for the rest once other
ready callbacks (feedback, ``~/reload``, parameters) have had their turn. Handing requests
to a worker thread cost ~0.7 ms a request in waiting for the GIL while the executor went
round its wait set (README, "Benchmarks"). ``~/reload`` runs between two batches, so every
ranking is scored by exactly one checkpoint, the one whose fingerprint it carries. The
callbacks share the node's default, mutually exclusive callback group, so a
multi-threaded executor keeps this order too.

Feedback is journaled (written and fsync'd) by a thread of its own, so the disk never
holds up the rankings.

Online fold-in: accepted feedback on a scene the node ranked (its request text and the h
its ranking computed remembered in a bounded LRU map: strings and arrays cost the garbage
collector little, parsed JSON would cost it much more) is added to that user's history
(bounded: foldin.FeedbackHistories), and the executor re-solves the user's (p_u, b_u)
(stars_ros.foldin) when no scene waits, one user per turn, so the ranking of others waits
for at most one solve (0.6–1.4 ms with up to 200 ratings, docs/personalisation.md). The
result goes into the predictor's overlay (swapped whole), on stars/user_model (recorded),
and into ``user_models.json`` in the record folder (written by its own thread too), which a
restart with the same checkpoint restores.

A ranking's ``processing_ms`` counts from the middleware's reception of the request (its
message info), so a wait behind other callbacks is in it. The executor notes when it does
fold-in work; a ranking whose wait overlapped such work is counted, with that overlap, in
the next /diagnostics (``period.*``): the node itself shows what fold-in costs others.
"""
from __future__ import annotations

import collections
import gc
import json
import os
import queue
import threading
import time
from pathlib import Path

import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import InvalidHandle
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger
from threadpoolctl import threadpool_limits

from . import messages, recording, usage
from .errors import CheckpointError, StarsError
from .foldin import FeedbackHistories, FoldIn, Rating, UserModel, rating_from_feedback
from .predictor import Predictor
from .resources import share_path
from .serving import BusySpans, Pending, PeriodStats, error_kind, rank_batch
from .spinning import spin_until_shutdown

DEFAULT_CHECKPOINT = 'models/socnav1_gat_stars.pt'
WARNINGS = ('unknown_user', 'unknown_scene', 'user_models')
MAX_STRANGERS_REMEMBERED = 10000
SCENE_MEMORY = 4096  # scene requests remembered for feedback (least recently received go)
STATE_FILE = 'user_models.json'
STATE_FORMAT = "stars_ros.user_models"
_INT_MAX = 2 ** 31 - 1

PARAMETERS = {  # name: (default, description, read_only, range)
    'checkpoint': ('', f'checkpoint file; empty: the packaged {DEFAULT_CHECKPOINT}. Read again by ~/reload',
                   False, None),
    'top_k': (0, 'publish only the best k entries of each ranking; 0: all', False, (0, _INT_MAX)),
    'record_folder': (str(recording.default_folder()), 'folder for the MCAP bags and user_models.json; default '
                      '$ROS_HOME/stars_ros/records (ROS_HOME: ~/.ros unless set); empty: do not record', True, None),
    'rotation_bytes': (64 << 20, 'start a new MCAP file once one reaches this size (bytes)', True,
                       (4096, _INT_MAX)),
    'flush_interval': (1.0, 'seconds between flushes of the recording; a hard kill loses at most this',
                       True, (0.01, 3600.0)),
    'max_message_bytes': (messages.DEFAULT_MAX_BYTES, 'larger messages are refused (kind oversized)',
                          False, (1024, 64 << 20)),
    'queue_depth': (1000, 'QoS depth of stars/scene and the most requests waiting to be scored', True,
                    (1, 100000)),
    'max_batch': (16, 'most queued requests scored in one forward pass', False, (1, 1024)),
    'log_throttle': (5.0, 'seconds between two log lines about the same kind of error', False,
                     (0.0, 3600.0)),
    'diagnostics_period': (1.0, 'seconds between two /diagnostics messages', True, (0.05, 3600.0)),
    'fold_in': (True, "personalise from feedback: re-solve the user's embedding after each rating", False, None),
    'fold_in_min_ratings': (1, 'ratings a user needs before their folded-in embedding is served', False,
                            (1, 100000)),
    'fold_in_max_ratings': (200, "most recent ratings per user the fold-in is solved from (and the state file "
                            'keeps); older ones stay in the MCAP log for the offline refit', True, (1, 1000000)),
    'fold_in_max_users': (1000, 'folded-in users kept; beyond this the one who rated least recently goes back to '
                          'the checkpoint (their feedback stays in the MCAP log)', True, (1, 10000000)),
    'fold_in_regularisation': (1.0, 'ridge weight λ pulling a folded-in user towards the prior '
                               '(their trained row, else the population mean)', False, (1e-6, 1e6)),
}


def _descriptor(name: str) -> ParameterDescriptor:
    default, description, read_only, limits = PARAMETERS[name]
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    if isinstance(default, int) and limits:
        descriptor.integer_range = [IntegerRange(from_value=limits[0], to_value=limits[1], step=1)]
    elif isinstance(default, float) and limits:
        descriptor.floating_point_range = [FloatingPointRange(from_value=limits[0], to_value=limits[1])]
    return descriptor


def resolve_checkpoint(value: str) -> str:
    """The checkpoint parameter as a path: the packaged default when it is empty."""
    if value:
        return value
    try:
        return str(share_path(DEFAULT_CHECKPOINT))
    except FileNotFoundError as error:
        raise CheckpointError(f'no checkpoint given and the packaged default is missing ({error}); '
                              'pass --ros-args -p checkpoint:=PATH') from None


class RankerNode(Node):
    """Serves rankings from a StARS checkpoint; see the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('ranker', **kwargs)
        self.params = {name: self.declare_parameter(name, spec[0], _descriptor(name)).value
                       for name, spec in PARAMETERS.items()}
        self.add_on_set_parameters_callback(self._on_set_parameters)
        torch.set_num_threads(1)
        # numpy's OpenBLAS spreads products above ~0.26 M multiply-adds (a fold-in solve over
        # 200 ratings, a batch of scenes) over every core, and its idle workers then spin on the
        # cores the executor, the DDS threads and the node's neighbours need
        threadpool_limits(1, user_api='blas')
        path = resolve_checkpoint(self.params['checkpoint'])
        self.predictor = Predictor.load(path)
        self.checkpoint_path = path
        self.get_logger().info(f'serving {path} (fingerprint {self.predictor.fingerprint[:12]}, '
                               f'actions {list(self.predictor.actions)})')

        self._user_id = None
        self._lock = threading.Lock()
        self._counts = collections.Counter()
        self._strangers_reported = set()
        self._period = {}  # kind -> (count, last detail) since the last diagnostics
        self._last_log = {}
        self._queue = collections.deque()  # Pending requests (executor thread only)
        # scene_id -> [request text, (predictor, h of its scenes) once ranked]; executor thread only
        self._scenes = collections.OrderedDict()
        self._histories = FeedbackHistories(self.params['fold_in_max_ratings'], self.params['fold_in_max_users'])
        self._fold_pending = collections.OrderedDict()  # users to re-solve (executor thread only)
        self._foldin = self._fold_in_model(self.predictor)
        self._fold_in_spans = BusySpans()  # when the executor did fold-in work (time.time_ns; executor thread only)
        self._period_stats = PeriodStats()  # for the next /diagnostics (executor thread only)

        depth = self.params['queue_depth']
        reliable = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.ranking_pub = self.create_publisher(String, 'stars/ranking', reliable)
        self.error_pub = self.create_publisher(String, 'stars/errors', 100)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.user_model_pub = self.create_publisher(String, 'stars/user_model', reliable)
        self.topics = {name: self.resolve_topic_name(name) for name in
                       ('stars/scene', 'stars/user_id', 'stars/feedback', 'stars/ranking', 'stars/errors',
                        'stars/user_model')}
        self.recorder = None
        self.recorder = self._start_recorder(depth)
        self.state_path = Path(self.params['record_folder']).expanduser() / STATE_FILE \
            if self.params['record_folder'] else None
        self._restore_user_models()
        self._scene_subscription = self.create_subscription(String, 'stars/scene', self._on_scene, reliable)
        self.create_subscription(String, 'stars/user_id', self._on_user_id, latched)
        self.create_subscription(String, 'stars/feedback', self._on_feedback, 100)
        self.create_service(Trigger, '~/reload', self._on_reload)
        self.create_timer(self.params['diagnostics_period'], self._publish_diagnostics)
        self._more_work = self.create_guard_condition(self._work)
        self._save_wanted = threading.Event()  # the state file is written by its own thread,
        self._closing = threading.Event()
        self._rating_texts = {}  # id(Rating) -> (Rating, its JSON); the state writer's cache
        self._saver = threading.Thread(target=self._save_loop, name='stars-ranker-state', daemon=True)
        self._saver.start()  # so an fsync never holds up serving
        self._to_journal = queue.SimpleQueue()  # accepted feedback on its way to the recorder's journal
        self._journal_thread = threading.Thread(target=self._journal_loop, name='stars-ranker-journal', daemon=True)
        self._journal_thread.start()

    # -- parameters ----------------------------------------------------------------------
    def _on_set_parameters(self, changed) -> SetParametersResult:
        for parameter in changed:
            if parameter.name not in PARAMETERS:
                continue
            default, _, _, limits = PARAMETERS[parameter.name]
            value = parameter.value
            if type(value) is not type(default):
                return SetParametersResult(successful=False,
                                           reason=f'{parameter.name} must be a {type(default).__name__}')
            if limits and not limits[0] <= value <= limits[1]:
                return SetParametersResult(successful=False,
                                           reason=f'{parameter.name} must be within {limits[0]}..{limits[1]}')
        for parameter in changed:
            if parameter.name in PARAMETERS:
                self.params[parameter.name] = parameter.value
        return SetParametersResult(successful=True)

    # -- recording -----------------------------------------------------------------------
    def _start_recorder(self, depth: int):
        folder = self.params['record_folder']
        if not folder:
            self.get_logger().warning('record_folder is empty: scenes, rankings and feedback are not recorded')
            return None
        try:
            for bag in recording.abandoned_bags(folder):
                self.get_logger().warning(f'recovered {bag} left by a hard kill: {recording.recover(bag)}')
        except (OSError, ValueError) as error:
            self.report('recording', f'could not recover old bags in {folder}: {error}')
        qos = {self.topics[t]: recording.qos_profile(depth) for t in ('stars/scene', 'stars/ranking')}
        qos[self.topics['stars/user_id']] = recording.qos_profile(1, transient_local=True)
        qos[self.topics['stars/feedback']] = recording.qos_profile(100)
        qos[self.topics['stars/errors']] = recording.qos_profile(100)
        qos[self.topics['stars/user_model']] = recording.qos_profile(depth)
        recorder = recording.Recorder(
            folder, qos, rotation_bytes=self.params['rotation_bytes'], flush_interval=self.params['flush_interval'],
            custom={'node': self.get_fully_qualified_name(), 'checkpoint': self.checkpoint_path,
                    'fingerprint': self.predictor.fingerprint},
            on_event=self._on_recorder_event)
        if recorder.error is None:
            self.get_logger().info(f'recording to {recorder.path}')
        return recorder

    def _on_recorder_event(self, level: str, text: str):
        if level == 'error':
            self.report('recording', text + '; ranking goes on, feedback is kept in memory until the disk works')
        else:
            self.get_logger().info(text)

    def _record(self, topic: str, text: str, log_time: int | None = None):
        """Record ``text`` on ``topic`` at ``log_time`` (ns of ROS time; default: now)."""
        if self.recorder is not None:
            self.recorder.write(self.topics[topic], text,
                                self.get_clock().now().nanoseconds if log_time is None else log_time)

    # -- errors and diagnostics ----------------------------------------------------------
    def report(self, kind: str, detail: str, topic: str = '', scene_id: str | None = None):
        """Count, publish on stars/errors, log (throttled per kind) and record one problem."""
        now = time.monotonic()
        with self._lock:
            self._counts[kind] += 1
            count = self._period.get(kind, (0, ''))[0] + 1
            self._period[kind] = (count, detail)
            log = now - self._last_log.get(kind, -1e9) >= self.params['log_throttle']
            if log:
                self._last_log[kind] = now
        payload = messages.dumps({'kind': kind, 'message': detail, 'topic': topic, 'scene_id': scene_id,
                                  'level': 'warning' if kind in WARNINGS else 'error'})
        try:
            self.error_pub.publish(String(data=payload))
        except (InvalidHandle, _rclpy.RCLError):  # shutting down (a thread of close()): logged and recorded
            pass
        self._record('stars/errors', payload)
        if log:
            line = (f'[{kind}] {detail} (total {self._counts[kind]}; repeats are logged at most every '
                    f"{self.params['log_throttle']} s)")
            if kind in WARNINGS:  # rclpy fixes one severity per call site
                self.get_logger().warning(line)
            else:
                self.get_logger().error(line)

    def _publish_diagnostics(self):
        with self._lock:
            period, self._period = self._period, {}
            counts = dict(self._counts)
        name = self.get_fully_qualified_name()
        recorder = self.recorder
        errors = {k for k in period if k not in WARNINGS}
        level = DiagnosticStatus.ERROR if errors or (recorder and recorder.error) else (
            DiagnosticStatus.WARN if period else DiagnosticStatus.OK)
        summary = 'serving' if not period else 'serving; problems since last report: ' + ', '.join(
            f'{k} x{n}' for k, (n, _) in sorted(period.items()))
        values = {'checkpoint': self.checkpoint_path, 'fingerprint': self.predictor.fingerprint,
                  'rankings': counts.get('ranking', 0), 'queued': len(self._queue),
                  'recording': 'off' if recorder is None else (recorder.error or str(recorder.path)),
                  'feedback_not_on_disk': 0 if recorder is None else
                  recorder.pending_feedback + self._to_journal.qsize(),
                  'folded_in_users': len(self.predictor.user_models)}
        values.update(self._period_stats.values())
        self._period_stats = PeriodStats()
        values.update({f'errors.{k}': n for k, n in sorted(counts.items()) if k != 'ranking'})
        statuses = [DiagnosticStatus(level=level, name=f'{name}: ranker', message=summary, hardware_id=name,
                                     values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]
        for kind, (count, detail) in sorted(period.items()):
            statuses.append(DiagnosticStatus(
                level=DiagnosticStatus.WARN if kind in WARNINGS else DiagnosticStatus.ERROR,
                name=f'{name}: {kind}', message=detail, hardware_id=name,
                values=[KeyValue(key='count', value=str(count))]))
        array = DiagnosticArray(status=statuses)
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(array)

    # -- callbacks (executor thread) -----------------------------------------------------
    def _on_scene(self, msg: String, info: dict):
        """Queue this request and those already waiting behind it (at most queue_depth per
        call, so a flood cannot keep the executor from serving), then serve a batch."""
        self._accept_scene(msg.data, info)
        for _ in range(self.params['queue_depth']):
            taken = self._take_waiting_scene()
            if taken is None:
                break
            self._accept_scene(taken[0].data, taken[1])
        self._work()

    def _take_waiting_scene(self) -> tuple | None:
        """The next message waiting on stars/scene and its message info, taken as the
        executor takes them (None: none)."""
        subscription = self._scene_subscription
        with subscription.handle:
            return subscription.handle.take_message(subscription.msg_type, subscription.raw)

    def _accept_scene(self, text: str, info: dict):
        received = info.get('received_timestamp') or time.time_ns()  # 0: the middleware does not stamp
        try:
            request = messages.parse_scene_request(text, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            self.report(error.kind, str(error), self.topics['stars/scene'], error.scene_id)
            return
        log_time = self.get_clock().now().nanoseconds
        self._scenes[request.scene_id] = [text, None]
        self._scenes.move_to_end(request.scene_id)
        if len(self._scenes) > SCENE_MEMORY:
            self._scenes.popitem(last=False)
        if len(self._queue) >= self.params['queue_depth']:
            self._record('stars/scene', text, log_time)
            self.report('overload', f"{self.params['queue_depth']} requests already wait to be scored; "
                        'this one is dropped', self.topics['stars/scene'], request.scene_id)
            return
        self._queue.append(Pending(request, request.user_id or self._user_id, received, text, log_time))

    def _on_user_id(self, msg: String):
        try:
            self._user_id = messages.parse_user_id(msg.data)
        except messages.BadMessage as error:
            self.report(error.kind, str(error), self.topics['stars/user_id'])
            return
        self._record('stars/user_id', msg.data)

    def _on_feedback(self, msg: String):
        topic = self.topics['stars/feedback']
        try:
            feedback = messages.parse_feedback(msg.data, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            self.report(error.kind, str(error), topic, error.scene_id)
            return
        if feedback.action is not None and feedback.action not in self.predictor.actions:
            self.report('unknown_action', f"feedback for unknown action '{feedback.action}'; this model knows "
                        f'{list(self.predictor.actions)}', topic, feedback.scene_id)
            return
        if self.recorder is None:
            self.report('recording', 'feedback accepted but record_folder is empty: it is not stored', topic,
                        feedback.scene_id)
        else:
            self._to_journal.put((topic, msg.data, self.get_clock().now().nanoseconds, feedback.scene_id))
        if self.params['fold_in']:
            started = time.time_ns()
            self._queue_fold_in(feedback, topic)
            self._fold_in_spans.add(started, time.time_ns())

    # -- fold-in -------------------------------------------------------------------------
    def _rating(self, feedback) -> Rating | str:
        """The Rating ``feedback`` gives, or why it cannot be folded in."""
        text, encoded = self._scenes.get(feedback.scene_id, (None, None))
        if text is None:
            return (f"feedback for scene '{feedback.scene_id}', which this node has not ranked (or no longer "
                    'remembers): recorded, not folded in')
        try:  # parsed again: it passed before, unless max_message_bytes was lowered since
            request = messages.parse_scene_request(text, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            return f"feedback for scene '{feedback.scene_id}' not folded in: its request no longer passes: {error}"
        rating = rating_from_feedback(feedback, request, self.predictor.actions)
        if not isinstance(rating, str) and encoded is not None and self._foldin is not None \
                and encoded[0] is self._foldin.predictor:  # h from ranking it: the solve need not encode
            index = request.labels.index(feedback.candidate) if request.ranks_scenes else 0
            self._foldin.remember([rating.scene], encoded[1][index:index + 1])
        return rating

    def _queue_fold_in(self, feedback, topic: str):
        rating = self._rating(feedback)
        if isinstance(rating, str):
            self.report('unknown_scene', rating, topic, feedback.scene_id)
            return
        self._forget(self._histories.add(feedback.user_id, rating))
        self._fold_pending[feedback.user_id] = None
        self._more_work.trigger()

    def _fold_in(self, user_id: str):
        """Re-solve ``user_id`` from their history against the current model."""
        predictor, foldin = self.predictor, self._foldin
        if foldin is None:
            return
        ratings = self._histories.ratings(user_id)
        if not ratings or len(ratings) < self.params['fold_in_min_ratings']:
            return
        try:
            model = foldin.fit(ratings, user_id, self.params['fold_in_regularisation'])
        except StarsError:
            ratings = self._drop_unusable(foldin, user_id, ratings)
            if not ratings:
                return
            model = foldin.fit(ratings, user_id, self.params['fold_in_regularisation'])
        predictor.set_user_model(user_id, model)
        payload = messages.dumps(messages.user_model_payload(user_id, model, predictor.fingerprint))
        self.user_model_pub.publish(String(data=payload))
        self._record('stars/user_model', payload)
        self._save_wanted.set()

    def _fold_in_model(self, predictor):
        """The FoldIn of ``predictor``; None (and a warning) for a model without users."""
        try:
            foldin = FoldIn(predictor)
        except StarsError as error:
            self.get_logger().warning(f'no online fold-in with this checkpoint: {error}')
            return None
        return foldin

    def _drop_unusable(self, foldin, user_id: str, ratings: list) -> list:
        """Ratings whose scene the model cannot encode leave the history, each reported."""
        unusable = []
        for rating in ratings:
            try:
                foldin.encode([rating.scene])
            except StarsError as error:
                unusable.append(rating)
                self.report(error_kind(error), f"feedback of '{user_id}' not folded in: {error}")
        self._histories.discard(user_id, unusable)
        return self._histories.ratings(user_id)

    def _forget(self, evicted: list):
        """Users pushed out by fold_in_max_users go back to the checkpoint's row."""
        for user_id in evicted:
            self.predictor.set_user_model(user_id, None)
            self.report('user_models', f"folded-in user '{user_id}' dropped: more than fold_in_max_users = "
                        f"{self.params['fold_in_max_users']} users rated more recently (their feedback stays in "
                        'the MCAP log for the offline refit)')
        if evicted:
            self._save_wanted.set()

    def _journal_loop(self):
        """Feedback into the recorder's journal (written and fsync'd) from a thread of its own:
        an fsync takes 0.4–6 ms on this machine's disk, and every ranking queued behind it in
        the executor thread would wait that long."""
        while (item := self._to_journal.get()) is not None:
            topic, text, log_time, scene_id = item
            if not self.recorder.write_feedback(topic, text, log_time):
                self.report('recording', 'feedback could not be written yet; kept in memory and retried', topic,
                            scene_id)

    def _save_loop(self):
        """Write the state file when asked, at most once per flush_interval: a hard kill loses
        at most that much, as for the recording, and a stream of feedback costs one JSON dump
        per interval, not one per rating."""
        while True:
            self._save_wanted.wait()
            if self._closing.is_set():
                return
            self._save_wanted.clear()
            self._save_user_models(self.predictor)
            self._closing.wait(self.params['flush_interval'])

    def _save_user_models(self, predictor):
        """Write every folded-in user (model and history) to the state file, atomically."""
        if self.state_path is None:
            return
        histories = self._histories.snapshot()
        known, self._rating_texts = self._rating_texts, {}
        users = []
        for user_id, model in predictor.user_models.items():
            ratings = []
            ratings_of_user, dropped = histories.get(user_id, ((), 0))
            for rating in ratings_of_user:
                kept = known.get(id(rating))
                if kept is None or kept[0] is not rating:  # each rating is serialised once: a dump
                    kept = (rating, messages.dumps({   # of long histories holds the GIL briefly
                        'scene': rating.scene, 'action': rating.action, 'score': rating.score,
                        'scene_id': rating.scene_id}))
                self._rating_texts[id(rating)] = kept
                ratings.append(kept[1])
            users.append(f'{messages.dumps(user_id)}:{messages.dumps(model.to_json())[:-1]},'
                         f'"ratings_dropped":{dropped},"ratings":[{",".join(ratings)}]}}')
        head = messages.dumps({'format': STATE_FORMAT, 'version': 1, 'fingerprint': predictor.fingerprint})
        text = f'{head[:-1]},"users":{{{",".join(users)}}}}}'
        try:
            self.state_path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.state_path.with_name(self.state_path.name + '.tmp')
            with open(tmp, 'w') as handle:
                handle.write(text)
                handle.flush()
                os.fsync(handle.fileno())
            os.replace(tmp, self.state_path)
        except OSError as error:
            self.report('recording', f'could not write {self.state_path}: {error}')

    def _restore_user_models(self):
        """Folded-in users of the last run, if they were solved against this checkpoint."""
        if self.state_path is None or not self.state_path.exists():
            return
        try:
            state = json.loads(self.state_path.read_text())
            if state.get('format') != STATE_FORMAT:
                raise ValueError(f'not a {STATE_FORMAT} file')
            if state['fingerprint'] != self.predictor.fingerprint:
                self.report('user_models', f"{self.state_path} was solved against checkpoint "
                            f"{state['fingerprint'][:12]}, not the served {self.predictor.fingerprint[:12]}: "
                            'folded-in users are not restored')
                return
            models = {u: UserModel.from_json(v) for u, v in state['users'].items()}
            histories = {u: ([Rating(r['scene'], r['action'], float(r['score']), r.get('scene_id'))
                              for r in v['ratings']], int(v.get('ratings_dropped', 0)))
                         for u, v in state['users'].items()}
        except (OSError, ValueError, KeyError, TypeError) as error:
            self.report('user_models', f'cannot read {self.state_path}: {error}; folded-in users are not restored')
            return
        evicted = set(self._histories.restore(histories))
        self.predictor.set_user_models({u: m for u, m in models.items() if u not in evicted})
        self.get_logger().info(f'restored {len(models)} folded-in users from {self.state_path}')

    def _carry_user_models(self, predictor):
        """After a reload: users the new checkpoint was refit on keep only the feedback it did
        not absorb; everyone with a history left is re-solved against the new model."""
        absorbed = predictor.metadata.get('provenance', {}).get('refit', {}).get('ratings_per_user', {})
        for user_id in self._histories.absorb(absorbed):
            self._fold_pending[user_id] = None
        self._more_work.trigger()

    def _on_reload(self, request, response):
        try:
            path = resolve_checkpoint(self.params['checkpoint'])
            predictor = Predictor.load(path)
        except CheckpointError as error:
            self.report('checkpoint', f'reload failed, still serving {self.predictor.fingerprint[:12]}: {error}')
            response.success, response.message = False, str(error)
            return response
        self._foldin = self._fold_in_model(predictor)
        self.predictor, self.checkpoint_path = predictor, path  # from the next batch on
        self._carry_user_models(predictor)
        self._strangers_reported = set()  # who is a stranger depends on the model
        response.success = True
        response.message = f'serving {path} (fingerprint {predictor.fingerprint})'
        self.get_logger().info(response.message)
        return response

    # -- serving (executor thread) -------------------------------------------------------
    def _work(self):
        """One batch of queued requests, else one fold-in solve; comes back for the rest."""
        try:
            if self._queue:
                self._serve([self._queue.popleft() for _ in range(min(len(self._queue), self.params['max_batch']))])
            elif self._fold_pending:
                started = time.time_ns()
                try:
                    self._fold_in(self._fold_pending.popitem(last=False)[0])
                finally:
                    ended = time.time_ns()
                    self._fold_in_spans.add(started, ended)
                    self._period_stats.fold_in_update((ended - started) / 1e6)
        except Exception as error:  # noqa: BLE001 - the node must keep serving
            self.report('internal', f'{type(error).__name__}: {error}')
        if self._queue or self._fold_pending:
            self._more_work.trigger()

    def _serve(self, batch):
        predictor, top_k = self.predictor, self.params['top_k']
        started = time.time_ns()
        results = rank_batch(predictor, batch, top_k)
        for item, result in zip(batch, results):
            request = item.request
            if isinstance(result, Exception):
                self._record('stars/scene', item.text, item.log_time)
                self.report(error_kind(result), str(result), self.topics['stars/scene'], request.scene_id)
                continue
            known = predictor.knows_user(item.user_id)
            personalised = predictor.personalised_from(item.user_id)
            processing_ms = max(0, time.time_ns() - item.received) / 1e6
            payload = messages.dumps(messages.ranking_payload(
                request, item.user_id, known, result.ranked, predictor.fingerprint, round(processing_ms, 3),
                result.action, personalised))
            self.ranking_pub.publish(String(data=payload))
            self._period_stats.ranking(processing_ms, self._fold_in_spans.overlap(item.received, started) / 1e6)
            self._record('stars/scene', item.text, item.log_time)  # after the reply: off its latency
            self._record('stars/ranking', payload)
            remembered = self._scenes.get(request.scene_id)
            if remembered is not None and remembered[0] is item.text:
                remembered[1] = (predictor, result.h)
            with self._lock:
                self._counts['ranking'] += 1
            if item.user_id is not None and not known and not personalised:
                self._report_stranger(item.user_id, request.scene_id)

    def _report_stranger(self, user_id: str, scene_id: str):
        """Warn once per unknown user and model, not per ranking: strangers are the normal
        case on a robot, and a warning per ranking would cost every one of them latency."""
        if user_id in self._strangers_reported:
            return
        if len(self._strangers_reported) >= MAX_STRANGERS_REMEMBERED:
            self._strangers_reported.clear()
        self._strangers_reported.add(user_id)
        self.report('unknown_user', f"user '{user_id}' is not in the training data: ranked by scene content and "
                    'population offsets (reported once per user and checkpoint)', self.topics['stars/scene'], scene_id)

    def close(self):
        """Finish the state file and the recording (clean shutdown). Called after
        ``destroy_node``, which takes the node's /rosout publisher with it: a signal has shut
        the context down by then, and each line logged while that publisher still existed
        would end in "Failed to publish log message to rosout: publisher's context is invalid"."""
        waiting = len(self._queue)
        for item in self._queue:  # in the log even though they were never scored
            self._record('stars/scene', item.text, item.log_time)
        wanted = self._save_wanted.is_set()
        self._closing.set()
        self._save_wanted.set()
        self._saver.join(timeout=10)
        if wanted:  # the last updates are on disk before the process ends
            self._save_user_models(self.predictor)
        self._to_journal.put(None)
        self._journal_thread.join(timeout=10)  # every accepted feedback reaches the recorder
        if waiting:
            self.get_logger().warning(f'{waiting} queued requests were not scored before shutdown')
        if self.recorder is not None:
            for entry in self.recorder.close():
                self.get_logger().error(f'feedback that could not be stored: {entry}')
            self.get_logger().info(f'recording closed: {self.recorder.path}')


def main(args=None):
    if usage.print_help_if_asked('ranker', __doc__, PARAMETERS,
                                 'ros2 run stars_ros ranker --ros-args -p checkpoint:=model.pt -p top_k:=3', args):
        return
    rclpy.init(args=args)
    node = None
    try:
        node = RankerNode()
        gc.collect()
        gc.freeze()  # the model and imports leave the collector's generations: full
        spin_until_shutdown(node)  # collections while serving then walk only what requests create
    except (KeyboardInterrupt, ExternalShutdownException):  # before spinning
        pass
    except CheckpointError as error:
        get_logger('ranker').fatal(str(error))
        raise SystemExit(1) from None
    finally:
        if node is not None:
            node.destroy_node()
            node.close()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
