"""Lay out PREFIX/share as ``colcon build --symlink-install`` does for stars_ros: for each of
setup.py's data_files, a real folder holding a link to each of its files in this checkout
(edits are live; a new file needs a rerun). Not links to whole folders: ``ros2 launch``
finds launch files with os.walk, which does not enter a linked folder.

    python scripts/link_share.py PREFIX      (scripts/setup_venv.sh: PREFIX=.venv)
"""
import os
import shutil
import sys
import types
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def data_files() -> list:
    """setup.py's data_files: (folder under the prefix, [files relative to the checkout]),
    its globs read from the checkout."""
    captured, cwd = {}, os.getcwd()
    stand_in = types.SimpleNamespace(setup=lambda **kwargs: captured.update(kwargs),
                                     find_packages=lambda **kwargs: [])
    saved = sys.modules.get('setuptools')
    sys.modules['setuptools'] = stand_in
    os.chdir(REPO)
    try:
        setup_py = REPO / 'setup.py'
        exec(compile(setup_py.read_text(), 'setup.py', 'exec'), {'__file__': str(setup_py)})
    finally:
        os.chdir(cwd)
        if saved is None:
            del sys.modules['setuptools']
        else:
            sys.modules['setuptools'] = saved
    return captured['data_files']


def link_share(prefix: Path) -> None:
    share = prefix / 'share' / 'stars_ros'
    if share.is_symlink():
        share.unlink()
    elif share.exists():
        shutil.rmtree(share)  # an earlier layout (links to whole folders; rmtree removes links, not targets)
    for folder, files in data_files():
        destination = prefix / folder
        destination.mkdir(parents=True, exist_ok=True)
        for name in files:
            link = destination / Path(name).name
            if link.is_symlink() or link.exists():
                link.unlink()
            link.symlink_to(REPO / name)


if __name__ == '__main__':
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    link_share(Path(sys.argv[1]).resolve())
