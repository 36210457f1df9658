"""What the ranker node does, without ROS: the checkpoint served, the queue of scene
requests and their batches, problem reports and diagnostics, the recording, and the fold-in
of feedback (``personalisation``). ``stars_ros.ros.ranker`` declares the parameters, turns
messages into the text this class takes and publishes the text it gives.

One thread (the node's executor) calls ``RankerCore``; the state store's thread
(``recording.state_store``) commits feedback and people, and the recorder's flushes the bag,
so the disk never holds up the rankings. ``work`` scores one batch of
queued requests with one model snapshot, else re-solves one user who gave feedback, so the
ranking of others waits for at most one solve; ``reload`` runs between two batches, so every
ranking is scored by exactly one checkpoint, the one whose fingerprint it carries.

A ranking's ``processing_ms`` counts from the middleware's reception of the request, so a
wait behind other callbacks is in it. The core notes when it does fold-in work; a ranking
whose wait overlapped such work is counted, with that overlap, in the next diagnostics
(``period.*``): the node itself shows what fold-in costs others.
"""
from __future__ import annotations

import collections
import time
from typing import Callable, Mapping

from stars_ros import feedback_auth, messages
from stars_ros import recording
from stars_ros.node import markers
from stars_ros.errors import CheckpointError, StarsError
from stars_ros.node.questions import NoQuestion, choose_question
from stars_ros.personalisation.online import Personalisation
from stars_ros.model.predictor import Predictor
from stars_ros.resources import DEFAULT_CHECKPOINT, resolve_checkpoint
from stars_ros.node.batching import WARNINGS, BusySpans, Pending, PeriodStats, Problems, rank_batch

MAX_STRANGERS_REMEMBERED = 10000
TOPICS = ('stars/scene', 'stars/user_id', 'stars/feedback', 'stars/ranking', 'stars/errors', 'stars/user_model',
          'stars/question_request', 'stars/question', 'stars/markers')
_INT_MAX = 2 ** 31 - 1


def topic_qos(params: Mapping) -> dict:
    """topic -> (depth, latched) of every topic of TOPICS, all reliable: what the rclpy
    adapter subscribes and publishes with and the recorder offers again (``ros2 bag play``).
    A robot that joins late gets the last user models; with fleet sharing the history also
    holds a re-send of every user until the newcomer has it; a viewer that joins late gets
    the latest scene's markers."""
    depth = params['queue_depth']
    models = depth + (params['fold_in_max_users'] if params['fleet_sharing'] else 0)
    return {'stars/scene': (depth, False), 'stars/ranking': (depth, False), 'stars/feedback': (100, False),
            'stars/errors': (100, False), 'stars/user_id': (1, True), 'stars/user_model': (models, True),
            'stars/question_request': (10, False), 'stars/question': (10, False), 'stars/markers': (1, True)}


