"""The hri_bridge node: a robot's ROS4HRI (REP 155) stack in, the ranker's topics out.

Reads who is tracked (/humans/persons/tracked), each person's engagement_status, anonymous,
alias and location_confidence (/humans/persons/<id>/...), groups and gazes
(/humans/interactions/...) and where people are (TF frames person_<id>, or with
``pose_source:=topic`` geometry_msgs/TransformStamped on hri/transforms); publishes the
served person on stars/user_id (and, for the feedback page, on stars/served_person with
whether they are anonymous), scenes on stars/scene (once the ranker is up: a node that
subscribes stars/scene and publishes stars/ranking; until then /diagnostics says it waits),
implicit outcomes on stars/feedback, and for each ranking of its scenes a decision
(stars/decision). A placement becomes a goal only when the decision changes
(``stars_ros.hri.goals``): stars/goal (geometry_msgs/PoseStamped in ``goal_frame``, a frame
that does not move with the robot, stamped when decided) and, with ``navigate_to_pose`` set,
Nav2's NavigateToPose action, cancelled on an abstain or when the person leaves, whose
success is published on stars/executed. With ``store_policy:=consented`` it relays feedback
and implicit outcomes of the people on the consent list only (``consent_file`` and the latched
stars/consent, as the ranker reads them; docs/privacy.md). The logic is ``stars_ros.hri``;
docs/hri.md has the rules, the parameters and how to point it at a robot.

    ros2 run stars_ros hri_bridge --ros-args -p base_frame:=base_link -p goal_frame:=map

Needs hri_msgs (ros-jazzy-hri-msgs); tf2_ros (ros-jazzy-tf2-ros) for ``pose_source:=tf``;
nav2_msgs (ros-jazzy-nav2-msgs) for ``navigate_to_pose``.
"""
from __future__ import annotations

import json
import re

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, TransformStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.time import Time
from std_msgs.msg import Bool, Float32, String

from stars_ros.errors import ConfigError
from stars_ros.hri.bridge import BridgeCore, BridgeSettings
from stars_ros.hri.goals import GoalPolicy, GoalSettings, GoalStep, robot_frame_goal_refusal
from stars_ros.hri.poses import TIMELESS, Pose, TransformTable
from stars_ros.hri.scene import DEFAULT_ROOM, SceneSettings
from stars_ros.ros import usage
from stars_ros.ros.qos_watch import NO_PUBLISHER_EVENTS, NO_SUBSCRIPTION_EVENTS, QosWatch
from stars_ros.ros.spinning import run_node
from stars_ros.ros.unknown_parameters import warn_unknown_overrides
from stars_ros.rotations import quaternion_of_yaw, yaw_of_quaternion

try:
    from hri_msgs.msg import EngagementLevel, Gaze, Group, IdsList
except ImportError as missing:  # the node cannot run; the package still installs
    HRI_MSGS_ERROR = f'hri_bridge needs hri_msgs (ros-jazzy-hri-msgs, ROS4HRI): {missing}'
else:
    HRI_MSGS_ERROR = None

TICK = 0.05  # s between two looks at the facts (a changed scene goes out within this)
MAX_PEOPLE = 256  # per-person subscriptions held at most
PERSON_TOPIC = re.compile(r'^/humans/persons/([^/]+)/(engagement_status|anonymous|alias|location_confidence)$')
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

