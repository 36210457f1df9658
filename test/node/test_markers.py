"""stars/markers without ROS: SocNav1 centimetres (+y ahead, +x right) become REP 103 metres
(x forward, y left), one marker per entity and candidate with stable ids, candidates placed
where their robot stands and coloured by score, entities tinted by their effect; the core
builds them after each ranking only when somebody listens or the bag records them."""
import json
import math

import pytest
from rosbags.typesys import Stores, get_typestore

from core_harness import Node, drain
from stars_ros import messages, recording
from stars_ros.data.scene_graph import entity_nodes
from stars_ros.data.scene_source import placement_candidates, scene_request
from stars_ros.model.explain import Why
from stars_ros.model.predictor import Ranked
from stars_ros.node.core import RankerCore
from stars_ros.node.parameters import PARAMETERS, TOPICS
from stars_ros.data.frames import heading_yaw, to_rep103
from stars_ros.node.markers import encode_marker_array, ranking_markers, scene_markers

ROOM = [[-300, -300], [300, -300], [300, 300], [-300, 300], [-300, -300]]
SCENE = {'robot': {'id': 0}, 'room': ROOM,
         'humans': [{'id': 1, 'xPos': 0, 'yPos': 100, 'orientation': 0},     # 1 m ahead, facing the robot
                    {'id': 2, 'xPos': 50, 'yPos': 0, 'orientation': 90}],    # 0.5 m to the right, facing right
         'objects': [{'id': 3, 'xPos': -200, 'yPos': 0, 'orientation': 0}],  # 2 m to the left
         'links': [[1, 2, 'interact'], [2, 1, 'interact']]}


MARKER_ARRAY_DEFINITION = get_typestore(Stores.ROS2_JAZZY).generate_msgdef('visualization_msgs/msg/MarkerArray',
                                                                          ros_version=2)[0]


def _by(markers):
    return {(m.ns, m.id): m for m in markers}


def test_socnav1_centimetres_become_rep103_metres():
    assert to_rep103(0, 100) == (1.0, 0.0)          # ahead: +x
    assert to_rep103(100, 0) == (0.0, -1.0)         # right: -y
    assert heading_yaw(0) == pytest.approx(math.pi)        # facing the robot: backwards
    assert heading_yaw(90) == pytest.approx(-math.pi / 2)  # facing the robot's right
    assert heading_yaw(180) == pytest.approx(0.0, abs=1e-12)
    markers = _by(scene_markers(SCENE))
    assert markers['humans', 1].position[:2] == (1.0, 0.0) and markers['humans', 1].kind == 'ARROW'
    assert markers['humans', 1].yaw == pytest.approx(math.pi)
    assert markers['humans', 2].position[:2] == (0.0, -0.5)
    assert markers['objects', 3].position[:2] == (0.0, 2.0) and markers['objects', 3].kind == 'CUBE'
    wall = markers['walls', 0]  # (-300, -300) -> (300, -300): 3 m behind, from left to right
    assert [p[:2] for p in wall.points] == [(-3.0, 3.0), (-3.0, -3.0)] and wall.kind == 'LINE_LIST'
    assert [p[:2] for p in markers['interactions', 0].points] == [(1.0, 0.0), (0.0, -0.5)]
    assert markers['robot', 0].position[:2] == (0.0, 0.0)


def test_one_marker_per_entity_and_the_robot_with_stable_ids():
    markers = scene_markers(SCENE)
    assert len(markers) == 1 + len(entity_nodes(SCENE))  # room, 2 humans, 1 object, 4 walls, 1 interaction
    assert len({(m.ns, m.id) for m in markers}) == len(markers)
    assert [(m.ns, m.id) for m in markers] == [(m.ns, m.id) for m in scene_markers(SCENE)]
    assert {m.ns for m in markers} == {'robot', 'room', 'humans', 'objects', 'walls', 'interactions'}


def test_entities_are_tinted_and_sized_by_their_effect():
    plain = _by(scene_markers(SCENE))
    tinted = _by(scene_markers(SCENE, {1: 0.4, 3: -0.1}))
    raises, lowers = tinted['humans', 1], tinted['objects', 3]
    assert raises.color[1] > raises.color[0] and lowers.color[0] > lowers.color[1]  # green, red
    assert raises.color[3] == 1.0 and lowers.color[3] < raises.color[3]
    assert raises.scale[0] > plain['humans', 1].scale[0] and lowers.scale[0] < raises.scale[0]
    assert tinted['humans', 2] == plain['humans', 2]  # not named: as it is


