"""The ranker node: personalised rankings of robot actions (or candidate scenes) per scene.

Subscribes ``stars/scene``, ``stars/user_id`` (transient local), ``stars/feedback`` and
``stars/question_request``; publishes ``stars/ranking``, ``stars/errors``, ``stars/question``,
``stars/user_model`` (transient local), ``stars/markers`` (visualization_msgs/MarkerArray,
transient local: the latest scene in ``frame_id``) and ``/diagnostics``; serves ``~/reload``. The
typed interface (``stars_ros_msgs``, ``ros.typed_interface``, docs/interfaces.md) beside it:
services ``~/rank_actions``, ``~/rank_candidates``, ``~/choose_question`` and the topic
``stars/typed/feedback``. With ``fleet_sharing`` it also subscribes to
``stars/user_model`` (its peers', and its own, which changes nothing) and sends every
folded-in user again when a subscriber joins that topic (``stars_ros.personalisation.fleet``). See README.md
("The ranker node") and docs/personalisation.md. Run with ``ros2 run stars_ros ranker`` or
``python -m stars_ros.ros.ranker --ros-args -p checkpoint:=PATH``.

Threads: the executor thread does the serving. The scene callback validates and queues a
request (beyond ``queue_depth`` waiting it is refused as ``overload``); the guard condition's
callback scores up to ``max_batch`` of them in one pass with one model snapshot, or solves a
fold-in. rclpy's executor takes one message per subscription per wait, and runs a node's
subscriptions before its guard conditions: so while the scenes it takes had waited in the
middleware, the guard condition's callback puts each batch off by one wait at a time, at most
``queue_depth`` times in a row, and a flood fills the queue (and is refused as overload)
rather than the middleware's history (dropped without a word); a steady stream is scored as
it comes. Other ready callbacks (feedback, ``~/reload``,
parameters) have their turn between two passes. Handing requests to a worker thread cost more
in waiting for the GIL (docs/performance.md). The callbacks share the node's default,
mutually exclusive callback group, so a multi-threaded executor keeps this order too.

The work itself, ROS-free, is ``stars_ros.node.core.RankerCore``; this module declares the
parameters (``node.core.PARAMETERS``; an override of a name it does not declare is warned
about), creates the topics, the services and the timers, and passes messages to and from
the core. ``ros2 run stars_ros managed_ranker`` is the same node managed (lifecycle):
``ros.managed_ranker``.
"""
from __future__ import annotations

import gc
import os
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.exceptions import InvalidHandle
from rclpy.guard_condition import GuardCondition
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.service import Service
from rclpy.subscription import Subscription
from rclpy.task import Future
from rclpy.timer import Timer
from std_msgs.msg import String
from std_srvs.srv import Trigger
from threadpoolctl import threadpool_limits
from visualization_msgs.msg import MarkerArray

from stars_ros.errors import CheckpointError, ConfigError, StoreError
from stars_ros_msgs.srv import ForgetPerson
from stars_ros.node.parameters import PARAMETERS, TOPICS, topic_qos
from stars_ros.ros import usage
from stars_ros.ros.markers import MarkerOutput
from stars_ros.ros.qos_watch import NO_PUBLISHER_EVENTS, NO_SUBSCRIPTION_EVENTS, QosWatch
from stars_ros.ros.replies import resend_dropped
from stars_ros.ros.spinning import run_node, spin_until_shutdown
from stars_ros.ros.typed_interface import TypedInterface
from stars_ros.ros.unknown_parameters import warn_unknown_overrides

# s: how long a thread that holds the GIL keeps it while another waits (Python's default 5 ms);
# the state store's writer thread then holds a ranking back for at most this long
SWITCH_INTERVAL = 0.001
RETENTION_CHECK_PERIOD = 3600.0  # s between two passes of retention_days (one runs at start too)
LEVELS = {'ok': DiagnosticStatus.OK, 'warn': DiagnosticStatus.WARN, 'error': DiagnosticStatus.ERROR}


