import json

import numpy as np
import torch
import pytest

from stars_ros.data.ratings import load_dataset
from stars_ros.errors import DataError

SCENE = {'humans': [{'id': 1, 'xPos': 50, 'yPos': 80, 'orientation': 10}], 'objects': [], 'links': [],
         'room': [[-300, -300], [300, -300], [300, 300], [-300, 300], [-300, -300]]}


@pytest.mark.socnav1
def test_socnav1_counts_match_its_readme(socnav1):
    assert len(socnav1) == 9280
    assert sorted(set(socnav1.users.tolist())) == list('abcdefghijkl')
    assert int((socnav1.users == 'g').sum()) == 2500
    assert socnav1.action_names == ('navigate',)
    assert socnav1.scores.min() >= 0 and socnav1.scores.max() <= 1
    assert socnav1.scores.mean() == pytest.approx(0.571, abs=5e-4)
    # 5,735 identifiers; the one with two contents becomes two scenes
    assert len(socnav1.scene_keys) == 5736
    assert len(set(socnav1.item_keys('prefix'))) == 4904  # the paper's count of SocNav1 scenes
    assert socnav1.item_keys('prefix')[socnav1.scene_keys.index('01892 A')] == '01892'


@pytest.mark.socnav1
def test_identifier_with_two_contents_becomes_two_scenes(socnav1):
    variants = [k for k in socnav1.scene_keys if k.startswith('01998 A')]
    assert len(variants) == 2 and all('#' in k for k in variants)
    rows = np.flatnonzero(np.isin(socnav1.scenes, [socnav1.scene_keys.index(k) for k in variants]))
    assert sorted(socnav1.users[rows].tolist()) == ['g', 'i']  # both ratings kept, one per content
    assert len(set(socnav1.scenes[rows].tolist())) == 2
    assert any('01998 A' in note for note in socnav1.notes)


@pytest.mark.socnav1
def test_shared_identifier_is_one_scene(socnav1):
    counts = np.bincount(socnav1.scenes)
    assert counts.max() == 4  # README: up to 4 annotators per identifier


def write_generic(root, annotations, scenes_csv=None, scenes_jsonl=None):
    root.mkdir(exist_ok=True)
    (root / 'annotations.csv').write_text(annotations)
    if scenes_csv is not None:
        (root / 'scenes.csv').write_text(scenes_csv)
    if scenes_jsonl is not None:
        (root / 'scenes.jsonl').write_text(scenes_jsonl)
    return root


GOOD_ANNOTATIONS = 'user,scene,action,score\nu1,s1,wave,4\nu1,s2,wave,2\nu2,s1,beep,5\n'
GOOD_SCENES = 'scene,crowd,noise\ns1,3,0.5\ns2,0,0.1\n'


def test_generic_tabular(tmp_path):
    data = load_dataset(write_generic(tmp_path / 'd', GOOD_ANNOTATIONS, scenes_csv=GOOD_SCENES))
    assert data.kind == 'tabular' and data.action_names == ('beep', 'wave')
    assert data.store.feature_names == ('crowd', 'noise')
    assert data.scores.tolist() == [4.0, 2.0, 5.0]
    assert data.actions.tolist() == [1, 1, 0]


def test_generic_graphs(tmp_path):
    lines = '\n'.join(json.dumps({'scene': name, **SCENE}) for name in ('s1', 's2'))
    data = load_dataset(write_generic(tmp_path / 'd', GOOD_ANNOTATIONS, scenes_jsonl=lines))
    assert data.kind == 'graph' and len(data.store) == 2


@pytest.mark.parametrize('annotations, scenes, message', [
    ('user,scene,score\nu1,s1,3\n', GOOD_SCENES, r'annotations.csv:1: missing columns \[.action.\]'),
    ('user,scene,action,score\nu1,s1,wave,high\n', GOOD_SCENES, r'annotations.csv:2: score .high. is not a number'),
    ('user,scene,action,score\nu1,s1,wave,4\nu1,s2,wave,\n', GOOD_SCENES, r'annotations.csv:3: score is empty'),
    ('user,scene,action,score\nu1,s1,wave,nan\n', GOOD_SCENES, r'annotations.csv:2: .* not a finite'),
    ('user,scene,action,score\nu1,s9,wave,4\n', GOOD_SCENES, r"annotations.csv:2: scene 's9' is not in scenes.csv"),
    ('', GOOD_SCENES, r'annotations.csv: empty file'),
    ('user,scene,action,score\n', GOOD_SCENES, r'annotations.csv: no data rows'),
    (GOOD_ANNOTATIONS + 'u1,s1,wave,3\n', GOOD_SCENES, r'annotations.csv:5: duplicate rating .*first at line 2'),
    (GOOD_ANNOTATIONS, 'scene,crowd\ns1,lots\n', r'scenes.csv:2: column crowd value .lots. is not a number'),
    (GOOD_ANNOTATIONS, 'scene,crowd\ns1,1\ns1,2\n', r'scenes.csv:3: scene key .s1. empty or repeated'),
    (GOOD_ANNOTATIONS, 'scene\ns1\n', r'scenes.csv:1: no feature columns'),
    (GOOD_ANNOTATIONS, 'scene,crowd,crowd\ns1,1,2\n', r"scenes.csv:1: repeated columns \['crowd'\]"),
    ('user,scene,action,score\nu1,s1,wave,4\nu1,s2\n', GOOD_SCENES, r'annotations.csv:3: 2 fields, header has 4'),
    # lines count from the header as line 1, blank lines and quoted line breaks included
    ('user,scene,action,score\n"u\n1",s1,wave,4\n\nu1,s2,wave,4,9\n', GOOD_SCENES,
     r'annotations.csv:5: 5 fields, header has 4'),
    ('user,scene,action,score\n"u\n1",s1,wave,4\n  ,  \nu1,s2,wave,high\n', GOOD_SCENES,
     r'annotations.csv:5: score .high. is not a number'),
])
def test_generic_errors_name_file_and_line(tmp_path, annotations, scenes, message):
    root = write_generic(tmp_path / 'd', annotations, scenes_csv=scenes)
    with pytest.raises(DataError, match=message):
        load_dataset(root)


