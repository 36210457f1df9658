"""Forget leaves nothing of a person in the running node's memory (docs/privacy.md): after
``forget_person``, no object reachable from the core (the owner of people, the fold-in's
caches, the store and the recording, their closures) holds the forgotten id, a rating of
theirs or a message of theirs, while another person's are all still there."""
import json

from core_harness import Node, drain, make_core, woken_and_drained
from memory_walk import naming, reachable
from stars_ros import feedback_auth, messages
from stars_ros.data.scene_source import read_scenes, scene_request
from waiting import wait_for

FORGOTTEN, KEPT = 'wren-forgotten-41', 'ivo-kept-93'
SECRET = bytes(range(32))


def _feedback(core, user_id: str, scene_id: str, score: float, implicit: bool = False):
    fields = {'user_id': user_id, 'scene_id': scene_id, 'action': 'navigate', 'score': score}
    if implicit:
        fields['implicit'] = True
    assert core.accept_feedback(json.dumps(feedback_auth.sign(fields, 'tablet', SECRET, 1_000_000_000)))
    drain(core)


def test_nothing_of_a_forgotten_person_is_reachable_from_the_core(tmp_path, tiny_checkpoint, synthetic_root):
    keys = tmp_path / 'keys.txt'
    keys.write_text(f'tablet:{SECRET.hex()}\n')
    keys.chmod(0o600)
    node = Node()
    core = make_core(node, tiny_checkpoint, record_folder=str(tmp_path / 'records'),
                     feedback_key_file=str(keys), flush_interval=0.01)
    scenes = read_scenes(synthetic_root / 'raw' / 'h.jsonl')[:3]
    for n, scene in enumerate(scenes):
        for user_id in (KEPT, FORGOTTEN):  # the latest report of a stranger names the forgotten one
            scene_id = f'scene-{user_id[:3]}-{n}'
            core.accept_scene(messages.dumps(scene_request(scene_id, scene, user_id)), 0)
            drain(core)
            _feedback(core, user_id, scene_id, 1.0, implicit=n == 2)
    assert wait_for(lambda: (woken_and_drained(node, core) or True)
                    and len(node.on('stars/user_model')) == 6, 30)  # every model sent, nothing waits
    ratings = {user_id: core.personalisation.ratings(user_id) for user_id in (FORGOTTEN, KEPT)}
    assert len(ratings[FORGOTTEN]) == 3 and ratings[FORGOTTEN][2].implicit
    assert core.personalisation.foldin.cached[1] >= 6  # the fold-in keeps every rating's row
    assert naming(reachable(core, outside=[node]), FORGOTTEN)  # the walk finds them while they are held

    core.forget_person(FORGOTTEN)
    drain(core)

    held = reachable(core, outside=[node])
    held_ids = {id(o) for o in held}
    assert naming(held, FORGOTTEN) == []
    assert not [r for r in ratings[FORGOTTEN] if id(r) in held_ids or id(r.feedback) in held_ids]
    assert naming(held, KEPT) and all(id(r) in held_ids for r in ratings[KEPT])
    core.close()
