"""The ranker node, started for real on loopback DDS with the generated data's tiny checkpoint:
every ranking entry carries score_sd, a question request is answered on stars/question with
a scene the node then takes feedback on, and a bad one is refused on stars/errors."""
import json

import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from ros_helpers import domain_id, running_ranker
from waiting import wait_for
from stars_ros import messages
from stars_ros.data.scene_source import scene_request

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
QUESTIONS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture
def ranker(tiny_checkpoint, synthetic_scenes, tmp_path):
    """A ranker of its own (fresh state) and a client that also listens on stars/question."""
    params = {'checkpoint': tiny_checkpoint, 'record_folder': tmp_path / 'records'}
    with running_ranker(domain_id(12), params, tmp_path / 'ranker.log', scene_request('probe', synthetic_scenes[0])) \
            as (process, client):
        yield process, client, client.node.create_publisher(String, '/stars/question_request', QUESTIONS), \
            client.collect('/stars/question', QUESTIONS)


def test_rankings_carry_score_sd_and_questions_are_answered(ranker, synthetic_scenes):
    process, client, asker, questions = ranker
    client.scene(scene_request('seen', synthetic_scenes[5], 'newcomer'))
    assert client.wait(lambda: client.ranking_for('seen') is not None, 30)
    ranking = client.ranking_for('seen')
    messages.check('ranking', ranking)
    assert all(entry['score_sd'] > 0 for entry in ranking['ranking']) and 'p_first_is_best' in ranking

    offered = [scene_request(f'ask-{k}', scene) for k, scene in enumerate(synthetic_scenes[30:34])]
    asker.publish(String(data=json.dumps({'user_id': 'newcomer', 'candidates': offered})))
    assert client.wait(lambda: len(questions) == 1, 30), 'no answer on stars/question'
    answer = questions[0]
    messages.check('question', answer)
    assert answer['scene_id'] in {f'ask-{k}' for k in range(4)} and answer['candidates'] == 4

    client.feedback({'user_id': 'newcomer', 'scene_id': answer['scene_id'], 'action': answer['action'], 'score': 0.2})

    asked = []

    def personalised():  # the solve runs once no scene waits: ask again until it is served
        asked.append(scene_id := f'after-{len(asked)}')
        client.scene(scene_request(scene_id, synthetic_scenes[5], 'newcomer'))
        assert client.wait(lambda: client.ranking_for(scene_id), 30), 'no ranking came back'
        return client.ranking_for(scene_id).get('personalised_from') == 1
    assert wait_for(personalised, 30), 'the answer was not folded in'

    asker.publish(String(data='{"candidates": "none"}'))
    assert client.wait(lambda: any(e['topic'] == '/stars/question_request' for e in client.errors), 30)
    refusal = next(e for e in client.errors if e['topic'] == '/stars/question_request')
    assert refusal['kind'] == 'schema' and process.poll() is None