PARAMETERS = {  # name: (default, description)
    'base_frame': ('base_link', "the robot's frame (REP 103): scenes are built in it"),
    'goal_frame': ('map', 'frame of stars/goal, one the navigation stack takes and that does not move with the '
                   'robot (map, odom; REP 105); empty: base_frame (needs goal_in_robot_frame)'),
    'goal_in_robot_frame': (False, 'true: allow a goal_frame that moves with the robot (base_frame, base_link, '
                            'base_footprint); refused at start otherwise'),
    'goal_position_tolerance': (0.25, 'm: a new best placement whose goal is closer than this (and within '
                                'goal_yaw_tolerance) to the goal followed sends no new goal'),
    'goal_yaw_tolerance': (0.35, 'rad: see goal_position_tolerance'),
    'goal_hysteresis': (0.05, 'score: another placement replaces the one followed only when it beats it by more '
                        'than this in the same ranking'),
    'navigate_to_pose': ('', "Nav2's NavigateToPose action to send goals to (e.g. navigate_to_pose); empty: "
                         'stars/goal only'),
    'wait_for_ranker': (True, 'send scenes only once a node subscribes stars/scene and publishes stars/ranking'),
    'pose_source': ('tf', 'tf: person_<id> frames from TF (needs tf2_ros); topic: geometry_msgs/TransformStamped '
                    'on hri/transforms (header.frame_id the parent, child_frame_id person_<id>)'),
    'max_age': (0.5, 's: an older pose, group or gaze is left out'),
    'min_confidence': (0.5, 'a person whose location_confidence is below this is left out'),
    'rate': (2.0, 'scenes a second sent to the ranker (and at once on a change of people, interactions or user)'),
    'placements': (6, 'robot placements ranked per scene (stay, 50 cm left, right, back, ahead, 100 cm left, '
                   'right, back); 0: rank the model actions in the scene instead'),
    'abstain_below': (0.5, 'abstain (no goal) when the ranking p_first_is_best is below this'),
    'outcome_window': (5.0, 's after stars/executed: disengaging within it is an implicit "disengaged", engaged '
                       'at its end "stayed"'),
    'rating_min': (0.0, "the model's lowest rating (a disengaged outcome's score)"),
    'rating_max': (1.0, "the model's highest rating (a stayed outcome's score)"),
    'room': ([float(v) for corner in DEFAULT_ROOM for v in corner], 'room polygon in base_frame, metres: x0, y0, '
             'x1, y1, ...'),
    'objects': ('[]', 'objects in base_frame, JSON: [[x, y, yaw], ...] (metres, radians)'),
    'diagnostics_period': (1.0, 's between two /diagnostics messages (and scans for per-person topics)'),
    'store_policy': ('all', "whose feedback and implicit outcomes are relayed to the ranker: 'all'; 'consented': "
                     'only those of people on the consent list (consent_file and stars/consent), the others are '
                     'dropped, counted as consent (docs/privacy.md); as the ranker\'s store_policy'),
    'consent_file': ('', "with store_policy 'consented': a file of the ids of people who agreed to be stored, one a "
                     'line (# starts a comment), joined by those stars/consent lists; empty: none'),
}


class TfPoses:
    """The pose seam over tf2 (``stars_ros.hri.poses.PoseSource``)."""

    def __init__(self, node: Node):
        import tf2_ros  # only here: a ROS install provides it, the wheels do not
        self._buffer = tf2_ros.Buffer()
        self._listener = tf2_ros.TransformListener(self._buffer, node)
        self._errors = (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException)

    def lookup(self, target_frame: str, source_frame: str) -> Pose | None:
        try:
            return pose_of(self._buffer.lookup_transform(target_frame, source_frame, Time()))
        except self._errors:
            return None


def pose_of(transform: TransformStamped) -> Pose:
    """The planar pose of ``transform``; stamped 0 (what tf2 gives for a chain of static
    transforms, /tf_static) it is static: it has no age and is never stale."""
    t, r = transform.transform.translation, transform.transform.rotation
    stamp = Time.from_msg(transform.header.stamp).nanoseconds
    return Pose(t.x, t.y, yaw_of_quaternion(r.x, r.y, r.z, r.w), stamp or TIMELESS)


