"""What the ranker node does, without ROS: the queue of scene requests and the work loop
over them, problem reports, and the intake of feedback for the owner of people
(``personalisation.online.Personalisation``, which holds the model served and everything
about a person). The rest of the node's logic sits beside it, one concern a module: its
parameters and topics (``parameters``), the figures of /diagnostics (``diagnostics``), the
state store and the recording (``records``), peers' user models (``fleet_intake``), forgets
and retention (``forgetting``), batch ranking (``batching``), questions (``questions``) and
markers (``markers``). ``stars_ros.ros.ranker`` declares the parameters, turns messages
into the text this class takes and publishes the text it gives.

One thread (the node's executor) calls ``RankerCore``; the state store's thread
(``stars_ros.state``) commits feedback and people, and the recorder's flushes the bag, so
the disk never holds up the rankings. What waits for a commit comes back to the executor:
the store's thread only queues it and calls ``wake`` (a model whose ratings are committed
goes out at the next ``work``). ``work`` scores one batch of queued requests with one model
snapshot, else re-solves one user who gave feedback, so the ranking of others waits for at
most one solve; ``reload`` runs between two batches, so every
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
from stars_ros.node.consent import Consent
from stars_ros.node.diagnostics import WARNINGS, BusySpans, PeriodStats, Problems, period_report
from stars_ros.node.records import NodeRecords
from stars_ros.node.erasing import Erase
from stars_ros.node.forgetting import Forgetting
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
        self.markers_out = markers_out
        self.checkpoint_path = resolve_checkpoint(params['checkpoint'])
        predictor = Predictor.load(self.checkpoint_path)
        logger.info(f'serving {self.checkpoint_path} (fingerprint {predictor.fingerprint[:12]}, '
                    f'actions {list(predictor.actions)})')
        self.problems = Problems()
        self.queue = collections.deque()  # Pending requests
        self.questions = collections.deque()  # QuestionRequests waiting to be answered
        self.replied = collections.deque()  # (Pending, reply, ranked) of rank_now: to record, markers to send
        self._fold_in_spans = BusySpans()  # when fold-in work was done (``clock``)
        self._period_stats = PeriodStats()  # for the next diagnostics
        self.authenticator = feedback_auth.from_key_file(  # first: a bad key file leaves no recording open
            params['feedback_key_file'], lambda: self.params['feedback_max_age'], logger)
        self.consent = Consent(params['store_policy'], params['consent_file'])  # as is a bad consent file
        self.records = None  # while it opens, a problem is published and logged, not recorded
        self.records = NodeRecords(params, self.topics, node_name,
                                   {'checkpoint': self.checkpoint_path, 'fingerprint': predictor.fingerprint},
                                   self.report, logger, now, None if markers_out is None else markers_out.message_type)
        self.personalisation = Personalisation(
            predictor, params['fold_in_max_ratings'], params['fold_in_max_users'], self.report, logger,
            self.store, origin=node_name, sharing=params['fleet_sharing'], authenticator=self.authenticator,
            after_person_read=after_person_read, holders={'problem_reports': self.problems.forget})
        self.fleet = FleetIntake(params, self.topics['stars/user_model'], self.report)
        self.records.consent, self.fleet.may_store = self.consent, self.consent.allows
        self.records.withheld = self.personalisation.names_someone_erased
        self.forgetting = Forgetting(params, self.topics, self.personalisation, self.records, self.report,
                                     self._send, logger, now, self._wake, self.authenticator)
        self.forgetting.finish_interrupted()  # before restore: a person half erased is not read back
        self.personalisation.restore()
        self.apply_retention()  # at start, before serving; then on the node's timer

    @property
    def predictor(self):
        """The Predictor served: the owner of people's (``Personalisation.serving``)."""
        return self.personalisation.predictor

    @property
    def user_id(self) -> str | None:
        """The person stars/user_id says is served now."""
        return self.personalisation.served_user

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
        self.personalisation.scene_received(request.scene_id, text)
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
        self.personalisation.scene_received(request.scene_id, message)
        log_time = self._now() if log_time is None else log_time
        return self._serve([Pending(request, request.user_id or self.user_id, received, message, log_time)],
                           publish=False, source=source)[0]

    def accept_user_id(self, text: str):
        try:
            self.personalisation.served_user = messages.parse_user_id(text)
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
        if not self.params['fold_in'] and not self.personalisation.is_forgotten(feedback.user_id):
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
        return self.fleet.accept(text, self.personalisation)

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
        return bool(self.personalisation.waiting()['announce'])

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
        self.checkpoint_path = path
        self.personalisation.use(predictor)
        message = f'serving {path} (fingerprint {predictor.fingerprint})'
        self.logger.info(message)
        return True, message

    # -- work ----------------------------------------------------------------------------
    def work(self) -> bool:
        """One batch of queued requests, else one question answered, else one peer rating
        checked, else one fold-in solve, else one model sent again to peers; True when more
        work waits."""
        personalisation = self.personalisation
        try:
            self.forgetting.finish_erases()
            while self.replied:
                self._after_reply(*self.replied.popleft())
            self._send_durable_models()
            waiting = personalisation.waiting()
            if self.queue:
                self._serve([self.queue.popleft() for _ in range(min(len(self.queue), self.params['max_batch']))])
            elif self.questions:
                self._answer_question(self.questions.popleft())
            elif waiting['intake']:
                started = self._clock()
                try:
                    refused = personalisation.take_in_next()
                finally:
                    self._fold_in_spans.add(started, self._clock())
                if refused is not None:
                    self.report(*refused, self.topics['stars/user_model'])
            elif waiting['solve']:
                started = self._clock()
                try:
                    self._solve_next()
                finally:
                    ended = self._clock()
                    self._fold_in_spans.add(started, ended)
                    self._period_stats.fold_in_update((ended - started) / 1e6)
            elif waiting['announce']:
                self._publish_model(personalisation.next_to_announce())
        except Exception as error:  # noqa: BLE001 - the node must keep serving
            self.report('internal', f'{type(error).__name__}: {error}')
        return bool(self.queue or self.questions or any(personalisation.waiting().values()))

    def _solve_next(self):
        solved = self.personalisation.solve_next(self.params['fold_in_min_ratings'],
                                                 self.params['fold_in_regularisation'])
        if solved is not None:
            self._publish_model(solved[0])

    def _publish_model(self, user_id: str):
        """Send ``user_id``'s served model to peers, subscribers and the bag once the store
        has committed the ratings it was solved from (``Personalisation.publish_when_durable``;
        their own rankings use it at once)."""
        self.personalisation.publish_when_durable(user_id, self._send_model, self._wake)

    def _send_durable_models(self):
        for payload in self.personalisation.models_to_send():
            self._send_model(payload)

    def _send_model(self, payload: str):
        """Publish and record (logged when it goes out) a user model whose ratings are durable."""
        self._send('stars/user_model', payload)

    def _send(self, topic: str, payload: str):
        self._publish(topic, payload)
        self.record(topic, payload)

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
            self.personalisation.scene_ranked(request.scene_id, item.message, predictor, result.h,
                                              result.plain)
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
        if not self.personalisation.first_report_of_stranger(user_id):
            return
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
        if not self.forgetting.close(ERASING_CLOSE_WAIT):
            self.logger.warning(f'an erase still runs after {ERASING_CLOSE_WAIT:g} s: the next start finishes it')
        self.records.close(self.personalisation.flush, self._send_durable_models)

    # -- forget, fleet forget and retention (node.forgetting, docs/privacy.md) -------------------
    def begin_forget(self, user_id: str, tell_fleet: bool = True,
                     then: Callable[[dict | None, BaseException | None], None] | None = None) -> Erase | None:
        """Erase ``user_id`` everywhere this node keeps them: ``Forgetting.begin_forget``."""
        return self.forgetting.begin_forget(user_id, tell_fleet, then)

    def forget_person(self, user_id: str, tell_fleet: bool = True) -> dict:
        """``begin_forget``, waited for: what it removed where (its errors raised)."""
        return self.forgetting.forget_person(user_id, tell_fleet)

    def accept_forget_message(self, text: str) -> int:
        """A peer's stars/forget_person message: ``Forgetting.accept_forget_message``."""
        return self.forgetting.accept_forget_message(text)

    def apply_retention(self, in_background: bool = False) -> dict:
        """Erase what is older than ``retention_days``: ``Forgetting.apply_retention``."""
        return self.forgetting.apply_retention(in_background)

    # -- consent (docs/privacy.md) -----------------------------------------------------------------
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
