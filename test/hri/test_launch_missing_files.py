"""The launch files refuse a file argument that names no file before any node starts (a node
started on it would die while the launch runs on)."""
import pytest

from stars_ros.errors import LaunchArgumentError
from stars_ros.ros.launch_arguments import existing_file
from test_hri_launch import launched


def test_hri_launch_refuses_a_missing_source(monkeypatch, tmp_path):
    with pytest.raises(LaunchArgumentError, match='source:=.*no such file'):
        launched(monkeypatch, source=str(tmp_path / 'missing.jsonl'))
    present = tmp_path / 'a.jsonl'
    present.write_text('')
    assert launched(monkeypatch, source=str(present))['hri_world']['parameters'][0]['source'].name == 'source'


def test_hri_launch_refuses_a_missing_consent_file(monkeypatch, tmp_path):
    with pytest.raises(LaunchArgumentError, match='consent_file:=.*no such file'):
        launched(monkeypatch, store_policy='consented', consent_file=str(tmp_path / 'consent.txt'))


def test_existing_file(tmp_path):
    (tmp_path / 'ranker.yaml').write_text('')
    assert existing_file('params_file', str(tmp_path / 'ranker.yaml')) == str(tmp_path / 'ranker.yaml')
    with pytest.raises(LaunchArgumentError, match=r'checkpoint:=.*nope\.pt: no such file'):
        existing_file('checkpoint', str(tmp_path / 'nope.pt'))
