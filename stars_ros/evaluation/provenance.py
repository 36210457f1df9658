"""How a run was made, as every results folder and checkpoint records it: the command, the
checkout's commit (and whether it had uncommitted changes) and the machine.

Imports nothing heavy: torch's version is read from its installed metadata, so a benchmark
of a process that never loads torch can record it too.
"""
from __future__ import annotations

import importlib.metadata
import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

from stars_ros.errors import StarsError

REPO = Path(__file__).resolve().parents[2]  # the checkout this package runs from


def machine(device: str | None = None) -> dict:
    """What the figures were measured on (and ``device``, where the run names one)."""
    found = {'platform': platform.platform(), 'python': platform.python_version(), 'torch': _torch_version(),
             'cpus': os.cpu_count(), 'processor': platform.processor() or platform.machine()}
    return found if device is None else {**found, 'device': device}


def _torch_version() -> str | None:
    if 'torch' in sys.modules:
        return str(sys.modules['torch'].__version__)
    try:
        return importlib.metadata.version('torch')
    except importlib.metadata.PackageNotFoundError:
        return None


def git_state(ignoring: Path | None = None) -> dict:
    """Commit and whether the checkout had uncommitted changes to tracked files (results must
    say), not counting those under ``ignoring`` (a run's own results folder, whose records it
    writes); None for both where the package does not run from a git checkout."""
    def git(*command):
        done = subprocess.run(['git', *command], cwd=REPO, capture_output=True, text=True, timeout=30)
        if done.returncode:
            raise subprocess.SubprocessError(done.stderr)
        return done.stdout.strip()
    paths = ['--', '.']
    if ignoring is not None and Path(ignoring).resolve().is_relative_to(REPO):
        paths.append(f':(exclude){Path(ignoring).resolve().relative_to(REPO)}')
    try:
        return {'commit': git('rev-parse', 'HEAD'),
                'dirty': bool(git('status', '--porcelain', '--untracked-files=no', *paths))}
    except (OSError, subprocess.SubprocessError):
        return {'commit': None, 'dirty': None}


def refuse_uncommitted(out: Path, allowed: bool) -> None:
    """Refuse a run from a checkout with uncommitted changes outside its results folder ``out``
    unless ``allowed`` (``--allow-dirty``, ``--quick``): a run that results cite starts from a
    commit, so its records name what ran."""
    if not allowed and git_state(ignoring=Path(out))['dirty']:
        raise StarsError('tracked files have uncommitted changes: commit the config and the code this run '
                         'uses first, so its records name what ran (or --allow-dirty)')


def program_argv(program: str, argv: list[str] | None = None) -> list[str]:
    """The command line that runs ``program`` with ``argv`` (default: this process's
    arguments): ``python -m program`` for a module name, ``python program`` for a script's
    path (one ending in ``.py``), as a reader types it from the repository root."""
    arguments = sys.argv[1:] if argv is None else list(argv)
    return ['python', program, *arguments] if program.endswith('.py') else ['python', '-m', program, *arguments]


def run_record(program_argv: list[str], device: str | None = None) -> dict:
    """``{'command', 'git', 'machine'}`` of a run started as ``program_argv``."""
    return {'command': shlex.join(program_argv), 'git': git_state(), 'machine': machine(device)}


def write_run_files(folder: Path, record: dict, **more) -> None:
    """``command.txt`` and ``machine.json`` (the machine, the git state and ``more``) of the
    run ``record`` (``run_record``'s) into ``folder``."""
    (folder / 'command.txt').write_text(record['command'] + '\n')
    (folder / 'machine.json').write_text(json.dumps({**record['machine'], 'git': record['git'], **more}, indent=2))