def _descriptor(name: str) -> ParameterDescriptor:
    """The parameter's description, and what rclpy then refuses on its own: a value of
    another type than the default's, one outside the range, any change to a read-only one."""
    default, description, read_only, limits = PARAMETERS[name]
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    if isinstance(default, int) and limits:
        descriptor.integer_range = [IntegerRange(from_value=limits[0], to_value=limits[1], step=1)]
    elif isinstance(default, float) and limits:
        descriptor.floating_point_range = [FloatingPointRange(from_value=limits[0], to_value=limits[1])]
    return descriptor


def _received(info: dict) -> int:
    """When the middleware received a message (time.time_ns; now if it does not stamp)."""
    return info.get('received_timestamp') or time.time_ns()


class RankerParts:
    """The ranker's life in three steps, shared by ``RankerNode`` (all three at once) and the
    managed ``managed_ranker.ManagedRankerNode`` (configure, activate, deactivate): declare the
    parameters; configure (load the checkpoint into the core, create the publishers); activate
    (create the subscriptions, services and timers that serve). Mixed into a ``Node``."""

    core, _configured, _serving, _more_work = None, (), (), None  # before configure, after cleanup
    _scoring_due = False  # the guard condition was triggered to score (by a scene, or a pass with more)
    _scenes_meanwhile = _put_off = 0  # scenes taken since then that had waited; times in a row put off
    _due_since = 0  # time.time_ns() when the scoring became due

    def _declare_parameters(self):
        self.params = {name: self.declare_parameter(name, spec[0], _descriptor(name)).value
                       for name, spec in PARAMETERS.items()}
        self.add_post_set_parameters_callback(self._on_parameters_set)
        warn_unknown_overrides(self, 'ranker', PARAMETERS)

    def _configure(self):
        durability = {True: DurabilityPolicy.TRANSIENT_LOCAL, False: DurabilityPolicy.VOLATILE}
        self.qos = {topic: QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                                      durability=durability[latched])
                    for topic, (depth, latched) in topic_qos(self.params).items()}
        sharing = self.params['fleet_sharing']
        # no default QoS event handlers: each would join every executor turn's wait set; QosWatch checks instead
        self.publishers_by_topic = {
            topic: self.create_publisher(String, topic, self.qos[topic], event_callbacks=(
                PublisherEventCallbacks(matched=self._on_model_subscriber,  # re-sends every user to a newcomer
                                        use_default_callbacks=False)
                if sharing and topic == 'stars/user_model' else NO_PUBLISHER_EVENTS))
            for topic in ('stars/ranking', 'stars/errors', 'stars/question', 'stars/user_model')}
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10,
                                                     event_callbacks=NO_PUBLISHER_EVENTS)
        markers_pub = self.create_publisher(MarkerArray, 'stars/markers', self.qos['stars/markers'],
                                            event_callbacks=NO_PUBLISHER_EVENTS)
        self.qos_watch = QosWatch(self)
        for publisher in [*self.publishers_by_topic.values(), self.diagnostics_pub, markers_pub]:
            self.qos_watch.watch(publisher, publishes=True)
        type_hash = next((str(i.topic_type_hash)
                          for i in self.get_publishers_info_by_topic(markers_pub.topic_name)), '')
        self._configured = [*self.publishers_by_topic.values(), self.diagnostics_pub, markers_pub]
        # imported here, not at the top: the node's DDS participant is up, and discoverable by
        # peers that start with it, during the half second this import and the checkpoint take
        from stars_ros.node.core import RankerCore

        self.core = RankerCore(self.params, {name: self.resolve_topic_name(name) for name in TOPICS},
                               self.get_fully_qualified_name(), self._publish, ContextLogger(self),
                               lambda: self.get_clock().now().nanoseconds,
                               MarkerOutput(markers_pub, type_hash),
                               # a stored person's ratings, read at their first feedback, live as long as the
                               # model: out of the collector's generations too (a full collection walking
                               # them held the executor 20-33 ms)
                               after_person_read=gc.freeze, wake=self._wake_work)
        self._configure_privacy()

    def _activate(self):
        callbacks = {'stars/scene': self._on_scene, 'stars/user_id': lambda msg: self.core.accept_user_id(msg.data),
                     'stars/feedback': self._on_feedback, 'stars/question_request': self._on_question_request}
        if self.params['fleet_sharing']:
            callbacks['stars/user_model'] = self._on_user_model
        subscriptions = {topic: self.create_subscription(String, topic, callback, self.qos[topic],
                                                         event_callbacks=NO_SUBSCRIPTION_EVENTS)
                         for topic, callback in callbacks.items()}
        for subscription in subscriptions.values():
            self.qos_watch.watch(subscription, publishes=False)
        self._scoring_due, self._scenes_meanwhile, self._put_off = False, 0, 0
        self._more_work = self.create_guard_condition(self._on_more_work)
        self._serving = [*subscriptions.values(), self._more_work,
                         self.create_service(Trigger, '~/reload', self._on_reload),
                         self.create_service(ForgetPerson, '~/forget_person', self._on_forget_person,
                                             callback_group=MutuallyExclusiveCallbackGroup()),
                         self.create_timer(self.params['diagnostics_period'], self._publish_diagnostics),
                         *TypedInterface(self, self.core, self.params, self._more_work.trigger,
                                         self.qos_watch).entities]
        self._serving += self._activate_privacy()
        for service in self._serving:
            if isinstance(service, Service):  # answers to a client that called as it found the service
                resend_dropped(self, service)

    def _configure_privacy(self):
        """With fleet sharing, the publisher of stars/forget_person (docs/privacy.md)."""
        if self.params['fleet_sharing']:
            publisher = self.create_publisher(String, 'stars/forget_person', self.qos['stars/forget_person'],
                                              event_callbacks=NO_PUBLISHER_EVENTS)
            self.qos_watch.watch(publisher, publishes=True)
            self.publishers_by_topic['stars/forget_person'] = publisher
            self._configured.append(publisher)

    def _activate_privacy(self) -> list:
        """Peers' forgets (fleet sharing), the consent list (store_policy consented) and the
        retention timer: the entities they add to serving."""
        callbacks = {}
        if self.params['fleet_sharing']:
            callbacks['stars/forget_person'] = self._on_forget_message
        if self.params['store_policy'] == 'consented':
            callbacks['stars/consent'] = lambda msg: self.core.accept_consent(msg.data)
        entities = []
        for topic, callback in callbacks.items():
            subscription = self.create_subscription(String, topic, callback, self.qos[topic],
                                                    event_callbacks=NO_SUBSCRIPTION_EVENTS)
            self.qos_watch.watch(subscription, publishes=False)
            entities.append(subscription)
        entities.append(self.create_timer(RETENTION_CHECK_PERIOD,
                                          lambda: self.core.apply_retention(in_background=True)))
        return entities

    def _on_forget_message(self, msg: String):
        if self.core.accept_forget_message(msg.data):
            self._more_work.trigger()

    def _deactivate(self):
        """Stop serving: every subscription, service, timer and guard condition of ``_activate`` goes."""
        destroy = {Subscription: self.destroy_subscription, Service: self.destroy_service, Timer: self.destroy_timer,
                   GuardCondition: self.destroy_guard_condition}
        self.qos_watch.forget([entity for entity in self._serving if isinstance(entity, Subscription)])
        self._more_work = None
        for entity in self._serving:
            destroy[type(entity)](entity)
        self._serving = ()

    def _unconfigure(self):
        """Close the core (recording, state store) and destroy the publishers of ``_configure``."""
        self.close()
        for publisher in self._configured:
            self.destroy_publisher(publisher)
        self._configured, self.core = (), None

    def _on_parameters_set(self, parameters):
        """Apply what rclpy accepted: the descriptors have checked type, range and read-only."""
        self.params.update({p.name: p.value for p in parameters if p.name in PARAMETERS})

    def _publish(self, topic: str, text: str):
        try:
            self.publishers_by_topic[topic].publish(String(data=text))
        except (InvalidHandle, RuntimeError):  # RuntimeError: rclpy's RCLError
            # a signal shut ROS down during the work: nothing goes out any more (what the work
            # recorded is in the bag); shutting down, a thread of close() publishes errors (logged
            # and recorded) and models (a model whose write the close committed is in the store)
            if self.context.ok() and topic not in ('stars/errors', 'stars/user_model'):
                raise

    def _publish_diagnostics(self):
        for topic, problem in self.qos_watch.new_mismatches():
            self.core.report('qos', problem, topic)
        level, summary, values, kinds = self.core.diagnostics()
        name = self.get_fully_qualified_name()
        statuses = [DiagnosticStatus(level=LEVELS[level], name=f'{name}: ranker', message=summary, hardware_id=name,
                                     values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]
        statuses += [DiagnosticStatus(level=LEVELS[kind_level], name=f'{name}: {kind}', message=detail,
                                      hardware_id=name, values=[KeyValue(key='count', value=str(count))])
                     for kind, kind_level, count, detail in kinds]
        array = DiagnosticArray(status=statuses)
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(array)

    def _on_scene(self, msg: String, info: dict):
        """Queue this request; the guard condition's callback scores it (``_on_more_work``)."""
        received = _received(info)
        self.core.accept_scene(msg.data, received)
        if not self._scoring_due:
            self._scoring_due, self._due_since = True, time.time_ns()
            self._more_work.trigger()
        elif received <= self._due_since:  # it waited in the middleware: more may wait behind it
            self._scenes_meanwhile += 1

    def _on_more_work(self):
        """Score a batch, fold in, send what waits. A scene taken since this was triggered
        (in this wait: subscriptions run first) that the middleware had received before the
        scoring became due says more may wait there: the scoring is put off by one wait, at
        most ``queue_depth`` times in a row, so that many requests waiting are taken per batch
        scored, and those beyond the queue are refused as overload rather than dropped by the
        middleware's history. A scene that came after is scored in this batch, at once."""
        if self._scenes_meanwhile and self._put_off < self.params['queue_depth']:
            self._scenes_meanwhile = 0
            self._put_off += 1
            self._more_work.trigger()
            return
        self._scenes_meanwhile = self._put_off = 0
        self._scoring_due, self._due_since = self.core.work(), time.time_ns()
        if self._scoring_due:
            self._more_work.trigger()

    def _on_feedback(self, msg: String):
        if self.core.accept_feedback(msg.data):
            self._more_work.trigger()

    def _on_question_request(self, msg: String):
        if self.core.accept_question_request(msg.data):
            self._more_work.trigger()

    def _on_user_model(self, msg: String):
        if self.core.accept_user_model(msg.data):
            self._more_work.trigger()

    def _on_model_subscriber(self, info):
        """A subscriber joined stars/user_model: the history a late joiner gets holds the last
        messages, not the last of each user, so every folded-in user is sent again."""
        if info.current_count_change > 0 and self.core.announce():
            self._more_work.trigger()

    def _on_reload(self, request, response):
        response.success, response.message = self.core.reload()
        if response.success:
            self._more_work.trigger()
        return response

    async def _on_forget_person(self, request, response):
        """~/forget_person: erase the person everywhere (``RankerCore.begin_forget``),
        answering with what was removed where once the store and the bags are done; the
        executor serves others meanwhile (this callback's own group waits, not the node's).
        A failure is answered, the node serves on."""
        forgotten = Future()
        try:
            self.core.begin_forget(request.user_id, then=lambda removed, error: forgotten.set_result((removed, error)))
        except (ValueError, OSError, StoreError) as error:
            forgotten.set_result((None, error))
        removed, error = await forgotten
        if error is not None:
            response.success, response.message = False, f'not forgotten: {error}'
            return response
        places = [(f'{place}/{what}', count) for place, counts in removed.items() for what, count in counts.items()]
        response.success = True
        response.removed_places = [place for place, _ in places]
        response.removed_counts = [int(count) for _, count in places]
        return response

    def _wake_work(self):
        """From the state store's thread: a committed model waits for the executor to send it."""
        guard = self._more_work
        if guard is not None:
            try:
                guard.trigger()
            except InvalidHandle:  # deactivated meanwhile: it goes out at the next work
                pass

    def close(self):
        """Close the state store and the recording (clean shutdown); nothing before configure.
        Called after ``destroy_node``, which takes the node's /rosout publisher with it: a
        signal has shut the context down by then, and each line logged while that publisher
        still existed would end in "Failed to publish log message to rosout: publisher's
        context is invalid"."""
        if self.core is not None:
            self.core.close()


class ContextLogger:
    """The core's logger: the node's while its context is up, once a signal has shut that
    down a logger of another name, which rcl's /rosout handler does not publish for. A line
    the core logs between the signal and ``destroy_node`` (a report of the work in hand) would
    otherwise end in "Failed to publish log message to rosout: publisher's context is invalid"."""

    def __init__(self, node):
        self._node = node
        self._after_shutdown = get_logger(f'stars_ros.{node.get_name()}')

    def _logger(self):
        return self._node.get_logger() if self._node.context.ok() else self._after_shutdown

    def info(self, line: str) -> None:
        self._logger().info(line)

    def warning(self, line: str) -> None:
        self._logger().warning(line)

    def error(self, line: str) -> None:
        self._logger().error(line)


class RankerNode(RankerParts, Node):
    """Serves rankings from a StARS checkpoint as soon as it is made; see the module docstring."""

    def __init__(self, **kwargs):
        Node.__init__(self, 'ranker', **kwargs)
        self._declare_parameters()
        self._configure()
        self._activate()


def one_thread_per_library():
    """The executables' threads, set in their ``main``, never by a node (one composed into
    another process leaves that process's settings alone): numpy's and scipy's OpenBLAS spread
    products above ~0.26 M multiply-adds (a fold-in solve over 200 ratings, a batch of scenes)
    over every core, and their idle workers then spin on the cores the executor, the DDS
    threads and the node's neighbours need; torch (tabular checkpoints only) likewise. One
    thread each, unless the environment's OPENBLAS_NUM_THREADS or OMP_NUM_THREADS says otherwise."""
    os.environ.setdefault('OMP_NUM_THREADS', '1')  # read by torch when a tabular checkpoint imports it
    os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # read by a BLAS loaded later (scipy's, at configure)
    threadpool_limits(int(os.environ['OPENBLAS_NUM_THREADS']), user_api='blas')  # those loaded now: numpy's


def serve(node):
    """Spin ``node`` until shutdown, the imports and the model out of the collector's way."""
    gc.collect()
    gc.freeze()  # the model and imports leave the collector's generations: full
    sys.setswitchinterval(SWITCH_INTERVAL)
    spin_until_shutdown(node)  # collections while serving then walk only what requests create


def main(args=None):
    if usage.print_help_if_asked('ranker', __doc__, PARAMETERS,
                                 'ros2 run stars_ros ranker --ros-args -p checkpoint:='
                                 '$(ros2 pkg prefix --share stars_ros)/models/socnav1_gat_stars.pt -p top_k:=3', args):
        return
    one_thread_per_library()
    run_node('ranker', RankerNode, serve, (CheckpointError, ConfigError), args, close=RankerNode.close)


if __name__ == '__main__':
    main()