class NavigateToPoseGoals:
    """Goals to Nav2's NavigateToPose action server ``action_name``: one followed at a time
    (a new goal or a cancel ends the one before); ``on_succeeded(context)`` when a goal
    succeeds, ``on_problem(detail)`` when one is refused or the server is not up."""

    def __init__(self, node: Node, action_name: str, on_succeeded, on_problem):
        try:
            from nav2_msgs.action import NavigateToPose
        except ImportError as missing:
            raise ImportError(f'navigate_to_pose needs nav2_msgs (ros-jazzy-nav2-msgs): {missing}') from None
        from action_msgs.msg import GoalStatus
        from rclpy.action import ActionClient
        self._action, self._succeeded = NavigateToPose, GoalStatus.STATUS_SUCCEEDED
        self._client, self._name = ActionClient(node, NavigateToPose, action_name), action_name
        self._on_succeeded, self._on_problem = on_succeeded, on_problem
        self._wanted = None  # the token of the goal followed (sent, perhaps not yet accepted)
        self._handle = None

    def send(self, pose: PoseStamped, context) -> None:
        self.cancel()
        if not self._client.server_is_ready():
            self._on_problem(f"NavigateToPose server '{self._name}' is not up: goal not sent")
            return
        token = self._wanted = object()
        future = self._client.send_goal_async(self._action.Goal(pose=pose))
        future.add_done_callback(lambda done: self._accepted(done.result(), token, context))

    def cancel(self) -> None:
        self._wanted = None
        if self._handle is not None:
            self._handle.cancel_goal_async()
            self._handle = None

    def _accepted(self, handle, token, context) -> None:
        if not handle.accepted:
            self._on_problem('NavigateToPose refused the goal')
            return
        if token is not self._wanted:  # cancelled or replaced while it was being accepted
            handle.cancel_goal_async()
            return
        self._handle = handle
        handle.get_result_async().add_done_callback(lambda done: self._finished(done.result(), handle, context))

    def _finished(self, result, handle, context) -> None:
        if self._handle is handle:
            self._handle = None
        if result.status == self._succeeded:
            self._on_succeeded(context)


