"""The runtime pins resolve for Python 3.12, Jazzy's on Ubuntu 24.04 (docs/interfaces.md, "In a
ROS workspace"), without a 3.12 interpreter: pip's resolver in dry-run mode with
``--python-version 3.12 --only-binary=:all:`` picks, for every pin, a wheel a CPython 3.12
can install. pip evaluates environment markers for the running interpreter, not for 3.12;
requirements.txt has none. It needs the package index, as scripts/setup_venv.sh does: with
none reachable it fails, saying so, rather than skipping (a skip here could never fail offline)."""
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
OFFLINE = ('NewConnectionError', 'Failed to establish a new connection', 'Temporary failure in name resolution',
           'Network is unreachable', 'Could not fetch URL', 'ConnectTimeoutError', 'ReadTimeoutError')
WHEEL_TAGS = re.compile(r'-(cp312-cp312|cp312-abi3|cp3\d+-abi3|py3-none|py2\.py3-none)-[^-]+\.whl$')


@pytest.mark.slow
def test_the_runtime_pins_resolve_to_python_312_wheels(tmp_path):
    report = tmp_path / 'report.json'
    resolved = subprocess.run(
        [sys.executable, '-m', 'pip', 'install', '--dry-run', '--quiet', '--python-version', '3.12',
         '--only-binary=:all:', '--ignore-installed', '-r', str(REPO / 'requirements.txt'), '--report', str(report)],
        capture_output=True, text=True, timeout=600)
    offline = resolved.returncode != 0 and any(sign in resolved.stderr for sign in OFFLINE)
    assert not offline, 'no package index reachable: this test resolves the pins against it'
    assert resolved.returncode == 0, resolved.stderr[-3000:]
    installs = {item['metadata']['name'].lower().replace('_', '-'): item for item in json.loads(report.read_text())[
        'install']}
    pins = [line.split('#', 1)[0].strip() for line in (REPO / 'requirements.txt').read_text().splitlines()]
    for pin in filter(None, pins):
        name, version = pin.split('==')
        item = installs[name.lower().replace('_', '-')]
        assert item['metadata']['version'] == version, pin
        wheel = item['download_info']['url'].rsplit('/', 1)[-1]
        assert WHEEL_TAGS.search(wheel), f'{pin}: {wheel} is not a wheel for CPython 3.12'
