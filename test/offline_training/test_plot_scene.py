"""python -m offline_training.plot_scene on generated data: one PNG with a panel per person,
placements or actions ranked as the model ranks them, effects as model.explain gives them;
clear errors for a person or scene that is not there, and for a missing matplotlib."""
import sys

import numpy as np
import pytest

from offline_training import plot_scene
from stars_ros.data.scene_source import read_scenes
from stars_ros.errors import StarsError
from stars_ros.figures import scene as figure
from stars_ros.model.explain import removal_effects
from stars_ros.model.predictor import Predictor

PNG = b'\x89PNG\r\n\x1a\n'


def _shared(root, users):
    rated = [{s['identifier']: s for s in read_scenes(root / 'raw' / f'{u}.jsonl')} for u in users]
    return next(key for key in rated[0] if key in rated[1])


@pytest.mark.parametrize('placements', [3, 0])
def test_two_people_side_by_side(tiny_checkpoint, synthetic_root, tmp_path, capsys, placements):
    out = tmp_path / 'scene.png'
    code = plot_scene.main(['--checkpoint', str(tiny_checkpoint), '--data-root', str(synthetic_root),
                            '--users', 'a', 'b', '--placements', str(placements), '--out', str(out)])
    assert code == 0 and capsys.readouterr().out.strip() == str(out)
    assert out.read_bytes()[:8] == PNG and out.stat().st_size > 10_000


def test_a_persons_view_is_the_models_ranking_and_effects(tiny_checkpoint, synthetic_root):
    predictor = Predictor.load(tiny_checkpoint)
    scene = plot_scene.choose_scene(synthetic_root, ['a', 'b'], None)
    assert scene['identifier'] == _shared(synthetic_root, ['a', 'b'])
    view = figure.person_view(predictor, 'a', scene)
    scores = predictor.score('a', [scene])[0]
    assert [name for name, _ in view.ranking] == [predictor.actions[k] for k in np.argsort(-scores, kind='stable')]
    entities, effects = removal_effects(predictor, 'a', [scene])[0]
    best = int(np.argmax(scores))
    assert view.effects == pytest.approx({e[0]: float(v) for e, v in zip(entities, effects[:, best])})
    placed = figure.person_view(predictor, 'a', scene, placements=3)
    assert placed.poses['stay'] == pytest.approx((0.0, 0.0)) and placed.poses['left_50cm'] == pytest.approx((0.0, 0.5))


def test_clear_errors(tiny_checkpoint, synthetic_root, tmp_path, capsys, monkeypatch):
    args = ['--checkpoint', str(tiny_checkpoint), '--data-root', str(synthetic_root), '--out', str(tmp_path / 'x.png')]
    assert plot_scene.main(args + ['--users', 'a', 'nobody']) == 1
    assert "no ratings of 'nobody'" in capsys.readouterr().err
    assert plot_scene.main(args + ['--users', 'a', 'b', '--scene', 'no such scene']) == 1
    assert "'a' did not rate scene 'no such scene'" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, 'matplotlib', None)  # as if it were not installed
    with pytest.raises(StarsError, match='pip install matplotlib=='):
        figure.pyplot()