class HriBridge(Node):
    """Subscribes to ROS4HRI, calls the core, publishes what it gives (module docstring)."""

    def __init__(self, **kwargs):
        super().__init__('hri_bridge', **kwargs)
        if HRI_MSGS_ERROR:
            raise ImportError(HRI_MSGS_ERROR)
        v = {name: self.declare_parameter(name, default, ParameterDescriptor(description=text)).value
             for name, (default, text) in PARAMETERS.items()}
        warn_unknown_overrides(self, 'hri_bridge', PARAMETERS)
        room, objects = list(v['room']), json.loads(v['objects'])
        if len(room) % 2 or not all(len(o) == 3 for o in objects):
            raise ValueError('room takes x, y pairs and objects [x, y, yaw] triples')
        scene = SceneSettings(v['base_frame'], v['max_age'], v['min_confidence'],
                              tuple(tuple(float(c) for c in o) for o in objects),
                              tuple((room[k], room[k + 1]) for k in range(0, len(room), 2)), v['placements'])
        settings = BridgeSettings(scene, v['rate'], v['goal_frame'], v['abstain_below'], v['outcome_window'],
                                  (v['rating_min'], v['rating_max']), store_policy=v['store_policy'],
                                  consent_file=v['consent_file'])
        self.qos_watch = QosWatch(self)  # endpoints keep no QoS event handlers: with 20 people, 170 of them
        if v['pose_source'] == 'tf':
            self.poses = TfPoses(self)
        elif v['pose_source'] == 'topic':
            self.poses = TransformTable()
            self._subscribe(TransformStamped, 'hri/transforms', self._on_transform, RELIABLE)
        else:
            raise ValueError(f"pose_source must be 'tf' or 'topic', got '{v['pose_source']}'")
        refusal = robot_frame_goal_refusal(settings.navigation_frame, v['base_frame'], v['goal_in_robot_frame'])
        if refusal:
            raise ValueError(refusal)
        self.goals = GoalPolicy(GoalSettings(v['goal_position_tolerance'], v['goal_yaw_tolerance'],
                                             v['goal_hysteresis']))
        self.core = BridgeCore(settings, self.poses, lambda: self.get_clock().now().nanoseconds)
        self.wait_for_ranker, self.ranker_up = v['wait_for_ranker'], False
        self.out = {name: self._advertise(String, name, qos) for name, qos in (
            ('stars/user_id', LATCHED), ('stars/served_person', LATCHED), ('stars/scene', RELIABLE),
            ('stars/feedback', RELIABLE), ('stars/decision', RELIABLE))}
        self._served_sent = None  # the (Served, kept) last published on stars/served_person
        self.goal_out = self._advertise(PoseStamped, 'stars/goal', LATCHED)
        self.executed_out = self._advertise(String, 'stars/executed', RELIABLE)
        self.navigation = (NavigateToPoseGoals(self, v['navigate_to_pose'], self._on_navigated,
                                               lambda detail: self.core.report('navigation', detail))
                           if v['navigate_to_pose'] else None)
        self.diagnostics_out = self._advertise(DiagnosticArray, '/diagnostics', 10)
        self._subscribe(IdsList, '/humans/persons/tracked', self._on_tracked, LATCHED)
        self._subscribe(Group, '/humans/interactions/groups', self._on_group, RELIABLE)
        self._subscribe(Gaze, '/humans/interactions/gazing', self._on_gaze, RELIABLE)
        self._subscribe(String, 'stars/ranking', self._on_ranking, RELIABLE)
        self._ranking_topic = self.resolve_topic_name('stars/ranking')
        self._subscribe(String, 'stars/executed', lambda m: self.core.on_executed(m.data), RELIABLE)
        self._subscribe(String, 'stars/person_feedback', self._on_person_feedback, RELIABLE)
        if self.core.consent.restricted:  # latched, as the ranker subscribes it (node.parameters.topic_qos)
            self._subscribe(String, 'stars/consent', self._on_consent, LATCHED)
        self.person_subscriptions: dict[str, list] = {}
        self.counts = {'scenes_sent': 0, 'decisions': 0, 'goals': 0, 'goals_cancelled': 0, 'outcomes_sent': 0,
                       'feedback_relayed': 0}
        self.goal_reason = ''
        self.create_timer(TICK, self._tick)
        self.create_timer(v['diagnostics_period'], self._diagnose)

    def _advertise(self, msg_type, topic: str, qos):
        publisher = self.create_publisher(msg_type, topic, qos, event_callbacks=NO_PUBLISHER_EVENTS)
        self.qos_watch.watch(publisher, publishes=True)
        return publisher

    def _subscribe(self, msg_type, topic: str, callback, qos):
        subscription = self.create_subscription(msg_type, topic, callback, qos, event_callbacks=NO_SUBSCRIPTION_EVENTS)
        self.qos_watch.watch(subscription, publishes=False)
        return subscription

    # -- ROS4HRI in -----------------------------------------------------------------------
    def _on_tracked(self, msg):
        self.core.on_tracked(msg.ids)
        self._follow_people(set(msg.ids))

    def _follow_people(self, wanted: set):
        """Per-person subscriptions for ``wanted`` ids (and ids that publish while not tracked,
        so their messages are diagnosed), at most MAX_PEOPLE; others are dropped."""
        for person_id in [i for i in self.person_subscriptions if i not in wanted]:
            gone = self.person_subscriptions.pop(person_id)
            self.qos_watch.forget(gone)
            for subscription in gone:
                self.destroy_subscription(subscription)
        for person_id in sorted(wanted - set(self.person_subscriptions))[:MAX_PEOPLE - len(self.person_subscriptions)]:
            base = f'/humans/persons/{person_id}/'
            self.person_subscriptions[person_id] = [
                self._subscribe(EngagementLevel, base + 'engagement_status',
                                self._fact('engagement_status', person_id, lambda m: m.level), RELIABLE),
                self._subscribe(Bool, base + 'anonymous', self._fact('anonymous', person_id), LATCHED),
                self._subscribe(String, base + 'alias', self._fact('alias', person_id), LATCHED),
                self._subscribe(Float32, base + 'location_confidence', self._fact('location_confidence', person_id),
                                RELIABLE)]

    def _fact(self, field: str, person_id: str, value=lambda m: m.data):
        return lambda msg: self.core.on_person(field, person_id, value(msg))

    def _on_group(self, msg):
        self.core.on_group(msg.group_id, list(msg.members), Time.from_msg(msg.header.stamp).nanoseconds)

    def _on_gaze(self, msg):
        self.core.on_gaze(msg.sender, msg.receiver, Time.from_msg(msg.header.stamp).nanoseconds)

    def _on_transform(self, msg: TransformStamped):
        try:
            self.poses.put(msg.header.frame_id, msg.child_frame_id, pose_of(msg))
        except ValueError as error:
            self.core.on_transform_problem(str(error))

    # -- the ranker and the robot ---------------------------------------------------------
    def _on_ranking(self, msg):
        frame = self.core.settings.navigation_frame
        decided_at = self.get_clock().now()
        decision = self.core.on_ranking(msg.data, self.poses.lookup(frame, self.core.settings.scene.base_frame))
        if decision is None:
            return
        self.out['stars/decision'].publish(String(data=json.dumps(decision.to_json())))
        self.counts['decisions'] += 1
        served = self.core.sent_for(decision.scene_id)
        person_id = served.person_id if served else None
        step = self.goals.on_decision(decision, person_id)
        self._follow(step)
        if step.send is not None:
            goal = PoseStamped()
            goal.header.frame_id, goal.header.stamp = frame, decided_at.to_msg()
            goal.pose.position.x, goal.pose.position.y = step.send.x, step.send.y
            q = goal.pose.orientation
            q.x, q.y, q.z, q.w = quaternion_of_yaw(step.send.yaw)
            self.goal_out.publish(goal)
            self.counts['goals'] += 1
            if self.navigation is not None:
                self.navigation.send(goal, (decision.scene_id, decision.choice, person_id))

    def _follow(self, step: GoalStep):
        """Keep why the goal changed (or not), and cancel the goal followed when told."""
        self.goal_reason = step.reason or self.goal_reason
        if step.cancel:
            self.counts['goals_cancelled'] += 1
            if self.navigation is not None:
                self.navigation.cancel()

    def _on_navigated(self, context):
        """A NavigateToPose goal succeeded: the robot did it, said on stars/executed."""
        scene_id, candidate, person_id = context
        executed = {'scene_id': scene_id, 'candidate': candidate}
        if person_id is not None:
            executed['person_id'] = person_id
        self.executed_out.publish(String(data=json.dumps(executed)))

    def _on_person_feedback(self, msg):
        payload = self.core.on_person_feedback(msg.data)
        if payload is not None:
            self.out['stars/feedback'].publish(String(data=json.dumps(payload)))
            self.counts['feedback_relayed'] += 1

    def _on_consent(self, msg):
        count = self.core.on_consent(msg.data)
        if count is not None:
            self.get_logger().info(f'consent list: {count} person(s) from stars/consent, '
                                   f'{len(self.core.consent.from_file)} from consent_file')

    def _ranker_listens(self) -> bool:
        """Whether a node both subscribes stars/scene and publishes stars/ranking (the ranker
        is up and serving; a managed ranker subscribes only once active)."""
        readers = {(i.node_namespace, i.node_name)
                   for i in self.get_subscriptions_info_by_topic(self.out['stars/scene'].topic_name)}
        return bool(readers) and any((i.node_namespace, i.node_name) in readers
                                     for i in self.get_publishers_info_by_topic(self._ranking_topic))

    def _tick(self):
        if self.wait_for_ranker and not self.ranker_up:
            self.ranker_up = self._ranker_listens()
            if self.ranker_up:
                self.get_logger().info('the ranker is up: sending scenes')
        out = self.core.tick(send_scene=self.ranker_up or not self.wait_for_ranker)
        self._follow(self.goals.on_served(self.core.served.person_id))
        if out.user_id is not None:
            self.out['stars/user_id'].publish(String(data=out.user_id))
            self.get_logger().info(f'serving {self.core.served.describe()}')
        served = (self.core.served, self.core.served_kept())
        if served != self._served_sent:  # for the feedback page: whom to ask, and whether it is kept
            self._served_sent = served
            self.out['stars/served_person'].publish(String(data=json.dumps(
                {'person_id': served[0].person_id, 'anonymous': served[0].anonymous, 'kept': served[1]})))
        if out.scene is not None:
            self.out['stars/scene'].publish(String(data=json.dumps(out.scene)))
            self.counts['scenes_sent'] += 1
        for feedback in out.feedback:
            self.out['stars/feedback'].publish(String(data=json.dumps(feedback)))
            self.counts['outcomes_sent'] += 1

    def _diagnose(self):
        """/diagnostics: one status of counts, served person and problems by kind; a scan for
        per-person topics of ids not tracked (their messages are then diagnosed)."""
        found = {m.group(1) for name, _ in self.get_topic_names_and_types() if (m := PERSON_TOPIC.match(name))}
        self._follow_people(set(self.core.people.tracked) | found)
        for _, problem in self.qos_watch.new_mismatches():
            self.core.report('qos', problem)
        if self.wait_for_ranker and self.ranker_up:
            self.ranker_up = self._ranker_listens()  # a ranker that went away is waited for again
        period, totals = self.core.problems.take_period()
        built = self.core.last_scene
        tracked, in_scene = len(self.core.people.members()), len(built.people) if built else 0
        values = {'served': self.core.served.describe(), 'tracked': len(self.core.people.tracked),
                  'in_scene': in_scene, 'ranker': 'up' if self.ranker_up or not self.wait_for_ranker else 'waiting',
                  'goal_reason': self.goal_reason, **self.counts,
                  **{f'left_out.{k}': n for k, n in self.core.left_out_total.items()},
                  **{f'problems.{k}': n for k, n in totals.items()},
                  **{f'latest.{k}': detail for k, (_, detail) in period.items()}}
        warnings = []
        if values['ranker'] == 'waiting':
            warnings.append(f'waiting for the ranker (a node that subscribes {self.out["stars/scene"].topic_name} '
                            f'and publishes {self._ranking_topic}): no scene sent yet')
        if tracked and not in_scene and built is not None:
            reasons = ', '.join(f'{reason} {len(ids)}' for reason, ids in sorted(built.left_out.items()))
            warnings.append(f'{tracked} people tracked, none in the scene (left out: {reasons or "none"})')
        warnings += [f'{k}: {n}' for k, (n, _) in period.items()]
        status = DiagnosticStatus(name=f'{self.get_fully_qualified_name()}: hri_bridge',
                                  level=DiagnosticStatus.WARN if warnings else DiagnosticStatus.OK,
                                  message='; '.join(warnings) or 'ok',
                                  hardware_id='ros4hri',
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_out.publish(array)
        for kind, (count, detail) in period.items():
            self.get_logger().warning(f'[{kind}] {detail} ({count} in the last period)')


def main(args=None):
    if usage.print_help_if_asked('hri_bridge', __doc__, PARAMETERS, 'ros2 run stars_ros hri_bridge --ros-args '
                                 '-p base_frame:=base_link -p goal_frame:=map', args):
        return
    run_node('hri_bridge', HriBridge, fatal=(ImportError, ValueError, ConfigError), args=args)


if __name__ == '__main__':
    main()
