"""The ranker node, started for real on loopback DDS: a request with "explain": true gets `why`
on every entry, stars/markers carries one marker per scene entity and candidate in the
frame_id frame, and both are in the MCAP bag, the markers as real
visualization_msgs/msg/MarkerArray read back with mcap_ros2 (and rosbags)."""
import json
import math

import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from visualization_msgs.msg import Marker, MarkerArray

from ros_helpers import domain_id, running_ranker
from stars_ros import messages, recording
from stars_ros.data.scene_graph import entity_nodes
from stars_ros.data.scene_source import placement_candidates, scene_request
from stars_ros.model.predictor import Predictor
from stars_ros.data.frames import to_rep103
from stars_ros.node.markers import encode_marker_array, scene_markers
from stars_ros.ros.markers import message_definition

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
MARKERS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
FRAME = 'robot1/base_link'


def test_the_encoded_marker_array_is_the_one_rclpy_serialises(scene):
    """The bytes the node publishes and records are those of the MarkerArray built field by field
    (as long, and the same message; Fast-CDR leaves its padding bytes uninitialised)."""
    markers = scene_markers(scene, {scene['humans'][0]['id']: 0.2}, 'scène')
    stamp = Time(sec=12, nanosec=345)
    clear = Marker(action=Marker.DELETEALL)
    clear.header.frame_id, clear.header.stamp = FRAME, stamp
    expected = [clear]
    for spec in markers:
        marker = Marker(ns=spec.ns, id=spec.id, type=getattr(Marker, spec.kind), action=Marker.ADD, text=spec.label)
        marker.header.frame_id, marker.header.stamp = FRAME, stamp
        marker.pose.position = Point(x=spec.position[0], y=spec.position[1], z=spec.position[2])
        marker.pose.orientation.z, marker.pose.orientation.w = math.sin(spec.yaw / 2), math.cos(spec.yaw / 2)
        marker.scale.x, marker.scale.y, marker.scale.z = spec.scale
        marker.color.r, marker.color.g, marker.color.b, marker.color.a = spec.color
        marker.points = [Point(x=x, y=y, z=z) for x, y, z in spec.points]
        expected.append(marker)
    ours, theirs = encode_marker_array(markers, FRAME, 12_000_000_345), serialize_message(MarkerArray(markers=expected))
    assert len(ours) == len(theirs)
    assert deserialize_message(ours, MarkerArray) == deserialize_message(theirs, MarkerArray)


def test_the_recorded_definition_is_the_installed_one():
    ours = message_definition(MarkerArray)
    theirs, _ = get_typestore(Stores.ROS2_JAZZY).generate_msgdef('visualization_msgs/msg/MarkerArray', ros_version=2)
    fields = [line for line in theirs.splitlines() if '=' not in line or line.startswith('=' * 80)]  # no constants
    assert ours.splitlines() == fields


def _added(array) -> list:
    return [m for m in array.markers if m.action == Marker.ADD]


def _robot_label(array) -> str | None:
    return next((m.text for m in array.markers if m.ns == 'robot'), None)


def _check_scene(added, scene):
    """One marker per entity and the robot, humans where SocNav1 puts them (REP 103 metres)."""
    by_key = {(m.ns, m.id): m for m in added}
    assert len(by_key) == len(added)
    for human in scene['humans']:
        marker = by_key['humans', human['id']]
        assert (marker.pose.position.x, marker.pose.position.y) == pytest.approx(
            to_rep103(human['xPos'], human['yPos']))
    assert sum(m.ns != 'candidates' for m in added) == 1 + len(entity_nodes(scene))
    return by_key


def _first(entry):
    return entry['why']['entities'][0]


@pytest.fixture
def scene(synthetic_scenes):
    return next(s for s in synthetic_scenes if len(s['humans']) >= 2 and s['links'])


