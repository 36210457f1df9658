"""How a run was made, recorded once for every program and benchmark (issue 50)."""
import importlib.metadata
import json
import re
import subprocess
import sys

from stars_ros.evaluation import provenance


def test_a_module_runs_with_dash_m_and_a_script_by_its_path():
    assert provenance.program_argv('offline_training.evaluate', ['--out', 'a b']) == [
        'python', '-m', 'offline_training.evaluate', '--out', 'a b']
    assert provenance.program_argv('benchmarks/state_scale.py', []) == ['python', 'benchmarks/state_scale.py']


def test_the_record_quotes_the_command_as_a_shell_reads_it():
    record = provenance.run_record(['python', '-m', 'offline_training.kshot', '--out', 'a b'], device='cuda:1')
    assert record['command'] == "python -m offline_training.kshot --out 'a b'"
    assert record['machine']['device'] == 'cuda:1' and record['machine']['cpus'] >= 1
    commit = record['git']['commit']
    assert commit is None or re.fullmatch('[0-9a-f]{40}', commit)
    assert 'device' not in provenance.machine()


def test_the_run_files_hold_the_command_the_machine_and_the_git_state(tmp_path):
    record = provenance.run_record(['python', 'benchmarks/featurise.py'])
    provenance.write_run_files(tmp_path, record, load_average_start=[0.5])
    assert (tmp_path / 'command.txt').read_text() == 'python benchmarks/featurise.py\n'
    written = json.loads((tmp_path / 'machine.json').read_text())
    assert written == {**record['machine'], 'git': record['git'], 'load_average_start': [0.5]}


def test_the_machine_names_torch_without_importing_it():
    script = ('import sys; from stars_ros.evaluation import provenance; '
              "print(provenance.machine()['torch'], 'torch' in sys.modules)")
    shown = subprocess.run([sys.executable, '-c', script], check=True, capture_output=True, text=True).stdout.split()
    assert shown == [importlib.metadata.version('torch'), 'False']


def test_a_runs_own_results_folder_does_not_make_the_tree_dirty(tmp_path, monkeypatch):
    """``git_state(ignoring=out)``: records a resumed run wrote into its own folder are not
    uncommitted work; a change anywhere else is."""
    def git(*command):
        subprocess.run(['git', '-c', 'user.name=t', '-c', 'user.email=t@t', *command], cwd=tmp_path,
                       check=True, capture_output=True)
    (tmp_path / 'results' / 'run').mkdir(parents=True)
    (tmp_path / 'results' / 'run' / 'records.jsonl').write_text('{}\n')
    (tmp_path / 'config.yaml').write_text('a: 1\n')
    git('init', '-q')
    git('add', '.')
    git('commit', '-qm', 'start')
    monkeypatch.setattr(provenance, 'REPO', tmp_path)
    out = tmp_path / 'results' / 'run'
    assert provenance.git_state(ignoring=out)['dirty'] is False
    (out / 'records.jsonl').write_text('{}\n{}\n')
    assert provenance.git_state()['dirty'] is True
    assert provenance.git_state(ignoring=out)['dirty'] is False
    assert provenance.git_state(ignoring=tmp_path.parent / 'elsewhere')['dirty'] is True
    (tmp_path / 'config.yaml').write_text('a: 2\n')
    assert provenance.git_state(ignoring=out)['dirty'] is True
