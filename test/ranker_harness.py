"""What the ranker's node tests share (``test/ros/test_ranker_node.py``, one node for the
module, and ``test_ranker_process.py``, a ranker per test): the scenes, the predictor of the
tiny checkpoint, and the waits that settle a node before a test reads it."""
import time

import numpy as np
import pytest

from stars_ros.model.predictor import Predictor


KNOWN_USER = 'b'  # in the tiny checkpoint's training rows
START_TIMEOUT = 90


@pytest.fixture(scope='module')
def scenes(synthetic_scenes):
    return synthetic_scenes


@pytest.fixture(scope='module')
def predictor(tiny_checkpoint):
    return Predictor.load(tiny_checkpoint)


def probe_request(scenes):
    """A scene request with an id of its own: what a start waits to see ranked."""
    return {'scene_id': f'probe-{time.monotonic_ns()}', 'graph': scenes[0]}


def served_latched_user(client, scenes, user_id=KNOWN_USER, timeout: float = 20.0) -> dict | None:
    """Probe (each probe waiting for its ranking) until a request that names no user is
    ranked for ``user_id`` (the latched id; None: nobody); that ranking, None if none was."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        probe = probe_request(scenes)
        client.scene(probe)
        if client.wait(lambda: client.ranking_for(probe['scene_id']) is not None, 5) and \
                client.ranking_for(probe['scene_id'])['user_id'] == user_id:
            return client.ranking_for(probe['scene_id'])
    return None


def assert_same(reply, expected, key='action', tolerance=1e-5):
    assert [entry[key] for entry in reply['ranking']] == [r.name for r in expected]
    assert np.allclose([e['score'] for e in reply['ranking']], [r.score for r in expected], atol=tolerance)
    assert [e['rank'] for e in reply['ranking']] == list(range(1, len(expected) + 1))


SETTLED = 'settled-'  # the scene ids of settle's markers


def settle(client, scenes, attempts: int = 10):
    """Return once every answer to the requests sent so far has reached ``client``. The node
    takes stars/scene in order and each of its topics arrives in order: a request ranked
    after all of them (sent again while a full queue refuses it, once a ranking has come
    since, so the queue has had room made in it: a refusal comes back faster than a ranking
    is made), then, once that ranking is in, a request refused at once, whose error follows
    every earlier error."""
    for _ in range(attempts):
        scene_id = f'{SETTLED}{time.monotonic_ns()}'
        client.scene({'scene_id': scene_id, 'user_id': KNOWN_USER, 'graph': scenes[0]})
        if client.wait(lambda: client.ranking_for(scene_id) is not None or any(
                e['scene_id'] == scene_id for e in client.errors), 20) and client.ranking_for(scene_id):
            break
        rankings = len(client.snapshot(client.rankings))
        client.wait(lambda: len(client.snapshot(client.rankings)) > rankings, 20)
    else:
        pytest.fail(f'no request was ranked in {attempts} attempts')
    refused = f'{SETTLED}{time.monotonic_ns()}'
    client.scene({'scene_id': refused, 'graph': {}})
    assert client.wait(lambda: any(e['scene_id'] == refused for e in client.errors), 20), 'the refusal never came'


def answers(client, prefix=None) -> tuple[set, list]:
    """(scene ids ranked, scene ids refused with an error, not a warning) of the answers
    ``client`` holds, settle's markers left out; only ids starting with ``prefix`` if given."""
    def kept(scene_id):
        return not str(scene_id).startswith(SETTLED) and (prefix is None or str(scene_id).startswith(prefix))
    ranked = [r['scene_id'] for r in client.snapshot(client.rankings) if kept(r['scene_id'])]
    refused = [e['scene_id'] for e in client.snapshot(client.errors) if e['level'] == 'error' and kept(e['scene_id'])]
    return ranked, refused
