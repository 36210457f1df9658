"""Where the package finds the files it ships (stars_ros.resources): the source tree, an
override, a sourced workspace, the packaged checkpoint, and what a missing file says."""
from pathlib import Path

import pytest

from stars_ros import resources
from stars_ros.errors import CheckpointError
from stars_ros.resources import resolve_checkpoint, share_path

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def no_overrides(monkeypatch):
    """Only the places each test sets up: no share override, no sourced workspace."""
    monkeypatch.delenv('STARS_ROS_SHARE', raising=False)
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)


def _shared_file(root: Path, relative: str) -> Path:
    path = root / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text('{}')
    return path


def test_a_checkout_finds_its_files_beside_the_source_tree():
    assert share_path('msg_schemas/scene_graph.schema.json') == REPO / 'msg_schemas' / 'scene_graph.schema.json'
    assert share_path('config/ranker.yaml') == REPO / 'config' / 'ranker.yaml'


def test_the_override_comes_before_the_source_tree(tmp_path, monkeypatch):
    ours = _shared_file(tmp_path, 'msg_schemas/scene_graph.schema.json')
    monkeypatch.setenv('STARS_ROS_SHARE', str(tmp_path))
    assert share_path('msg_schemas/scene_graph.schema.json') == ours
    assert share_path('config/ranker.yaml') == REPO / 'config' / 'ranker.yaml'  # what it lacks comes from the tree


def test_a_sourced_workspace_is_searched_after_the_source_tree(tmp_path, monkeypatch):
    installed = _shared_file(tmp_path / 'install' / 'share' / 'stars_ros', 'config/only_installed.yaml')
    _shared_file(tmp_path / 'install' / 'share' / 'stars_ros', 'config/ranker.yaml')
    monkeypatch.setenv('AMENT_PREFIX_PATH', f"{tmp_path / 'elsewhere'}:{tmp_path / 'install'}")
    assert share_path('config/only_installed.yaml') == installed
    assert share_path('config/ranker.yaml') == REPO / 'config' / 'ranker.yaml'


def test_a_missing_file_names_every_place_looked_in(tmp_path, monkeypatch):
    monkeypatch.setenv('STARS_ROS_SHARE', str(tmp_path))
    with pytest.raises(FileNotFoundError) as missing:
        share_path('config/absent.yaml')
    message = str(missing.value)
    assert message.startswith('config/absent.yaml not found; looked in: ')
    assert str(tmp_path / 'config' / 'absent.yaml') in message and str(REPO / 'config' / 'absent.yaml') in message


def test_an_empty_checkpoint_is_the_packaged_one_and_a_path_is_kept():
    assert resolve_checkpoint('') == str(REPO / 'models' / 'socnav1_gat_stars.pt')
    assert resolve_checkpoint('elsewhere/model.pt') == 'elsewhere/model.pt'  # not checked here: loading says


def test_a_missing_packaged_checkpoint_says_how_to_give_one(monkeypatch):
    monkeypatch.setattr(resources, 'DEFAULT_CHECKPOINT', 'models/not_packaged.pt')
    with pytest.raises(CheckpointError, match=r'packaged default is missing .*models/not_packaged.pt not found.*'
                                              r'-p checkpoint:=PATH'):
        resolve_checkpoint('')