PARAMETERS = {  # name: (default, description, read_only, range)
    'checkpoint': ('', f'checkpoint file; empty: the packaged {DEFAULT_CHECKPOINT}. Read again by ~/reload',
                   False, None),
    'top_k': (0, 'publish only the best k entries of each ranking; 0: all', False, (0, _INT_MAX)),
    'explain': (False, "give every ranking entry its 'why' (the parts of its score and the entities that drive it, "
                'docs/explanations.md), as a request with "explain": true does', False, None),
    'explain_entities': (5, "entities a 'why' names, largest |effect| first; 0: all", False, (0, 4096)),
    'frame_id': ('base_link', "the robot's frame, REP 103 axes: that of stars/markers (the scene converted from "
                 'SocNav1 centimetres, docs/explanations.md) and the one typed scenes must be in (docs/interfaces.md)',
                 False, None),
    'record_markers': (True, 'record stars/markers (visualization_msgs/MarkerArray) in the bag; they are published '
                       'latched either way, so a viewer that joins later gets the latest', False, None),
    'record_folder': (str(recording.default_folder() / recording.NODE_PLACEHOLDER), 'folder for the MCAP bags and '
                      'the state store (state.db), one node each; {node} stands for the node\'s namespace and name '
                      '(robot1/ranker); default $ROS_HOME/stars_ros/records/{node} (ROS_HOME: ~/.ros unless set); '
                      'empty: do not record', True, None),
    'rotation_bytes': (64 << 20, 'start a new MCAP file once one reaches this size (bytes)', True,
                       (4096, _INT_MAX)),
    'flush_interval': (1.0, 'seconds between flushes of the recording (a hard kill loses at most this of its other '
                       'topics; stored feedback is never lost) and between two tries of a disk that refuses the state '
                       'store', True, (0.01, 3600.0)),
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
    'fold_in_max_ratings': (200, "most recent ratings per user the fold-in is solved from (and the state store "
                            'keeps); older ones stay in the MCAP log for the offline refit', True, (1, 1000000)),
    'fold_in_max_users': (1000, 'folded-in users kept; beyond this the one who rated least recently goes back to '
                          'the checkpoint (their feedback stays in the MCAP log)', True, (1, 10000000)),
    'fold_in_regularisation': (0.0, '0: serve the Gaussian posterior of each person (no λ to set: the prior and '
                               'rating noise come from the checkpoint); > 0: the ridge solve with this λ towards the '
                               'prior mean instead', False, (0.0, 1e6)),
    'question_recent_scenes': (32, 'latest remembered scenes a stars/question_request without candidates chooses '
                               'among; the target set of every question request', False, (1, 4096)),
    'fleet_sharing': (False, 'share folded-in users with the other rankers on stars/user_model (remap it to one '
                      "fleet-wide topic): publish each model with the ratings it was solved from, take in peers' "
                      "ratings and solve each user from everyone's", True, None),
    'feedback_key_file': ('', 'file of feedback keys, one KEY_ID:HEX_SECRET a line (docs/security.md): feedback, and '
                          "with fleet sharing the ratings of peers' models, are taken only when one of them signed "
                          'it; empty: feedback is not authenticated', True, None),
    'feedback_max_age': (60.0, 'seconds signed feedback stays valid: a stamp further in the past or the future, or '
                         'a MAC already taken within it, is refused (kind auth)', False, (0.001, 86400.0)),
}


