"""What a ROS user expects of the ranker, checked on real nodes over loopback DDS: a viewer
that subscribes to stars/markers late still gets the latest array (latched), a misspelt
parameter override is warned about, and the managed ranker serves only once configured
(checkpoint loaded) and activated, stops serving when deactivated, and stays unconfigured,
saying why, when its checkpoint cannot be loaded."""
import signal

import pytest
from geometry_msgs import msg as geometry
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from stars_ros_msgs import msg as typed
from stars_ros_msgs.srv import RankActions
from visualization_msgs.msg import MarkerArray

from ros_helpers import RosClient, call_service as call, domain_id, running_ranker, start_node, stop
from waiting import wait_for
from stars_ros.data.scene_source import scene_request
from stars_ros.typed_messages import scene_message

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
LATE_VIEWER = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def test_a_late_viewer_gets_the_latest_markers_and_a_misspelt_override_is_warned_about(
        tiny_checkpoint, synthetic_scenes, tmp_path):
    params = {'checkpoint': tiny_checkpoint, 'record_folder': tmp_path / 'records', 'top_kk': 3}
    log = tmp_path / 'ranker.log'
    with running_ranker(domain_id(2), params, log, scene_request('probe', synthetic_scenes[0])) as (process, client):
        client.scene(scene_request('latest', synthetic_scenes[4]))  # nobody listens to stars/markers yet
        assert client.wait(lambda: client.ranking_for('latest') is not None, 30)
        arrays = client.collect_messages('/stars/markers', MarkerArray, LATE_VIEWER)
        assert client.wait(lambda: len(arrays) == 1, 30), 'a late viewer got no markers'
        labels = [m.text for m in arrays[0].markers]
        assert any('latest' in label for label in labels), labels
    assert wait_for(lambda: "parameter 'top_kk' is not one of the ranker's: ignored (did you mean 'top_k'?)"
                    in log.read_text(), 10), log.read_text()


def _lifecycle(client: RosClient, transition: int) -> bool:
    return call(client, ChangeState, '/ranker/change_state',
                ChangeState.Request(transition=Transition(id=transition))).success


def _state(client: RosClient) -> int:
    return call(client, GetState, '/ranker/get_state', GetState.Request()).current_state.id


def _serves(client: RosClient) -> bool:
    names = [name for name, _ in client.node.get_service_names_and_types()]
    return '/ranker/rank_actions' in names


def test_the_managed_ranker_serves_once_configured_and_activated(tiny_checkpoint, synthetic_scenes, tmp_path):
    domain = domain_id(2)
    client = RosClient(domain)
    log = tmp_path / 'm.log'
    process = start_node('stars_ros.ros.managed_ranker', domain,
                         {'checkpoint': tiny_checkpoint, 'record_folder': tmp_path / 'records'}, log)
    request = RankActions.Request(scene_id='managed', scene=scene_message(synthetic_scenes[1], 'base_link', typed,
                                                                          geometry))
    try:
        assert _state(client) == State.PRIMARY_STATE_UNCONFIGURED
        assert _lifecycle(client, Transition.TRANSITION_CONFIGURE)
        assert _state(client) == State.PRIMARY_STATE_INACTIVE and not _serves(client)
        assert _lifecycle(client, Transition.TRANSITION_ACTIVATE)
        assert call(client, RankActions, '/ranker/rank_actions', request).success
        assert _lifecycle(client, Transition.TRANSITION_DEACTIVATE)
        assert wait_for(lambda: not _serves(client), 30), 'still serving once deactivated'
        assert _lifecycle(client, Transition.TRANSITION_ACTIVATE)
        assert call(client, RankActions, '/ranker/rank_actions', request).success
        assert stop(process, signal.SIGINT) == 0
        assert 'rosout' not in log.read_text(), log.read_text()  # Ctrl-C logs nothing it cannot publish
    finally:
        if process.poll() is None:
            process.kill()
        client.close()


def test_a_managed_ranker_whose_checkpoint_fails_stays_unconfigured(tmp_path):
    domain = domain_id(2)
    client = RosClient(domain)
    missing = tmp_path / 'missing.pt'
    log = tmp_path / 'm.log'
    process = start_node('stars_ros.ros.managed_ranker', domain, {'checkpoint': missing, 'record_folder': "''"}, log)
    try:
        assert not _lifecycle(client, Transition.TRANSITION_CONFIGURE)
        assert _state(client) == State.PRIMARY_STATE_UNCONFIGURED
        assert 'configure failed, still unconfigured' in log.read_text() and str(missing) in log.read_text()
        assert stop(process, signal.SIGINT) == 0
    finally:
        if process.poll() is None:
            process.kill()
        client.close()
