"""Atomic file writes: the new content or the old, never a part, and no temporary left."""
import pytest

from stars_ros.files import atomic_write


def test_replaces_the_file_and_leaves_only_it(tmp_path):
    path = tmp_path / 'state.json'
    path.write_bytes(b'old')
    atomic_write(path, lambda handle: handle.write(b'new'))
    assert path.read_bytes() == b'new'
    assert [p.name for p in tmp_path.iterdir()] == ['state.json']


def test_a_failed_write_keeps_the_old_content_and_no_temporary(tmp_path):
    path = tmp_path / 'state.json'
    path.write_bytes(b'old')

    def half_then_fail(handle):
        handle.write(b'ne')
        raise OSError('No space left on device')

    with pytest.raises(OSError, match='No space left'):
        atomic_write(path, half_then_fail)
    assert path.read_bytes() == b'old'
    assert [p.name for p in tmp_path.iterdir()] == ['state.json']


def test_a_missing_folder_is_an_oserror(tmp_path):
    with pytest.raises(FileNotFoundError):
        atomic_write(tmp_path / 'missing' / 'state.json', lambda handle: handle.write(b'x'))