def test_candidates_stand_where_their_robot_is_coloured_by_score():
    candidates = placement_candidates(SCENE, 3)  # stay, left_50cm, right_50cm
    request = messages.SceneRequest('s', None, tuple(c['graph'] for c in candidates),
                                    tuple(c['candidate'] for c in candidates))
    why = Why(0.5, 0.1, 0.0, 'prior', ((1, 'human', 0.3),))
    ranked = [Ranked('right_50cm', 0.9, 1, None, why), Ranked('stay', 0.5, 2), Ranked('left_50cm', 0.1, 3)]
    markers = ranking_markers(request, ranked)
    assert len(markers) == 1 + len(entity_nodes(SCENE)) + 3
    discs = {m.label.split()[0]: m for m in markers if m.ns == 'candidates'}
    assert [m.id for m in markers if m.ns == 'candidates'] == [0, 1, 2]
    assert discs['stay'].position[:2] == pytest.approx((0.0, 0.0), abs=1e-9)
    assert discs['left_50cm'].position[:2] == pytest.approx((0.0, 0.5), abs=1e-9)   # left: +y
    assert discs['right_50cm'].position[:2] == pytest.approx((0.0, -0.5), abs=1e-9)
    assert discs['right_50cm'].color[:2] == pytest.approx((0.0, 0.8))  # best: green, opaque, larger
    assert discs['right_50cm'].color[3] == 1.0 and discs['right_50cm'].scale[0] > discs['stay'].scale[0]
    assert discs['left_50cm'].color[0] == pytest.approx(1.0) and discs['left_50cm'].color[3] < 1.0  # worst: red
    assert _by(markers)['humans', 1].color[1] > 0.5  # tinted by the best entry's why


def test_the_marker_array_decodes_as_a_real_one():
    markers = scene_markers(SCENE, {1: 0.3}, 'scene é')
    data = encode_marker_array(markers, 'base_link', 1_234_567_890_123)
    array = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(data, 'visualization_msgs/msg/MarkerArray')
    assert len(array.markers) == 1 + len(markers) and array.markers[0].action == 3  # DELETEALL first
    for ours, theirs in zip(markers, array.markers[1:]):
        assert (theirs.ns, theirs.id, theirs.text) == (ours.ns, ours.id, ours.label)
        assert theirs.header.frame_id == 'base_link'
        assert (theirs.header.stamp.sec, theirs.header.stamp.nanosec) == (1234, 567_890_123)
        assert (theirs.pose.position.x, theirs.pose.position.y, theirs.pose.position.z) == ours.position
        assert [(p.x, p.y, p.z) for p in theirs.points] == list(ours.points)
        assert (theirs.color.r, theirs.color.g, theirs.color.b, theirs.color.a) == pytest.approx(ours.color)


class FakeMarkers:
    message_type = recording.MessageType('visualization_msgs/msg/MarkerArray', MARKER_ARRAY_DEFINITION, 'RIHS01_x')

    def __init__(self):
        self.sent = []

    def publish(self, data):
        self.sent.append(data)


@pytest.mark.parametrize('record_folder, record', [(False, True), (True, True), (True, False)])
def test_the_core_publishes_markers_always_and_records_them_when_asked(tiny_checkpoint, synthetic_scenes, tmp_path,
                                                                       record_folder, record):
    """Published even while nobody listens (the latched latest array reaches a viewer that
    joins later); in the bag only with record_markers."""
    node, out = Node(), FakeMarkers()
    values = {name: spec[0] for name, spec in PARAMETERS.items()}
    values.update(checkpoint=str(tiny_checkpoint), record_folder=str(tmp_path) if record_folder else '',
                  record_markers=record)
    core = RankerCore(values, {topic: '/' + topic for topic in TOPICS}, '/ranker', node.publish, node,
                      lambda: next(node.clock), out)
    scene = synthetic_scenes[0]
    core.accept_scene(messages.dumps(scene_request('s0', scene)), 0)
    drain(core)
    assert len(node.on('stars/ranking')) == 1
    assert len(out.sent) == 1  # a DELETEALL, the robot and one marker per entity
    assert int.from_bytes(out.sent[0][4:8], 'little') == 2 + len(entity_nodes(scene))
    core.close()
    stored = []
    if record_folder:
        [bag] = tmp_path.glob('stars_*')  # beside the state store
        stored = list(recording.read_decoded(bag, ['/stars/markers']))
        if record:
            assert recording.bag_topics(bag, None)['/stars/markers'] == recording.qos_profile(1, True)
            assert '/stars/markers' not in recording.bag_topics(bag)  # the String topics a replay plays
    assert len(stored) == int(record and record_folder)


def test_rank_now_answers_at_once_and_records_and_draws_once_the_reply_is_out(tiny_checkpoint, synthetic_scenes,
                                                                              tmp_path):
    """A service call's ranking: returned, not published on stars/ranking; recorded and its
    markers sent by the next ``work``, after the caller has sent the reply."""
    node, out = Node(), FakeMarkers()
    values = {name: spec[0] for name, spec in PARAMETERS.items()}
    values.update(checkpoint=str(tiny_checkpoint), record_folder=str(tmp_path))
    core = RankerCore(values, {topic: '/' + topic for topic in TOPICS}, '/ranker', node.publish, node,
                      lambda: next(node.clock), out)
    reply, refusal = core.rank_now(messages.dumps(scene_request('now', synthetic_scenes[0], 'b')), 0)
    assert refusal is None and reply['scene_id'] == 'now' and reply['known_user'] is True
    messages.check('ranking', reply)
    assert not node.on('stars/ranking') and not out.sent
    drain(core)
    assert len(out.sent) == 1
    assert core.rank_now('{"scene_id": "broken"}', 0) == (None, (
        'schema', "scene_request message invalid: a scene request needs 'graph' (the scene to rank actions in) or "
        "'candidates' that are scenes"))
    assert node.on('stars/errors')[-1]['kind'] == 'schema'
    core.close()
    [bag] = tmp_path.glob('stars_*')
    recorded = [json.loads(m.data) for _, m, _ in recording.read_decoded(bag, ['/stars/ranking'])]
    assert [r['scene_id'] for r in recorded] == ['now']
