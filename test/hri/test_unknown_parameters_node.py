"""Every node warns about a parameter override it does not declare, as the ranker does
(``ros.unknown_parameters``): ``-p goal_fram:=map`` names what was meant instead of leaving
the default without a word."""
import signal

import pytest

from hri_fixtures import hri_msgs  # noqa: F401 - the fixture
from ros_helpers import domain_id, start_node, stop
from waiting import wait_for

pytestmark = pytest.mark.slow  # a node process per case
NODES = [  # module, executable, parameters it starts with, the misspelt override, the name meant
    ('stars_ros.ros.hri_bridge', 'hri_bridge', {'pose_source': 'topic'}, 'goal_fram', 'goal_frame'),
    ('stars_ros.ros.hri_world', 'hri_world', {'pose_source': 'topic'}, 'perod', 'period'),
    ('stars_ros.ros.scene_publisher', 'scene_publisher', {}, 'rat', 'rate'),
    ('stars_ros.ros.replay', 'replay', {}, 'bagg', 'bag'),
]


@pytest.mark.parametrize('module, executable, params, misspelt, meant', NODES, ids=[n[1] for n in NODES])
def test_a_misspelt_parameter_is_warned_about(hri_msgs, tmp_path, module, executable, params, misspelt, meant):
    log = tmp_path / f'{executable}.log'
    process = start_node(module, domain_id(17), {**params, misspelt: 1.0}, log)
    line = f"parameter '{misspelt}' is not one of the {executable}'s: ignored (did you mean '{meant}'?)"
    try:
        assert wait_for(lambda: line in log.read_text() or process.poll() is not None, 60)
        assert line in log.read_text(), log.read_text()[-2000:]
    finally:
        if process.poll() is None:
            stop(process, signal.SIGINT)
