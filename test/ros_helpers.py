"""Helpers for tests that run real nodes over loopback DDS: ``test_support.loopback`` (which
the benchmarks share) and what only the tests need."""
import contextlib
import json
import signal
from pathlib import Path

from stars_ros import state
from test_support.loopback import (DOMAINS_PER_BLOCK, LATCHED, RELIABLE, RosClient, domain_id,  # noqa: F401
                                    reserve_block, ros_env, start_node, stop)
from test_support.loopback import die_with_the_parent as die_with_the_tests  # noqa: F401
from waiting import wait_for

REPO = Path(__file__).resolve().parents[1]


def stored_feedback(bag: Path) -> list:
    """The feedback messages of recording ``bag`` that the state store beside it has
    committed now: what the ranker counts as stored (a positive sign that it took them in)."""
    try:
        with state.open_reader(bag.parent) as store:
            return [json.loads(entry['data']) for entry in store.feedback(bag.name)]
    except FileNotFoundError:
        return []


@contextlib.contextmanager
def running_ranker(domain: int, params: dict, log_path: Path, probe: dict, timeout: float = 90.0):
    """A ranker started for real and a client on its domain: (process, client) once it has
    answered ``probe``. On leaving, it must still be alive and stop cleanly on SIGINT."""
    client = RosClient(domain)
    process = start_node('stars_ros.ros.ranker', domain, params, log_path)
    try:
        client.wait_ready(process, timeout, probe)
        yield process, client
        assert process.poll() is None, 'the ranker died during the test'
        assert stop(process, signal.SIGINT) == 0
    finally:
        if process.poll() is None:
            process.kill()
        client.close()

def call_service(client: RosClient, kind, name: str, request, timeout: float = 30.0):
    """The response of service ``name`` (of type ``kind``) to ``request``, called from ``client``'s node."""
    service = client.node.create_client(kind, name)
    try:
        if not service.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f'{name} not available')
        future = service.call_async(request)
        if not wait_for(future.done, timeout):
            raise TimeoutError(f'{name} did not answer')
        return future.result()
    finally:
        client.node.destroy_client(service)
