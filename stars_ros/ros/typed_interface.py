"""The ranker's typed interface (``stars_ros_msgs``, docs/interfaces.md), beside the JSON one.

Serves ``~/rank_actions`` (RankActions), ``~/rank_candidates`` (RankCandidates) and
``~/choose_question`` (ChooseQuestion), and takes ``stars/typed/feedback`` (Feedback). Each
typed message becomes its JSON twin (``stars_ros.typed_messages``) and goes to the same
``RankerCore`` as the JSON topics' messages: same checks, same scores, same error kinds, in
the response and on stars/errors. A service answers in its callback, between two batches of
the queue, so its ranking is scored by one checkpoint like every other; it is not published
on stars/ranking, and it is recorded as its JSON twin, with its markers sent, within
``AFTER_REPLY_PERIOD`` of the response.
"""
from __future__ import annotations

import time

from rclpy.qos import QoSProfile, ReliabilityPolicy
from stars_ros_msgs import msg as typed
from stars_ros_msgs.srv import ChooseQuestion, RankActions, RankCandidates

from stars_ros import messages, typed_messages
from stars_ros.ros.qos_watch import NO_SUBSCRIPTION_EVENTS, QosWatch

FEEDBACK_TOPIC = 'stars/typed/feedback'
# seconds: how late the recording and markers of answered calls may come. Doing them right
# after each response put them before the next call: 4.9 ms round trip against 1.5 ms
# (benchmarks/service_latency.py's calls, p50, docs/performance.md)
AFTER_REPLY_PERIOD = 0.1
SERVICES = {'rank_actions': RankActions, 'rank_candidates': RankCandidates, 'choose_question': ChooseQuestion}


class TypedInterface:
    """Creates the typed services and subscription on ``node`` and hands their messages to
    ``core`` (``RankerCore``); ``more_work()`` brings the node's work loop back (a fold-in
    waits). ``entities`` lists what it created, for a managed node to destroy on deactivate."""

    def __init__(self, node, core, params: dict, more_work, qos_watch: QosWatch):
        self.node, self.core, self.params, self.more_work = node, core, params, more_work
        callbacks = {'rank_actions': self._on_rank_actions, 'rank_candidates': self._on_rank_candidates,
                     'choose_question': self._on_choose_question}
        self.entities = [node.create_service(kind, f'~/{name}', callbacks[name]) for name, kind in SERVICES.items()]
        self.entities.append(node.create_subscription(
            typed.Feedback, FEEDBACK_TOPIC, self._on_feedback,
            QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE), event_callbacks=NO_SUBSCRIPTION_EVENTS))
        qos_watch.watch(self.entities[-1], publishes=False)
        self.entities.append(node.create_timer(AFTER_REPLY_PERIOD, self._after_replies))
        self._names = {name: node.resolve_service_name(f'~/{name}') for name in SERVICES}
        self._feedback_topic = node.resolve_topic_name(FEEDBACK_TOPIC)

    def _twin(self, convert, request, source: str):
        """The JSON twin of ``request``, or the (kind, message) it was refused with (reported)."""
        try:
            return convert(request), None
        except messages.BadMessage as error:
            self.core.report(error.kind, str(error), source, error.scene_id)
            return None, (error.kind, str(error))

    def _rank(self, convert, request, response, name: str):
        received, taken = time.time_ns(), self.node.get_clock().now()
        frame = self.params['frame_id']

        def answer():
            twin, refusal = self._twin(lambda r: convert(r, frame), request, self._names[name])
            payload, refusal = (None, refusal) if twin is None else self.core.rank_now(
                twin, received, taken.nanoseconds, self._names[name])
            if payload is not None:
                response.ranking = typed_messages.ranking_message(payload, typed)
                response.ranking.header.stamp = taken.to_msg()
                response.ranking.header.frame_id = frame
            return refusal
        return _answer(response, self._guarded(answer, self._names[name], request.scene_id))

    def _on_rank_actions(self, request, response):
        return self._rank(typed_messages.rank_actions_twin, request, response, 'rank_actions')

    def _on_rank_candidates(self, request, response):
        return self._rank(typed_messages.rank_candidates_twin, request, response, 'rank_candidates')

    def _on_choose_question(self, request, response):
        def answer():
            text, refusal = self._twin(lambda r: typed_messages.question_request_text(r, self.params['frame_id']),
                                       request, self._names['choose_question'])
            payload, refusal = (None, refusal) if text is None else self.core.question_now(text)
            if payload is not None:
                response.question = typed_messages.question_message(payload, typed)
            return refusal
        return _answer(response, self._guarded(answer, self._names['choose_question']))

    def _guarded(self, answer, source: str, scene_id: str = ''):
        """``answer()``'s refusal (kind, message) or None; an unexpected exception becomes
        kind internal, reported, and the node keeps serving."""
        try:
            return answer()
        except Exception as error:  # noqa: BLE001 - the node must keep serving
            refusal = ('internal', f'{type(error).__name__}: {error}')
            self.core.report(*refusal, source, scene_id or None)
            return refusal

    def _after_replies(self):
        """The recording and markers of the calls answered since the last tick (``work``)."""
        if self.core.replied:
            self.more_work()

    def _on_feedback(self, feedback):
        """Typed feedback enters the core as a value (its JSON twin, written once, for the log)."""
        twin, _ = self._twin(typed_messages.feedback_twin, feedback, self._feedback_topic)
        if twin is not None and self.core.accept_feedback(twin, self._feedback_topic):
            self.more_work()


def _answer(response, refusal):
    response.success = refusal is None
    if refusal is not None:
        response.error_kind, response.message = refusal
    return response
