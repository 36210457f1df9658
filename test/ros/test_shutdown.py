"""The ranker ends on SIGINT and SIGTERM with status 0 and no traceback, round after round,
also when more signals land while it shuts down (a Ctrl-C pressed twice, launch's SIGINT then
SIGTERM), and within ``spinning``'s bound when the middleware hangs in ``destroy_node``, its
state store committed first."""
import signal
import subprocess
import sys

import pytest

from ros_helpers import RosClient, die_with_the_tests, domain_id, ros_env, start_node, stop, stored_feedback
from stars_ros.ros import spinning
from waiting import wait_for

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')  # rclpy's parameter handling
START_TIMEOUT = 90
ROUNDS = 3
HANGING_RANKER = '''
import sys, threading
from stars_ros.ros import ranker
ranker.RankerNode.destroy_node = lambda self: threading.Event().wait()  # the middleware never returns
ranker.main()
'''


@pytest.fixture(scope='module')
def scenes(synthetic_scenes):
    return synthetic_scenes


def _shut_down_by(process, signals, timeout):
    """Send ``signals`` one after the other, at once, and wait for the exit status."""
    for number in signals[:-1]:
        process.send_signal(number)
    return stop(process, signals[-1], timeout)


@pytest.mark.slow
def test_repeated_signals_end_the_ranker_cleanly_round_after_round(tiny_checkpoint, scenes, tmp_path):
    domain = domain_id(15)
    client = RosClient(domain)
    endings = [[signal.SIGINT], [signal.SIGINT, signal.SIGINT, signal.SIGINT], [signal.SIGINT, signal.SIGTERM]]
    try:
        for round_, signals in enumerate(endings[:ROUNDS]):
            log = tmp_path / f'ranker-{round_}.log'
            process = start_node('stars_ros.ros.ranker', domain, {'checkpoint': tiny_checkpoint,
                                                                  'record_folder': tmp_path / 'records'}, log)
            try:
                client.wait_ready(process, START_TIMEOUT, {'scene_id': f'probe-{round_}', 'graph': scenes[0]})
                assert _shut_down_by(process, signals, 60) == 0, log.read_text()
            finally:
                if process.poll() is None:
                    process.kill()
            text = log.read_text()
            assert 'Traceback' not in text and 'KeyboardInterrupt' not in text, text
    finally:
        client.close()


@pytest.mark.slow
def test_a_hung_middleware_still_ends_the_ranker_with_its_feedback_stored(tiny_checkpoint, scenes, tmp_path):
    domain = domain_id(15)
    client = RosClient(domain)
    log = tmp_path / 'ranker.log'
    command = [sys.executable, '-c', HANGING_RANKER, '--ros-args', '-p', f'checkpoint:={tiny_checkpoint}',
               '-p', f'record_folder:={tmp_path}', '-p', 'flush_interval:=60.0']
    process = subprocess.Popen(command, env=ros_env(domain), stdout=open(log, 'w'), stderr=subprocess.STDOUT,
                               preexec_fn=die_with_the_tests)
    try:
        client.wait_ready(process, START_TIMEOUT, {'scene_id': 'rated', 'graph': scenes[0]})
        feedback = {'user_id': 'ann', 'scene_id': 'rated', 'action': 'navigate', 'score': 0.5}
        client.feedback(feedback)

        def folded_in():  # accepted: her own ranking uses it (committed or not yet)
            scene_id = f'check-{len(client.rankings)}'
            client.scene({'scene_id': scene_id, 'user_id': 'ann', 'graph': scenes[1]})
            assert client.wait(lambda: client.ranking_for(scene_id), 30), 'no ranking came back'
            return client.ranking_for(scene_id).get('personalised_from', 0) == 1
        assert wait_for(folded_in, 60), 'the feedback was never folded in'
        bound = spinning.DESTROY_WAIT_S + spinning.CLOSE_WAIT_S
        assert _shut_down_by(process, [signal.SIGINT, signal.SIGINT], 4 * bound) == 0
    finally:
        if process.poll() is None:
            process.kill()
        client.close()
    text = log.read_text()
    assert 'the middleware did not shut down within' in text and 'Traceback' not in text, text
    assert stored_feedback(next(tmp_path.glob('stars_*'))) == [feedback]