def test_explained_rankings_and_markers_live_and_in_the_bag(tiny_checkpoint, synthetic_scenes, scene, tmp_path):
    action = Predictor.load(tiny_checkpoint).actions[0]
    records = tmp_path / 'records'
    params = {'checkpoint': tiny_checkpoint, 'record_folder': records, 'frame_id': FRAME, 'explain_entities': 0}
    with running_ranker(domain_id(14), params, tmp_path / 'ranker.log',
                        scene_request('probe', synthetic_scenes[0])) as (process, client):
        arrays = client.collect_messages('/stars/markers', MarkerArray, MARKERS)
        assert client.wait(lambda: client.node.count_publishers('/stars/markers') == 1, 30)

        client.scene({**scene_request('actions', scene), 'explain': True})
        candidates = {'scene_id': 'placements', 'candidates': placement_candidates(scene, 3), 'action': action,
                      'explain': True}
        client.scene(candidates)
        assert client.wait(lambda: {_robot_label(a) for a in arrays} >= {'actions', 'placements'}, 30)
        live = {_robot_label(a): a for a in arrays}
        rankings = {scene_id: client.ranking_for(scene_id) for scene_id in ('actions', 'placements')}
        for ranking in rankings.values():
            messages.check('ranking', ranking)
            assert ranking['ranking'] and all('why' in entry for entry in ranking['ranking'])

        for array in live.values():
            assert array.markers[0].action == Marker.DELETEALL  # the previous scene's markers go
            assert {m.header.frame_id for m in array.markers} == {FRAME}
        _check_scene(_added(live['actions']), scene)
        top = _first(rankings['actions']['ranking'][0])  # tinted by the best entry's strongest entity
        colour = next(m for m in _added(live['actions']) if m.ns != 'robot' and m.text == str(top['id'])).color
        assert (colour.g > colour.r) == (top['effect'] > 0) and colour.a == pytest.approx(1.0)

        placed = _check_scene(_added(live['placements']), scene)
        discs = [placed['candidates', k] for k in range(3)]
        best = rankings['placements']['ranking'][0]['candidate']
        labels = [c['candidate'] for c in candidates['candidates']]
        best_disc = discs[labels.index(best)]
        assert best_disc.color.a == pytest.approx(1.0) and best_disc.color.g == pytest.approx(0.8)
        assert all(d.color.a < 1.0 for d in discs if d is not best_disc)
        assert (discs[1].pose.position.x, discs[1].pose.position.y) == pytest.approx((0.0, 0.5))  # left_50cm

    [bag] = records.glob('stars_*')
    recorded = {json.loads(text)['scene_id']: json.loads(text)
                for _, text, _ in recording.read_messages(bag, ['/stars/ranking'])}
    for scene_id in ('actions', 'placements'):
        assert recorded[scene_id]['ranking'] == rankings[scene_id]['ranking']
    in_bag = {}
    for path in recording.bag_files(bag):
        with open(path, 'rb') as handle:
            reader = make_reader(handle, decoder_factories=[DecoderFactory()])
            for schema, channel, _, decoded in reader.iter_decoded_messages(topics=['/stars/markers']):
                assert schema.name == 'visualization_msgs/msg/MarkerArray' and channel.message_encoding == 'cdr'
                in_bag[_robot_label(decoded)] = decoded
    for scene_id, array in live.items():
        stored = in_bag[scene_id]
        assert len(stored.markers) == len(array.markers)
        for ours, theirs in zip(stored.markers, array.markers):
            assert (ours.ns, ours.id, ours.type, ours.action, ours.header.frame_id) == (
                theirs.ns, theirs.id, theirs.type, theirs.action, theirs.header.frame_id)
            assert (ours.pose.position.x, ours.pose.position.y, ours.pose.position.z) == (
                theirs.pose.position.x, theirs.pose.position.y, theirs.pose.position.z)
            assert (ours.color.r, ours.color.g, ours.color.b, ours.color.a) == pytest.approx(
                (theirs.color.r, theirs.color.g, theirs.color.b, theirs.color.a))
            assert [(p.x, p.y) for p in ours.points] == [(p.x, p.y) for p in theirs.points]

    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:  # what ros2 bag and Foxglove see: the real type, its hash
        [connection] = [c for c in reader.connections if c.topic == '/stars/markers']
        assert connection.msgtype == 'visualization_msgs/msg/MarkerArray'
        raw = next(data for c, _, data in reader.messages([connection]))
        assert store.deserialize_cdr(raw, connection.msgtype).markers[0].action == Marker.DELETEALL
    info = (bag / recording.METADATA_FILE).read_text()
    assert store.hash_rihs01('visualization_msgs/msg/MarkerArray') in info