class RankerCore:
    """The ranker's state and work; see the module docstring.

    Args:
        params (dict): parameter values by name (``PARAMETERS``); read at each use, so the
            node's updates to this dict apply at once.
        topics (Mapping): each of ``TOPICS`` -> its resolved name, as recordings and error
            reports give it.
        node_name (str): the node's fully qualified name, for the recording's metadata.
        publish (callable): ``publish(topic, text)`` sends ``text`` on stars/ranking,
            stars/errors or stars/user_model.
        logger: takes ``info``, ``warning`` and ``error`` lines.
        now (callable): the time recorded messages are logged at (ns of ROS time).
        markers_out (optional): where stars/markers go: ``publish(data)`` (a
            visualization_msgs/MarkerArray's CDR bytes, latched) and ``message_type``
            (``recording.MessageType``, for the bag); None: no markers.
    """

    def __init__(self, params: dict, topics: Mapping[str, str], node_name: str, publish: Callable[[str, str], None],
                 logger, now: Callable[[], int], markers_out=None):
        self.params, self.topics, self._publish, self.logger, self._now = params, dict(topics), publish, logger, now
        self.markers_out = markers_out
        self.checkpoint_path = resolve_checkpoint(params['checkpoint'])
        self.predictor = Predictor.load(self.checkpoint_path)
        logger.info(f'serving {self.checkpoint_path} (fingerprint {self.predictor.fingerprint[:12]}, '
                    f'actions {list(self.predictor.actions)})')
        self.user_id, self.problems, self._strangers_reported = None, Problems(), set()
        self.queue = collections.deque()  # Pending requests
        self.questions = collections.deque()  # QuestionRequests waiting to be answered
        self.replied = collections.deque()  # (Pending, reply, ranked) of rank_now: to record, markers to send
        self._fold_in_spans = BusySpans()  # when fold-in work was done (time.time_ns)
        self._period_stats = PeriodStats()  # for the next diagnostics
        self.authenticator = self._feedback_authenticator()  # first: a bad key file leaves no recording open
        folder = params['record_folder']
        self.record_folder = recording.node_folder(folder, node_name) if folder else None
        self.recorder = None
        self.store = self._open_store(node_name)  # first: StoreLockedError when another node holds the folder
        self.recorder = self._start_recorder(node_name)
        self.personalisation = Personalisation(
            self.predictor, params['fold_in_max_ratings'], params['fold_in_max_users'], self.report, logger,
            self.store, origin=node_name, sharing=params['fleet_sharing'], authenticator=self.authenticator)
        self._peers_reported = set()  # (peer, fingerprint or λ) warned about once
        self.personalisation.restore()

    def _feedback_authenticator(self):
        """The checks of signed feedback (``feedback_auth``), None without a key file. A key
        file that cannot be read raises ConfigError: the node does not start unprotected."""
        path = self.params['feedback_key_file']
        if not path:
            self.logger.warning('feedback_key_file is empty: feedback is not authenticated, anyone who reaches the '
                                'ROS domain can rate for any person (docs/security.md)')
            return None
        keys = feedback_auth.load_keys(path)
        if feedback_auth.readable_by_others(path):
            self.logger.warning(f'feedback key file {path} is readable by its group or others: chmod 600 it')
        self.logger.info(f'feedback is taken only when signed by a key of {path} ({", ".join(keys)})')
        return feedback_auth.FeedbackAuthenticator(keys, lambda: self.params['feedback_max_age'])

    # -- recording -----------------------------------------------------------------------
    def _open_store(self, node_name: str):
        if self.record_folder is None:
            return None
        store = recording.StateStore(self.record_folder, node_name, self._on_store_error, self.logger.info,
                                     self.params['flush_interval'])
        for imported in store.imported:
            self.logger.info(f'imported {imported} into {store.path} (the files are kept as they were)')
        return store

    def _on_store_error(self, text: str):
        self.report('recording', text + '; ranking goes on, feedback is kept in memory until the disk works')

    def _start_recorder(self, node_name: str):
        folder = self.record_folder
        if folder is None:
            self.logger.warning('record_folder is empty: scenes, rankings and feedback are not recorded')
            return None
        try:
            for bag in recording.abandoned_bags(folder):
                self.logger.warning(f'recovered {bag} left by a hard kill: {recording.recover(bag)}')
        except (OSError, ValueError) as error:
            self.report('recording', f'could not recover old bags in {folder}: {error}')
        qos = {self.topics[topic]: recording.qos_profile(depth, latched)
               for topic, (depth, latched) in topic_qos(self.params).items()
               if topic != 'stars/markers' or self.markers_out is not None}
        types = {} if self.markers_out is None else {self.topics['stars/markers']: self.markers_out.message_type}
        recorder = recording.Recorder(
            folder, qos, rotation_bytes=self.params['rotation_bytes'], flush_interval=self.params['flush_interval'],
            custom={'node': node_name, 'checkpoint': self.checkpoint_path, 'fingerprint': self.predictor.fingerprint},
            on_event=self._on_recorder_event, types=types)
        if recorder.error is None:
            self.logger.info(f'recording to {recorder.path}')
        return recorder

    def _on_recorder_event(self, level: str, text: str):
        if level == 'error':
            self.report('recording', text + '; ranking goes on, feedback is kept in memory until the disk works')
        else:
            self.logger.info(text)

    def record(self, topic: str, text: str, log_time: int | None = None):
        """Record ``text`` on ``topic`` (one of ``TOPICS``) at ``log_time`` (default: now)."""
        if self.recorder is not None:
            self.recorder.write(self.topics[topic], text, self._now() if log_time is None else log_time)

    def _committed(self, entry: dict):
        """Feedback the store committed (its thread): into the bag, the log of record."""
        if self.recorder is not None:
            self.recorder.write_feedback(entry['topic'], entry['data'], entry['log_time'])

    # -- problems and diagnostics --------------------------------------------------------
    def report(self, kind: str, detail: str, topic: str = '', scene_id: str | None = None):
        """Count, publish on stars/errors, log (throttled per kind) and record one problem."""
        total = self.problems.add(kind, detail, self.params['log_throttle'])
        payload = messages.dumps({'kind': kind, 'message': detail, 'topic': topic, 'scene_id': scene_id,
                                  'level': 'warning' if kind in WARNINGS else 'error'})
        self._publish('stars/errors', payload)
        self.record('stars/errors', payload)
        if total is not None:
            line = (f"[{kind}] {detail} (total {total}; repeats are logged at most every {self.params['log_throttle']}"
                    ' s)')
            if kind in WARNINGS:  # rclpy fixes one severity per call site
                self.logger.warning(line)
            else:
                self.logger.error(line)

    def diagnostics(self) -> tuple[str, str, dict, list]:
        """(level: 'ok', 'warn' or 'error'; summary; key-values; [(kind, level, count, latest
        detail)] of each kind of problem) of the period since the last call, which ends it."""
        period, counts = self.problems.take_period()
        recorder = self.recorder
        store = self.store
        failure = (recorder and recorder.error) or (store and store.error)
        level = 'error' if set(period) - set(WARNINGS) or failure else ('warn' if period else 'ok')
        summary = 'serving' if not period else 'serving; problems since last report: ' + ', '.join(
            f'{k} x{n}' for k, (n, _) in sorted(period.items()))
        values = {'checkpoint': self.checkpoint_path, 'fingerprint': self.predictor.fingerprint,
                  'rankings': counts.get('ranking', 0), 'queued': len(self.queue),
                  'recording': 'off' if recorder is None else (failure or str(recorder.path)),
                  'feedback_not_on_disk': 0 if store is None else store.uncommitted_feedback,
                  'folded_in_users': len(self.predictor.user_models), **self._period_stats.values()}
        values.update({f'errors.{k}': n for k, n in sorted(counts.items()) if k != 'ranking'})
        self._period_stats = PeriodStats()
        kinds = [(kind, 'warn' if kind in WARNINGS else 'error', count, detail)
                 for kind, (count, detail) in sorted(period.items())]
        return level, summary, values, kinds

    # -- input ---------------------------------------------------------------------------
    def _parse(self, parse, text: str, topic: str):
        """``parse(text, max_message_bytes)``, or None once the refusal is reported."""
        try:
            return parse(text, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            self.report(error.kind, str(error), topic, error.scene_id)
            return None

    def accept_scene(self, text: str, received: int):
        """Queue a stars/scene request the middleware received at ``received`` (time.time_ns)."""
        request = self._parse(messages.parse_scene_request, text, self.topics['stars/scene'])
        if request is None:
            return
        log_time = self._now()
        self.personalisation.scenes.received(request.scene_id, text)
        if len(self.queue) >= self.params['queue_depth']:
            self.record('stars/scene', text, log_time)
            self.report('overload', f"{self.params['queue_depth']} requests already wait to be scored; "
                        'this one is dropped', self.topics['stars/scene'], request.scene_id)
            return
        self.queue.append(Pending(request, request.user_id or self.user_id, received, text, log_time))

    def rank_now(self, text: str, received: int) -> tuple:
        """Score one stars/scene request at once, as the queue's next batch would (a service
        call, between two batches): (its stars/ranking payload, None), or (None, (kind,
        message)) once the refusal is on stars/errors. The ranking is not published; the next
        ``work`` records it and sends its markers (call it once the reply is out)."""
        try:
            request = messages.parse_scene_request(text, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            self.report(error.kind, str(error), self.topics['stars/scene'], error.scene_id)
            return None, (error.kind, str(error))
        self.personalisation.scenes.received(request.scene_id, text)
        return self._serve([Pending(request, request.user_id or self.user_id, received, text, self._now())],
                           publish=False)[0]

    def accept_user_id(self, text: str):
        try:
            self.user_id = messages.parse_user_id(text)
        except messages.BadMessage as error:
            self.report(error.kind, str(error), self.topics['stars/user_id'])
            return
        self.record('stars/user_id', text)

    def accept_feedback(self, text: str) -> bool:
        """Fold in a stars/feedback message and queue it, with the rating it gives, for the
        state store, which commits both in one transaction and only then counts the feedback
        as stored (``feedback_not_on_disk`` until then); True when a user now waits to be
        re-solved (call ``work``)."""
        topic = self.topics['stars/feedback']
        feedback = self._parse(messages.parse_feedback, text, topic)
        if feedback is None:
            return False
        if self.authenticator is not None:  # before the store: refused feedback is recorded as an error only
            refusal = self.authenticator.check(feedback.signed, self._now())
            if refusal is not None:
                self.report('auth', f'feedback refused, not folded in: {refusal}', topic, feedback.scene_id)
                return False
        if feedback.action is not None and feedback.action not in self.predictor.actions:
            self.report('unknown_action', f"feedback for unknown action '{feedback.action}'; this model knows "
                        f'{list(self.predictor.actions)}', topic, feedback.scene_id)
            return False
        log_time = self._now()
        if self.store is None:
            self.report('recording', 'feedback accepted but record_folder is empty: it is not stored', topic,
                        feedback.scene_id)
        elif not self.store.healthy:
            self.report('recording', 'feedback could not be stored yet; kept in memory and retried', topic,
                        feedback.scene_id)
        refused, update = 'fold_in is off', None
        if self.params['fold_in']:
            started = time.time_ns()
            refused = self.personalisation.add_feedback(feedback, self.params['max_message_bytes'], log_time)
            if refused is not None:
                self.report('unknown_scene', refused, topic, feedback.scene_id)
            elif self.store is not None:
                update = self.personalisation.update(feedback.user_id)
            self._fold_in_spans.add(started, time.time_ns())
        if self.store is not None:
            self.store.put_feedback({'topic': topic, 'log_time': log_time, 'data': text},
                                    self.recorder.name if self.recorder is not None else '', update, self._committed)
        return refused is None

    def accept_user_model(self, text: str) -> bool:
        """Take in a peer's stars/user_model message (fleet sharing): the ratings it was
        solved from that this node lacks join the user's. True when the user now waits to be
        re-solved (call ``work``). A message of another checkpoint is ignored (warned about
        once per peer and checkpoint); a bad one is reported and changes nothing."""
        topic = self.topics['stars/user_model']
        try:
            payload = messages.parse_user_model(text, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            self.report(error.kind, f'peer user model refused: {error}', topic)
            return False
        peer, user_id = payload.get('origin', 'a ranker without fleet sharing'), payload['user_id']
        if payload['fingerprint'] != self.predictor.fingerprint:
            self._warn_once(peer, payload['fingerprint'], f"user models from {peer} were solved against checkpoint "
                            f"{payload['fingerprint'][:12]}, not the served {self.predictor.fingerprint[:12]}: "
                            'ignored (reported once per peer and checkpoint)')
            return False
        if payload['regularisation'] != self.params['fold_in_regularisation']:
            self._warn_once(peer, payload['regularisation'], f"{peer} folds in with fold_in_regularisation = "
                            f"{payload['regularisation']}, this node with {self.params['fold_in_regularisation']}: "
                            'their models of a user differ (reported once per peer and value)')
        try:
            return self.personalisation.add_peer_ratings(user_id, payload.get('ratings', []), peer)
        except StarsError as error:
            self.report(messages.error_kind(error), f"user model of '{user_id}' from {peer} refused, nothing taken in: "
                        f'{error}', topic)
            return False

    def accept_question_request(self, text: str) -> bool:
        """Queue a stars/question_request; True when it waits to be answered (call ``work``)."""
        request = self._parse(messages.parse_question_request, text, self.topics['stars/question_request'])
        if request is None:
            return False
        self.record('stars/question_request', text)
        self.questions.append(request)
        return True

    def question_now(self, text: str) -> tuple:
        """Answer one stars/question_request at once (a service call): (its stars/question
        payload, None), or (None, (kind, message)) once the refusal is on stars/errors. The
        answer is recorded, not published."""
        try:
            request = messages.parse_question_request(text, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            self.report(error.kind, str(error), self.topics['stars/question_request'])
            return None, (error.kind, str(error))
        self.record('stars/question_request', text)
        return self._answer_question(request, publish=False)

    def _answer_question(self, request: messages.QuestionRequest, publish: bool = True) -> tuple:
        """(the stars/question payload, None) or (None, (kind, message)); ``publish``: it goes
        out on stars/question."""
        try:
            answer = choose_question(self.personalisation, request.user_id, list(request.candidates),
                                     self.params['question_recent_scenes'])
        except NoQuestion as error:
            self.report('no_question', str(error), self.topics['stars/question_request'])
            return None, ('no_question', str(error))
        except StarsError as error:
            kind, detail = messages.error_kind(error), f'question request refused: {error}'
            self.report(kind, detail, self.topics['stars/question_request'])
            return None, (kind, detail)
        payload = messages.dumps(answer)
        if publish:
            self._publish('stars/question', payload)
        self.record('stars/question', payload)
        return answer, None

    def _warn_once(self, peer: str, value, detail: str):
        if (peer, value) not in self._peers_reported:
            if len(self._peers_reported) >= MAX_STRANGERS_REMEMBERED:
                self._peers_reported.clear()
            self._peers_reported.add((peer, value))
            self.report('fleet', detail, self.topics['stars/user_model'])

    def announce(self) -> bool:
        """A subscriber joined stars/user_model: send it every folded-in user (fleet
        sharing); True when some wait to be sent (call ``work``)."""
        self.personalisation.announce_all()
        return bool(self.personalisation.to_announce)

    def reload(self) -> tuple[bool, str]:
        """Load the checkpoint parameter's file again and serve it from the next batch on:
        (success, what is served or why not). Folded-in users are re-solved against it (call
        ``work``)."""
        try:
            path = resolve_checkpoint(self.params['checkpoint'])
            predictor = Predictor.load(path)
        except CheckpointError as error:
            self.report('checkpoint', f'reload failed, still serving {self.predictor.fingerprint[:12]}: {error}')
            return False, str(error)
        self.predictor, self.checkpoint_path = predictor, path
        self.personalisation.use(predictor)
        self._strangers_reported = set()  # who is a stranger depends on the model
        message = f'serving {path} (fingerprint {predictor.fingerprint})'
        self.logger.info(message)
        return True, message

    # -- work ----------------------------------------------------------------------------
    def work(self) -> bool:
        """One batch of queued requests, else one question answered, else one peer rating
        checked, else one fold-in solve, else one model sent again to peers; True when more
        work waits."""
        personalisation = self.personalisation
        pending, to_announce, intake = personalisation.pending, personalisation.to_announce, personalisation.intake
        try:
            while self.replied:
                self._after_reply(*self.replied.popleft())
            if self.queue:
                self._serve([self.queue.popleft() for _ in range(min(len(self.queue), self.params['max_batch']))])
            elif self.questions:
                self._answer_question(self.questions.popleft())
            elif intake:
                started = time.time_ns()
                try:
                    refused = personalisation.take_in_next()
                finally:
                    self._fold_in_spans.add(started, time.time_ns())
                if refused is not None:
                    self.report(*refused, self.topics['stars/user_model'])
            elif pending:
                started = time.time_ns()
                try:
                    self._solve_next()
                finally:
                    ended = time.time_ns()
                    self._fold_in_spans.add(started, ended)
                    self._period_stats.fold_in_update((ended - started) / 1e6)
            elif to_announce:
                self._publish_model(to_announce.popitem(last=False)[0])
        except Exception as error:  # noqa: BLE001 - the node must keep serving
            self.report('internal', f'{type(error).__name__}: {error}')
        return bool(self.queue or self.questions or intake or pending or to_announce)

    def _solve_next(self):
        solved = self.personalisation.solve_next(self.params['fold_in_min_ratings'],
                                                 self.params['fold_in_regularisation'])
        if solved is not None:
            self._publish_model(solved[0])

    def _publish_model(self, user_id: str):
        message = self.personalisation.model_message(user_id)
        if message is not None:
            payload = messages.dumps(message)
            self._publish('stars/user_model', payload)
            self.record('stars/user_model', payload)

    def _serve(self, batch: list, publish: bool = True) -> list:
        """Score ``batch``; per request (its ranking payload, None) or (None, (kind, message)).
        ``publish``: the rankings go out on stars/ranking."""
        outcomes = []
        predictor, top_k = self.predictor, self.params['top_k']
        started = time.time_ns()
        uncertainty = self.personalisation.uncertainty
        explanations = (self.params['explain'], self.params['explain_entities'])
        for item, result in zip(batch, rank_batch(predictor, batch, top_k, uncertainty, explanations)):
            request = item.request
            if isinstance(result, Exception):
                self.record('stars/scene', item.text, item.log_time)
                self.report(messages.error_kind(result), str(result), self.topics['stars/scene'], request.scene_id)
                outcomes.append((None, (messages.error_kind(result), str(result))))
                continue
            known, personalised = predictor.knows_user(item.user_id), predictor.personalised_from(item.user_id)
            processing_ms = max(0, time.time_ns() - item.received) / 1e6
            reply = messages.ranking_payload(
                request, item.user_id, known, result.ranked, predictor.fingerprint, round(processing_ms, 3),
                result.action, personalised, result.p_first_is_best)
            if publish:
                self._publish('stars/ranking', messages.dumps(reply))
                self._after_reply(item, reply, result.ranked)
            else:  # the caller sends the reply: recording and markers wait for the next ``work``
                self.replied.append((item, reply, result.ranked))
            outcomes.append((reply, None))
            self._period_stats.ranking(processing_ms, self._fold_in_spans.overlap(item.received, started) / 1e6)
            self.personalisation.scenes.ranked(request.scene_id, item.text, predictor, result.h)
            self.problems.ranked()
            if item.user_id is not None and not known and not personalised:
                self._report_stranger(item.user_id, request.scene_id)
        return outcomes

    def _after_reply(self, item: Pending, reply: dict, ranked: list):
        """What follows a ranking's reply, off its latency: the request and the ranking
        recorded, the markers sent."""
        self.record('stars/scene', item.text, item.log_time)
        self.record('stars/ranking', messages.dumps(reply))
        self._send_markers(item.request, ranked)

    def _send_markers(self, request, ranked: list):
        """stars/markers of a ranked request, after its reply (off its latency): published
        even while nobody listens, so the latched latest array reaches a viewer that joins later."""
        out = self.markers_out
        if out is None:
            return
        stamp = self._now()
        data = markers.encode_marker_array(markers.ranking_markers(request, ranked), self.params['frame_id'], stamp)
        out.publish(data)
        if self.recorder is not None and self.params['record_markers']:
            self.recorder.write_encoded(self.topics['stars/markers'], data, stamp)

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
        """Record the requests never scored, commit what waits for the state store, close
        the store and the recording (clean shutdown)."""
        while self.replied:  # answered by rank_now since the last work
            item, reply, _ = self.replied.popleft()
            self.record('stars/scene', item.text, item.log_time)
            self.record('stars/ranking', messages.dumps(reply))
        for item in self.queue:  # in the log even though they were never scored
            self.record('stars/scene', item.text, item.log_time)
        if self.queue:
            self.logger.warning(f'{len(self.queue)} queued requests were not scored before shutdown')
        if self.store is not None:  # first: what it commits reaches the bag before the bag closes
            for entry in self.store.close():
                self.logger.error(f'feedback that could not be stored: {entry}')
        if self.recorder is not None:
            self.recorder.close()
            self.logger.info(f'recording closed: {self.recorder.path}')
