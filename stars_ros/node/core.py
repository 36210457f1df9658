"""What the ranker node does, without ROS: the checkpoint served, the queue of scene
requests and the work loop over them, problem reports, and the fold-in of feedback
(``personalisation``). The rest of the node's logic sits beside it, one concern a module:
its parameters and topics (``parameters``), the figures of /diagnostics (``diagnostics``),
the state store and the recording (``records``), peers' user models (``fleet_intake``),
batch ranking (``batching``), questions (``questions``) and markers (``markers``).
``stars_ros.ros.ranker`` declares the parameters, turns messages into the text this class
takes and publishes the text it gives.

One thread (the node's executor) calls ``RankerCore``; the state store's thread
(``stars_ros.state``) commits feedback and people, and the recorder's flushes the bag,
so the disk never holds up the rankings. What waits for a commit comes back to the executor:
the store's thread only queues it and calls ``wake`` (a model whose ratings are committed
goes out at the next ``work``). ``work`` scores one batch of
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
from stars_ros.node import markers
from stars_ros.errors import CheckpointError, StarsError
from stars_ros.node.questions import NoQuestion, choose_question
from stars_ros.personalisation.online import Personalisation
from stars_ros.personalisation.foldin import check_feedback_score
from stars_ros.model.predictor import Predictor
from stars_ros.resources import resolve_checkpoint
from stars_ros.node.batching import Pending, rank_batch
from stars_ros.node.fleet_intake import FleetIntake
from stars_ros.node import fleet_forget
from stars_ros.node.consent import Consent
from stars_ros.node.diagnostics import WARNINGS, BusySpans, PeriodStats, Problems, period_report
from stars_ros.node.records import NodeRecords
from stars_ros.node.erasing import Erase, Erasing
from stars_ros.recording import erasure
from stars_ros.state import mentions

MAX_STRANGERS_REMEMBERED = 10000
RETENTION_TIMEOUT = 600  # s a retention pass waits for the state store's erase
ERASING_CLOSE_WAIT = 10.0  # s a clean shutdown waits for an erase that runs (its intent record covers the rest)


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
        clock (callable): the system time in ns (``time.time_ns`` unless a test steps it),
            which ``received`` times, processing times and fold-in spans are read on.
        after_person_read (callable, optional): ``Personalisation``'s, called once a person
            restored from the store has their ratings read.
        wake (callable, optional): called from the state store's thread when something waits
            for the executor (call ``work``); None: the next ``work`` finds it.
    """

    def __init__(self, params: dict, topics: Mapping[str, str], node_name: str, publish: Callable[[str, str], None],
                 logger, now: Callable[[], int], markers_out=None, clock: Callable[[], int] = time.time_ns,
                 after_person_read: Callable[[], None] | None = None, wake: Callable[[], None] | None = None):
        self.params, self.topics, self._publish, self.logger, self._now = params, dict(topics), publish, logger, now
        self._clock, self._wake = clock, wake or (lambda: None)
        self.durable_models = collections.deque()  # (user, stars/user_model payload) whose ratings are committed
        self._erasing, self._erases_of = None, collections.Counter()  # node.erasing's thread; forgets running by id
        self._models_held = collections.Counter()  # models of people being forgotten, by id: never sent
        self.markers_out = markers_out
        self.checkpoint_path = resolve_checkpoint(params['checkpoint'])
        self.predictor = Predictor.load(self.checkpoint_path)
        logger.info(f'serving {self.checkpoint_path} (fingerprint {self.predictor.fingerprint[:12]}, '
                    f'actions {list(self.predictor.actions)})')
        self.user_id, self.problems, self._strangers_reported = None, Problems(), set()
        self.queue = collections.deque()  # Pending requests
        self.questions = collections.deque()  # QuestionRequests waiting to be answered
        self.replied = collections.deque()  # (Pending, reply, ranked) of rank_now: to record, markers to send
        self._fold_in_spans = BusySpans()  # when fold-in work was done (``clock``)
        self._period_stats = PeriodStats()  # for the next diagnostics
        self.authenticator = self._feedback_authenticator()  # first: a bad key file leaves no recording open
        self.consent = Consent(params['store_policy'], params['consent_file'])  # as is a bad consent file
        self.records = None  # while it opens, a problem is published and logged, not recorded
        self.records = NodeRecords(params, self.topics, node_name,
                                   {'checkpoint': self.checkpoint_path, 'fingerprint': self.predictor.fingerprint},
                                   self.report, logger, now, None if markers_out is None else markers_out.message_type)
        self.personalisation = Personalisation(
            self.predictor, params['fold_in_max_ratings'], params['fold_in_max_users'], self.report, logger,
            self.store, origin=node_name, sharing=params['fleet_sharing'], authenticator=self.authenticator,
            after_person_read=after_person_read)
        self.fleet = FleetIntake(params, self.topics['stars/user_model'], self.report)
        self.records.consent, self.fleet.may_store = self.consent, self.consent.allows
        self.finish_interrupted_forgets()  # before restore: a person half erased is not read back
        self.personalisation.restore()
        self.apply_retention()  # at start, before serving; then on the node's timer

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

    # -- recording ---------------------------------------------------------------------
    @property
    def store(self):
        """The state store (``stars_ros.state.StateStore``), None when nothing is recorded."""
        return self.records.store

    @property
    def recorder(self):
        """The recording (``stars_ros.recording.Recorder``), None when nothing is recorded."""
        return self.records.recorder

    def record(self, topic: str, text: str, log_time: int | None = None):
        """Record ``text`` on ``topic`` (one of ``TOPICS``) at ``log_time`` (default: now)."""
        if self.records is not None:
            self.records.record(topic, text, log_time)

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
        failure, recording_values = self.records.status()
        values = {'checkpoint': self.checkpoint_path, 'fingerprint': self.predictor.fingerprint,
                  'rankings': counts.get('ranking', 0), 'queued': len(self.queue), **recording_values,
                  'folded_in_users': len(self.predictor.user_models), **self._period_stats.values()}
        self._period_stats = PeriodStats()
        return period_report(period, counts, failure, values)

    # -- input ---------------------------------------------------------------------------
    def _parse(self, parse, text: str, topic: str):
        """``parse(text, max_message_bytes)``, or None once the refusal is reported."""
        try:
            return parse(text, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            self.report(error.kind, str(error), topic, error.scene_id)
            return None

    def accept_scene(self, text: str, received: int):
        """Queue a stars/scene request the middleware received at ``received`` (ns of ``clock``)."""
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

    def rank_now(self, message, received: int, log_time: int | None = None, source: str | None = None) -> tuple:
        """Score one stars/scene request (its text, or a typed request's ``Twin``) at once, as
        the queue's next batch would (a service call, between two batches): (its stars/ranking
        payload, None), or (None, (kind, message)) once the refusal is on stars/errors.
        ``log_time``: when the request was taken (ROS time, ns; default now); ``source``: the
        service or topic it came in on, which a refusal names (default: stars/scene). The
        ranking is not published; the next ``work`` records it and sends its markers (call it
        once the reply is out)."""
        source = source or self.topics['stars/scene']
        try:
            request = messages.parse_scene_request(message, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            self.report(error.kind, str(error), source, error.scene_id)
            return None, (error.kind, str(error))
        self.personalisation.scenes.received(request.scene_id, message)
        log_time = self._now() if log_time is None else log_time
        return self._serve([Pending(request, request.user_id or self.user_id, received, message, log_time)],
                           publish=False, source=source)[0]

    def accept_user_id(self, text: str):
        try:
            self.user_id = messages.parse_user_id(text)
        except messages.BadMessage as error:
            self.report(error.kind, str(error), self.topics['stars/user_id'])
            return
        self.record('stars/user_id', text)

    def accept_feedback(self, message, topic: str | None = None) -> bool:
        """Fold in a stars/feedback message (its text, or typed feedback's ``Twin``) and queue
        it, with the rating it gives, for the state store, which commits both in one
        transaction and only then counts the feedback as stored (``feedback_not_on_disk``
        until then); True when a user now waits to be re-solved (call ``work``). ``topic``:
        the topic it came in on, which a refusal names (default: stars/feedback); it is
        journaled as stars/feedback's text."""
        topic = topic or self.topics['stars/feedback']
        feedback = self._parse(messages.parse_feedback, message, topic)
        if feedback is None:
            return False
        if self.authenticator is not None:  # before the store: refused feedback is recorded as an error only
            refusal = self.authenticator.check(feedback.signed, self._now())
            if refusal is not None:
                self.report('auth', f'feedback refused, not folded in: {refusal}', topic, feedback.scene_id)
                return False
        if not self.consent.allows(feedback.user_id):  # the report does not name them: stars/errors is recorded
            self.report('consent', 'feedback of a person not on the consent list (store_policy consented): not '
                        'stored, not folded in', topic, feedback.scene_id)
            return False
        if feedback.action is not None and feedback.action not in self.predictor.actions:
            self.report('unknown_action', f"feedback for unknown action '{feedback.action}'; this model knows "
                        f'{list(self.predictor.actions)}', topic, feedback.scene_id)
            return False
        try:  # before the store: a score off the scale is neither stored nor folded in
            check_feedback_score(feedback, self.predictor.rating_scale)
        except StarsError as error:
            self.report(messages.error_kind(error), f'feedback refused, not stored: {error}', topic, feedback.scene_id)
            return False
        log_time = self._now()
        if self.store is None:
            self.report('recording', 'feedback accepted but record_folder is empty: it is not stored', topic,
                        feedback.scene_id)
        elif not self.store.healthy:
            self.report('recording', 'feedback could not be stored yet; kept in memory and retried', topic,
                        feedback.scene_id)
        journal = None if self.store is None else ({'topic': self.topics['stars/feedback'], 'log_time': log_time,
                                                    'data': messages.text_of(message)},
                                                   self.records.bag)
        if not self.params['fold_in'] and feedback.user_id not in self.personalisation.forgotten:
            self.personalisation.record_feedback(journal)
            return False
        started = self._clock()
        refused = self.personalisation.add_feedback(feedback, self.params['max_message_bytes'], log_time, journal)
        if refused is not None:
            self.report('unknown_scene', refused, topic, feedback.scene_id)
        self._fold_in_spans.add(started, self._clock())
        return refused is None

    def accept_user_model(self, text: str) -> bool:
        """Take in a peer's stars/user_model message (fleet sharing, ``FleetIntake``); True
        when the user now waits to be re-solved (call ``work``)."""
        return self.fleet.accept(text, self.predictor, self.personalisation)

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
            self._finish_erases()
            while self.replied:
                self._after_reply(*self.replied.popleft())
            self._send_durable_models()
            if self.queue:
                self._serve([self.queue.popleft() for _ in range(min(len(self.queue), self.params['max_batch']))])
            elif self.questions:
                self._answer_question(self.questions.popleft())
            elif intake:
                started = self._clock()
                try:
                    refused = personalisation.take_in_next()
                finally:
                    self._fold_in_spans.add(started, self._clock())
                if refused is not None:
                    self.report(*refused, self.topics['stars/user_model'])
            elif pending:
                started = self._clock()
                try:
                    self._solve_next()
                finally:
                    ended = self._clock()
                    self._fold_in_spans.add(started, ended)
                    self._period_stats.fold_in_update((ended - started) / 1e6)
            elif to_announce:
                self._publish_model(to_announce.popitem(last=False)[0])
        except Exception as error:  # noqa: BLE001 - the node must keep serving
            self.report('internal', f'{type(error).__name__}: {error}')
        return bool(self.queue or self.questions or intake or pending or to_announce or self.durable_models)

    def _solve_next(self):
        solved = self.personalisation.solve_next(self.params['fold_in_min_ratings'],
                                                 self.params['fold_in_regularisation'])
        if solved is not None:
            self._publish_model(solved[0])

    def _publish_model(self, user_id: str):
        """Send ``user_id``'s served model to peers, subscribers and the bag once the store
        has committed the ratings it was solved from: nobody sees a model a hard kill could
        take back (their own rankings use it at once)."""
        message = self.personalisation.model_message(user_id)
        if message is None:
            return
        payload = messages.dumps(message)
        if self.store is None:
            self._send_model(payload)
            return

        def committed():  # on the store's thread, or on this one if it is committed already
            self.durable_models.append((user_id, payload))
            self._wake()
        self.store.when_committed(self.personalisation.durable_after(user_id), committed)

    def _send_durable_models(self):
        while self.durable_models:
            user_id, payload = self.durable_models.popleft()
            if user_id in self._erases_of:  # being forgotten: held until the forget ends, then dropped
                self._models_held[user_id] += 1
            else:
                self._send_model(payload)

    def _send_model(self, payload: str):
        """Publish and record (logged when it goes out) a user model whose ratings are durable."""
        self._publish('stars/user_model', payload)
        self.record('stars/user_model', payload)

    def _serve(self, batch: list, publish: bool = True, source: str | None = None) -> list:
        """Score ``batch``; per request (its ranking payload, None) or (None, (kind, message)).
        ``publish``: the rankings go out on stars/ranking; ``source``: where the requests came
        in, which a refusal names (default: stars/scene)."""
        source = source or self.topics['stars/scene']
        outcomes = []
        predictor, top_k = self.predictor, self.params['top_k']
        started = self._clock()
        uncertainty = self.personalisation.uncertainty
        explanations = (self.params['explain'], self.params['explain_entities'])
        for item, result in zip(batch, rank_batch(predictor, batch, top_k, uncertainty, explanations)):
            request = item.request
            if isinstance(result, Exception):
                self.record('stars/scene', messages.text_of(item.message), item.log_time)
                self.report(messages.error_kind(result), str(result), source, request.scene_id)
                outcomes.append((None, (messages.error_kind(result), str(result))))
                continue
            known, personalised = predictor.knows_user(item.user_id), predictor.personalised_from(item.user_id)
            processing_ms = max(0, self._clock() - item.received) / 1e6
            reply = messages.ranking_payload(
                request, item.user_id, known, result.ranked, predictor.fingerprint, round(processing_ms, 3),
                result.action, personalised, result.p_first_is_best)
            if publish:  # recorded first: a ranking or markers anyone saw are in the bag, even if a signal follows
                self._record_reply(item, reply)
                self._publish('stars/ranking', messages.dumps(reply))
                self._send_markers(item.request, result.ranked)
            else:  # the caller sends the reply: recording and markers wait for the next ``work``
                self.replied.append((item, reply, result.ranked))
            outcomes.append((reply, None))
            self._period_stats.ranking(processing_ms, self._fold_in_spans.overlap(item.received, started) / 1e6)
            self.personalisation.scenes.ranked(request.scene_id, item.message, predictor, result.h, result.plain)
            self.problems.ranked()
            if item.user_id is not None and not known and not personalised:
                self._report_stranger(item.user_id, request.scene_id)
        return outcomes

    def _after_reply(self, item: Pending, reply: dict, ranked: list):
        """What follows a service's reply, off its latency: the request and the ranking
        recorded, the markers sent."""
        self._record_reply(item, reply)
        self._send_markers(item.request, ranked)

    def _record_reply(self, item: Pending, reply: dict):
        self.record('stars/scene', messages.text_of(item.message), item.log_time)
        self.record('stars/ranking', messages.dumps(reply))

    def _send_markers(self, request, ranked: list):
        """stars/markers of a ranked request, after its reply (off its latency): published
        even while nobody listens, so the latched latest array reaches a viewer that joins later."""
        out = self.markers_out
        if out is None:
            return
        stamp = self._now()
        data = markers.encode_marker_array(markers.ranking_markers(request, ranked), self.params['frame_id'], stamp)
        self.records.record_markers(data, stamp)
        out.publish(data)

    def _report_stranger(self, user_id: str, scene_id: str):
        """Warn once per unknown user and model, not per ranking: strangers are the normal
        case on a robot, and a warning per ranking would cost every one of them latency."""
        if user_id in self._strangers_reported:
            return
        if len(self._strangers_reported) >= MAX_STRANGERS_REMEMBERED:
            self._strangers_reported.clear()
        self._strangers_reported.add(user_id)
        how = ('the plain scene encoder the checkpoint keeps for strangers' if self.predictor.stranger_inference
               is not None else 'scene content and population offsets')
        self.report('unknown_user', f"user '{user_id}' is not in the training data: ranked by {how} "
                    '(reported once per user and checkpoint)', self.topics['stars/scene'], scene_id)

    def close(self):
        """Record the requests never scored, commit what waits for the state store, close
        the store and the recording (clean shutdown)."""
        while self.replied:  # answered by rank_now since the last work
            item, reply, _ = self.replied.popleft()
            self._record_reply(item, reply)
        for item in self.queue:  # in the log even though they were never scored
            self.record('stars/scene', messages.text_of(item.message), item.log_time)
        if self.queue:
            self.logger.warning(f'{len(self.queue)} queued requests were not scored before shutdown')
        if self._erasing is not None and not self._erasing.close(ERASING_CLOSE_WAIT):
            self.logger.warning(f'an erase still runs after {ERASING_CLOSE_WAIT:g} s: the next start finishes it')
        self.records.close(self.personalisation.flush, self._send_durable_models)

    def begin_forget(self, user_id: str, tell_fleet: bool = True,
                     then: Callable[[dict | None, BaseException | None], None] | None = None) -> Erase | None:
        """Erase ``user_id`` everywhere this node keeps them (docs/privacy.md): now, the
        intent record and memory (``Personalisation.forget_person``; from here their feedback
        and peers' models of them are refused and no message naming them is recorded); then,
        on the erasing thread while the node serves, the state store and every bag of the
        record folder (``recording.erasure.forget``), leaving a tombstone. When that is done,
        the next ``work`` drops their models waiting to go out, tells peers with fleet
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
        if self.user_id == user_id:
            self.user_id = None
        self._strangers_reported.discard(user_id)
        then = then or self._report_failed_forget
        if folder is None:
            self._forget_finished(user_id, tell_fleet, removed, then, {}, None)
            return None
        self.records.unrecorded[user_id] = mentions(user_id)
        self._erases_of[user_id] += 1
        recorder, erase_stored = self.recorder, self.personalisation.erase_stored
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
            self._finish_erases()
        if outcome['error'] is not None:
            raise outcome['error']
        return outcome['removed']

    def _forget_finished(self, user_id: str, tell_fleet: bool, removed: dict, then: Callable, result, error):
        """The executor's end of a forget (``begin_forget``)."""
        self._erases_of[user_id] -= 1
        if self._erases_of[user_id] <= 0:
            del self._erases_of[user_id]
            self.records.unrecorded.pop(user_id, None)
        # models committed before the erase (whose commit it waited for), not sent yet: never sent now
        waiting = [entry for entry in list(self.durable_models) if entry[0] == user_id]
        for entry in waiting:
            self.durable_models.remove(entry)
        held = self._models_held.pop(user_id, 0)
        if error is not None:
            then(None, error)
            return
        removed['memory']['models_to_send'] = len(waiting) + held
        removed.update(result)
        if tell_fleet and self.params['fleet_sharing']:
            self._tell_fleet_forgotten(user_id)
        then(removed, None)

    def _report_failed_forget(self, removed: dict | None, error: BaseException | None) -> None:
        if error is not None:  # the intent record stays: the next start finishes it
            self.report('recording', f'a forget could not finish (the next start finishes it): {error}',
                        self.topics['stars/forget_person'])

    def _erase_in_background(self, run: Callable[[], dict], then: Callable) -> Erase:
        """``run()`` on the erasing thread (``node.erasing``), then ``then(result, error)`` at a ``work``."""
        if self._erasing is None:
            self._erasing = Erasing(self._wake)
        return self._erasing.submit(Erase(run, then))

    def _finish_erases(self) -> None:
        """Run the executor's end of every erase the erasing thread has done."""
        if self._erasing is not None:
            for erase in self._erasing.finished():
                erase.then(erase.result, erase.error)

    def finish_interrupted_forgets(self) -> None:
        """Finish the forgets a kill interrupted (their intent records in the record folder)."""
        if self.records.folder is not None and erasure.interrupted(self.records.folder):
            finished = erasure.finish_interrupted(self.records.folder, self.personalisation.erase_stored,
                                                  self.recorder)
            self.logger.info(f'finished {len(finished)} forget(s) a kill had interrupted')

    # -- fleet forget (docs/privacy.md) ----------------------------------------------------
    def _tell_fleet_forgotten(self, user_id: str) -> None:
        """Send peers the stars/forget_person message of ``user_id`` (no id in it), and record it."""
        payload = messages.dumps(fleet_forget.forget_message(user_id, self.personalisation.origin, self.authenticator,
                                                             self._now()))
        self._publish('stars/forget_person', payload)
        self.record('stars/forget_person', payload)

    def accept_forget_message(self, text: str) -> int:
        """A peer's stars/forget_person message (fleet sharing): everyone this node holds
        whom it names is forgotten here through ``forget_person`` (not told again), and its
        tag is kept as a tombstone, so their models and feedback are refused from now on;
        how many were forgotten. A bad or unsigned one (with feedback keys) is reported
        and changes nothing; this node's own is ignored."""
        topic = self.topics['stars/forget_person']
        try:
            payload = fleet_forget.parse_forget_message(text, self.params['max_message_bytes'], self.authenticator)
        except messages.BadMessage as error:
            self.report(error.kind, f'{error}; nobody forgotten', topic)
            return 0
        if payload['origin'] == self.personalisation.origin:
            return 0
        known = self.personalisation.known_people() | ({self.user_id} - {None})
        if self.store is not None:
            known |= self.store.known_people()
        named = fleet_forget.named_in(payload, known, self.authenticator)
        self.personalisation.keep_fleet_tombstone(fleet_forget.tombstone_of(payload, self.authenticator))
        for user_id in named:
            try:
                self.begin_forget(user_id, tell_fleet=False)
            except OSError as error:  # the intent record could not be written: nothing forgotten yet
                self.report('recording', f"a forget from {payload['origin']} could not begin: {error}", topic)
        self.logger.info(f"forget from {payload['origin']}: {len(named)} person(s) held here being forgotten, its "
                         'tombstone kept')
        return len(named)

    # -- consent and retention (docs/privacy.md) --------------------------------------------
    def accept_consent(self, text: str) -> None:
        """A stars/consent message (store_policy consented): the list it gives replaces the
        topic's last one; a bad one is reported and the list stays as it was."""
        try:
            count = self.consent.accept(text, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            self.report(error.kind, f'{error}; the consent list stays as it was', self.topics['stars/consent'])
            return
        self.logger.info(f'consent list: {count} person(s) from stars/consent, {len(self.consent.from_file)} from '
                         'consent_file')

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
        folder, recorder = self.records.folder, self.recorder
        if folder is None:
            self._retention_finished(days, removed, {}, None)
        elif in_background:
            self._erase_in_background(lambda: {'bags': erasure.erase_older(folder, cutoff, recorder)},
                                      lambda result, error: self._retention_finished(days, removed, result, error))
        else:
            try:
                self._retention_finished(days, removed, {'bags': erasure.erase_older(folder, cutoff, recorder)}, None)
            except OSError as error:
                self._retention_finished(days, removed, None, error)
        return removed

    def _retention_finished(self, days: float, removed: dict, result: dict | None, error: BaseException | None):
        removed.update(result or {})
        if error is not None:
            self.report('recording', f'retention pass not finished (the next one goes on): {error}')
        if any(any(counts.values()) for counts in removed.values()):
            self.logger.info(f'retention_days = {days:g}: erased {removed}')