def test_generic_jsonl_scene_error_names_line(tmp_path):
    lines = json.dumps({'scene': 's1', **SCENE}) + '\n' + json.dumps({'scene': 's2', 'humans': []})
    with pytest.raises(DataError, match=r"scenes.jsonl:2: scene graph invalid at <root>: .*'room'"):
        load_dataset(write_generic(tmp_path / 'd', GOOD_ANNOTATIONS, scenes_jsonl=lines))


def test_generic_needs_one_scene_file(tmp_path):
    with pytest.raises(DataError, match='exactly one of'):
        load_dataset(write_generic(tmp_path / 'd', GOOD_ANNOTATIONS))


def socnav_root(tmp_path, lines):
    raw = tmp_path / 's' / 'raw'
    raw.mkdir(parents=True)
    (raw / 'a.jsonl').write_text('\n'.join(lines) + '\n')
    return raw.parent


def line(identifier='00001 A', score=50, **extra):
    return json.dumps({'identifier': identifier, 'score': score, **SCENE, **extra})


@pytest.mark.parametrize('lines, message', [
    (['{not json'], r'a.jsonl:1: not valid JSON'),
    ([line(), line(score='x')], r'a.jsonl:2: score .x. is not a number'),
    ([line(score=101)], r'a.jsonl:1: score 101.0 outside 0-100'),
    ([line().replace('50', 'NaN', 1)], r'a.jsonl:1: not valid JSON .*NaN'),
    ([line(), line()], r'a.jsonl:2: annotator a rates scene 00001 A again \(first at line 1\)'),
    ([line(room=[[0, 0]])], r'a.jsonl:1: scene graph invalid at room'),
    ([json.dumps({'score': 3})], r'a.jsonl:1: expected an object with identifier and score'),
])
def test_socnav1_errors_name_file_and_line(tmp_path, lines, message):
    with pytest.raises(DataError, match=message):
        load_dataset(socnav_root(tmp_path, lines))


def test_socnav1_empty_file(tmp_path):
    with pytest.raises(DataError, match='empty file'):
        load_dataset(socnav_root(tmp_path, ['']))


def test_unknown_root(tmp_path):
    with pytest.raises(DataError, match='neither'):
        load_dataset(tmp_path)


def test_generated_data_loads_as_socnav1_does(synthetic):
    assert len(synthetic) == 521 and sorted(set(synthetic.users.tolist())) == list('abcdefghijkl')
    assert synthetic.action_names == ('navigate',) and synthetic.scale == (0.0, 1.0)
    assert synthetic.scores.min() >= 0 and synthetic.scores.max() <= 1 and synthetic.scores.std() > 0.1
    assert np.bincount(synthetic.scenes).max() > 1  # people rate scenes in common
    assert len(set(synthetic.item_keys('prefix'))) < len(synthetic.scene_keys)  # "00007 A" and "00007 B"


def test_generated_identifier_with_two_contents_becomes_two_scenes(synthetic):
    variants = [k for k in synthetic.scene_keys if '#' in k]
    assert len(variants) == 2 and variants[0].split('#')[0] == variants[1].split('#')[0]
    raters = [set(synthetic.users[synthetic.scenes == synthetic.scene_keys.index(k)].tolist()) for k in variants]
    assert all(raters) and not raters[0] & raters[1]  # each rating kept, on the content its rater saw
    assert len(synthetic.notes) == 1 and variants[0].split('#')[0] in synthetic.notes[0]


def test_feature_cache_round_trip_and_damage(synthetic_root, synthetic, tmp_path, monkeypatch):
    monkeypatch.setenv('STARS_ROS_CACHE', str(tmp_path / 'cache'))
    first = load_dataset(synthetic_root)
    cached = list((tmp_path / 'cache').glob('graphs-v*.pt'))
    assert len(cached) == 1
    second = load_dataset(synthetic_root)
    assert torch.equal(second.store.x, synthetic.store.x)
    assert torch.equal(second.store.edge_index, first.store.edge_index)
    cached[0].write_bytes(b'damaged')
    third = load_dataset(synthetic_root)
    assert torch.equal(third.store.edge_type, synthetic.store.edge_type)
