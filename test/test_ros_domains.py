"""Two runs of the suite on one machine reserve different blocks of ROS domains."""
import subprocess
import sys

from ros_helpers import DOMAINS_PER_BLOCK, REPO, domain_id, reserve_block


def test_a_second_process_gets_another_block_while_the_first_holds_one():
    mine = reserve_block()
    assert domain_id(0) == mine and domain_id(DOMAINS_PER_BLOCK - 1) == mine + DOMAINS_PER_BLOCK - 1
    other = subprocess.run([sys.executable, '-c', f'import sys; sys.path.insert(0, {str(REPO / "test")!r}); '
                            'from ros_helpers import reserve_block; print(reserve_block())'],
                           capture_output=True, text=True, timeout=60, check=True)
    assert abs(int(other.stdout) - mine) >= DOMAINS_PER_BLOCK
