"""~/forget_person on a ranker running for real: it answers with what it removed where, the
person is in no byte of the state store's files and, once the node has closed its bag, in no
record of any bag; everyone else is served as before; an empty id is answered as an error and
the node serves on."""
import pytest

from ros_helpers import call_service, domain_id, running_ranker
from waiting import wait_for
from stars_ros import state
from stars_ros_msgs.srv import ForgetPerson

from forget_search import bag_records, holds, store_bytes

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')  # rclpy's parameter handling
PERSON, OTHER = 'p2', 'p21'


def _people(folder) -> dict:
    with state.open_reader(folder) as reader:
        return {p.user_id: len(p.ratings) for p in reader.people()}


def test_forget_person_erases_them_and_answers_what_was_removed_where(tiny_checkpoint, synthetic_scenes, tmp_path):
    folder = tmp_path / 'records'
    probe = {'scene_id': 'probe', 'graph': synthetic_scenes[0]}
    with running_ranker(domain_id(13), {'checkpoint': str(tiny_checkpoint), 'record_folder': str(folder),
                                        'flush_interval': 0.2}, tmp_path / 'ranker.log', probe) as (_, client):
        for n, scene in enumerate(synthetic_scenes[:3]):
            for k, user_id in enumerate((PERSON, OTHER)):
                client.scene({'scene_id': f'scene-{k}-{n}', 'user_id': user_id, 'graph': scene})
                assert client.wait(lambda: client.ranking_for(f'scene-{k}-{n}') is not None, 30)
                client.feedback({'user_id': user_id, 'scene_id': f'scene-{k}-{n}', 'action': 'navigate',
                                 'score': 0.5})
        assert wait_for(lambda: (folder / 'state.db').exists() and _people(folder) == {PERSON: 3, OTHER: 3}, 30)
        files = store_bytes(folder)
        assert holds(files['state.db'] + files.get('state.db-wal', b''), PERSON)

        response = call_service(client, ForgetPerson, '/ranker/forget_person', ForgetPerson.Request(user_id=PERSON))

        assert response.success, response.message
        removed = dict(zip(response.removed_places, response.removed_counts))
        assert removed['memory/ratings'] == 3 and removed['state_store/ratings'] == 3
        assert removed['state_store/journal'] == 3 and removed['state_store/people'] == 1
        assert any(place.startswith('bags/') and count > 0 for place, count in removed.items())
        assert _people(folder) == {OTHER: 3}
        for data in store_bytes(folder).values():
            assert not holds(data, PERSON)
        refused = call_service(client, ForgetPerson, '/ranker/forget_person', ForgetPerson.Request(user_id=''))
        assert not refused.success and 'empty' in refused.message
        client.scene({'scene_id': 'after', 'user_id': OTHER, 'graph': synthetic_scenes[0]})
        assert client.wait(lambda: client.ranking_for('after') is not None, 30)
        assert client.ranking_for('after')['personalised_from'] == 3
    assert not any(holds(record, PERSON) for record in bag_records(folder))
    assert _people(folder) == {OTHER: 3}
