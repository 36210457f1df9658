"""The evaluation's fits as Ray tasks (stars_ros.evaluation.ray_executor) and where the programs run their fits
(offline_training.common): same records as the process pool, failures named, a killed run resumed."""
import argparse
import json
import math
import multiprocessing
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import ray
import yaml

from offline_training import evaluate
from offline_training.common import add_executor_options, build_executor
from stars_ros.model.config import ExperimentConfig
from stars_ros.evaluation.ray_executor import RayExecutor, fit_slots
from stars_ros.errors import StarsError
from stars_ros.evaluation.executors import FitFailure, FitTask, fit_executor, fit_outcome, run_fits
from waiting import wait_for

REPO = Path(__file__).resolve().parents[2]
QUICK = ['--quick', '--backbones', 'gcn']
METRICS = ('mse', 'rmse', 'pearson_r', 'ccc', 'z_rmse')


@pytest.fixture(scope='module')
def ray_address():
    """One local Ray instance for the module (starting one takes seconds): 2 CPUs, a small
    object store, no dashboard, its sockets and logs in a fresh temporary folder. Ray picks
    free ports for a local instance (GCS port 0, the others random), so another test run on
    this machine does not meet this one. Token authentication is off, so that nothing is
    written under ~/.ray; the drivers the tests start inherit that."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv('RAY_AUTH_MODE', 'disabled')
        folder = tempfile.mkdtemp(prefix='ray', dir='/tmp')  # short: socket paths are limited to 107 bytes
        ray.init(address='local', num_cpus=2, object_store_memory=128 * 2 ** 20, include_dashboard=False,
                 _temp_dir=folder)
        try:
            yield ray.get_runtime_context().gcs_address
        finally:
            ray.shutdown()
            shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope='module')
def pool_run(synthetic_root, tmp_path_factory):
    """``evaluate --quick`` on two worker processes: the reference the Ray runs must equal."""
    out = tmp_path_factory.mktemp('pool')
    assert evaluate.main([*QUICK, '--jobs', '2', '--data-root', str(synthetic_root), '--out', str(out)]) == 0
    return out


def records(folder: Path) -> dict:
    """The complete entries of ``folder/records.jsonl`` by fit (a line cut short by a kill is left out)."""
    entries = {}
    for line in (folder / 'records.jsonl').read_text().splitlines():
        try:
            entry = json.loads(line)
        except json.JSONDecodeError:
            continue
        entries[entry['model'], entry['fold'], entry['stage'], entry.get('fraction'), entry.get('inner_fold'),
                entry['T1'], entry['T2'], json.dumps(entry['settings'], sort_keys=True)] = entry
    return entries


def assert_same_scores(found: dict, expected: dict) -> None:
    assert found.keys() == expected.keys()
    for key, entry in expected.items():
        for metric in METRICS:
            if metric in entry and not math.isnan(entry[metric]):
                assert found[key][metric] == pytest.approx(entry[metric], abs=1e-6), (key, metric)


def tiny_task(name: str, train: np.ndarray, joint_epochs: int = 1) -> FitTask:
    """A small StARS-GCN fit (one pre-training epoch, ``joint_epochs`` joint ones) on
    ``train``, scored on rows 300-449."""
    experiment = ExperimentConfig.from_dict({
        'encoder': {'name': 'gcn', 'hidden': 8, 'layers': 1}, 'model': {'dim': 8, 'variant': 'stars'},
        'training': {'pretrain_epochs': 1, 'joint_epochs': joint_epochs, 'lr': 3e-3, 'threads': 1, 'seed': 0}})
    return FitTask(name, '0:0', 'final', experiment.to_dict(), train, np.arange(300, 450))


@pytest.mark.slow  # the module's local Ray instance takes about 10 s to start
def test_ray_runs_the_grid_to_the_process_pools_records(synthetic_root, tmp_path, ray_address, pool_run):
    """Every fit a Ray task, as many in flight as the instance's 2 CPUs hold: the same fits
    and scores as two worker processes."""
    out = tmp_path / 'ray'
    assert evaluate.main([*QUICK, '--executor', 'ray', '--data-root', str(synthetic_root), '--out', str(out)]) == 0
    assert_same_scores(records(out), records(pool_run))
    written = yaml.safe_load((out / 'config.yaml').read_text())
    assert written['jobs'] == 2 and written['executor'] == {
        'kind': 'ray', 'address': ray_address, 'cpus_per_fit': 1.0, 'gpus_per_fit': 0.0, 'max_retries': 3}
    assert '| GCN StARS |' in (out / 'tables.md').read_text()


@pytest.mark.slow  # the module's local Ray instance takes about 10 s to start
def test_a_fit_that_raises_on_a_ray_worker_is_named_and_the_others_finish(synthetic, ray_address, caplog):
    """A fit with no rows to train on raises in its worker: it comes back as a failure with
    that error, logged by name with the worker's traceback, and the fits beside it finish."""
    rows = np.arange(300)
    waiting = [(tiny_task('first', rows),), (tiny_task('no rows', rows[:0]),), (tiny_task('third', rows[::2]),)]
    outcomes = {item[0].model: scores for item, scores in run_fits(RayExecutor(synthetic), waiting, 2)}
    assert outcomes['no rows'] == FitFailure('ValueError: no training rows')
    assert all(0 < outcomes[name]['mse'] < 1 for name in ('first', 'third'))
    failure, = (r for r in caplog.records if r.name == 'stars_ros.evaluation.executors')
    assert failure.getMessage() == 'no rows fold 0:0 final (T1, T2) = (1, 1) failed'
    assert 'raised in a Ray worker' in caplog.text  # the worker's traceback


@pytest.mark.slow  # the module's local Ray instance takes about 10 s to start
def test_a_ray_task_whose_worker_dies_runs_again(ray_address, tmp_path):
    """A task that kills its worker on its first run: retried, it finishes; without retries
    it is a failure that names the dead worker."""
    marker = tmp_path / 'died once'

    def die_once():  # defined here, so that Ray sends the function itself to the worker
        if not marker.exists():
            marker.touch()
            os._exit(1)
        return 'finished'

    retrying = RayExecutor(None, max_retries=1)
    assert retrying.submit(die_once).result(timeout=120) == 'finished'
    retrying.shutdown()
    marker.unlink()
    once = RayExecutor(None, max_retries=0)
    outcome = fit_outcome(once.submit(die_once), 'the task that dies')
    once.shutdown()
    assert isinstance(outcome, FitFailure) and outcome.error.startswith('WorkerCrashedError: ')


def test_dead_worker_processes_fail_the_fits_left_and_the_run_goes_on(synthetic):
    """The process pool cannot replace a worker that died: the fits not finished by then
    come back as failures, none of them raises. The first fit is one epoch, the others a
    hundred thousand, so none of them can finish before the workers are killed."""
    others = set(multiprocessing.active_children())
    waiting = [(tiny_task('fit 0', np.arange(300)),)]
    waiting += [(tiny_task(f'fit {i}', np.arange(300), joint_epochs=100_000),) for i in range(1, 4)]
    outcomes = []
    for item, scores in run_fits(fit_executor(synthetic, 2, 1), waiting, 2):
        if not outcomes:  # the short fit is done: kill the workers while a long one runs
            assert item[0].model == 'fit 0' and not isinstance(scores, FitFailure)
            for worker in set(multiprocessing.active_children()) - others:
                os.kill(worker.pid, signal.SIGKILL)
        outcomes.append(scores)
    failures = [o for o in outcomes if isinstance(o, FitFailure)]
    assert len(outcomes) == 4 and len(failures) == 3
    assert all(f.error.startswith('BrokenProcessPool: ') for f in failures)


@pytest.mark.slow
def test_a_killed_ray_run_resumes_without_refitting_what_it_finished(synthetic_root, tmp_path, ray_address, pool_run):
    """The driver of a run on a Ray cluster killed after some fits; a new driver with
    --resume runs only the fits left and ends with the records of an uninterrupted run.
    The kill lands wherever the driver is then (mid-fit, mid-write, or, on a rare fast turn,
    after its last record): the resumed run must end the same from any of them."""
    out = tmp_path / 'killed'
    with (tmp_path / 'log.txt').open('w') as log:
        driver = subprocess.Popen(
            [sys.executable, '-m', 'offline_training.evaluate', *QUICK, '--executor', 'ray', '--ray-address',
             ray_address, '--data-root', str(synthetic_root), '--out', str(out)],
            cwd=REPO, env={**os.environ, 'PYTHONPATH': str(REPO)}, stdout=log, stderr=log)

        def ten_records_or_ended():  # 2 population means + 8 fits
            return driver.poll() is not None or (out / 'records.jsonl').exists() and len(records(out)) >= 10
        assert wait_for(ten_records_or_ended, 240), (tmp_path / 'log.txt').read_text()[-3000:]
        assert driver.poll() in (None, 0), (tmp_path / 'log.txt').read_text()[-3000:]  # running, or done just now
        driver.kill()
        driver.wait()
    kept = records(out)
    kept_fits = {key: entry for key, entry in kept.items() if entry.get('variant') != 'population_mean'}
    assert 10 <= len(kept) <= len(records(pool_run))
    assert evaluate.main([*QUICK, '--executor', 'ray', '--resume', '--data-root', str(synthetic_root),
                          '--out', str(out)]) == 0
    resumed = json.loads((out / 'results.json').read_text())
    assert resumed['timing']['resumed_fits'] == len(kept_fits)
    final = records(out)
    for key, entry in kept_fits.items():  # taken over as they were: the same fit time, so not fitted again
        assert final[key]['fit_seconds'] == entry['fit_seconds']
    assert_same_scores(final, records(pool_run))


def test_the_core_imports_without_ray_and_asking_for_it_names_the_requirements(synthetic_root, tmp_path):
    child = '''
import importlib.abc, json, sys


class NoRay(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] == 'ray':
            raise ImportError('ray is made unimportable by this test', name=name)


sys.meta_path.insert(0, NoRay())
import stars_ros.evaluation.protocol
import stars_ros.evaluation.summaries
from offline_training import evaluate, kshot, learning_curve
imported = 'ray' in sys.modules
status = evaluate.main(['--quick', '--executor', 'ray', '--data-root', sys.argv[1], '--out', sys.argv[2]])
print(json.dumps({'imported': imported, 'status': status}))
'''
    done = subprocess.run([sys.executable, '-c', child, str(synthetic_root), str(tmp_path / 'out')], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert json.loads(done.stdout.splitlines()[-1]) == {'imported': False, 'status': 2}, done.stderr[-2000:]
    assert 'pip install -r requirements-ray.txt' in done.stderr


def options(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_executor_options(parser)
    return parser.parse_args(argv)


@pytest.mark.parametrize('argv, devices, message', [
    (['--gpus-per-fit', '0.1'], ['cuda'], '--gpus-per-fit go with --executor ray'),
    (['--jobs', '0'], ['cpu'], '--jobs must be positive'),
    (['--executor', 'ray'], ['cuda'], 'fits on the GPU need --gpus-per-fit'),
    (['--executor', 'ray', '--gpus-per-fit', '0.1'], ['cpu'], 'give --device cuda'),
    (['--executor', 'ray', '--gpus-per-fit', '0.1'], ['cuda:1'], "train on 'cuda', not 'cuda:1'"),
])
def test_contradictory_executor_options_are_refused(argv, devices, message):
    with pytest.raises(StarsError, match=message):
        build_executor(options(*argv), None, devices=devices)


def test_fits_in_flight_follow_each_nodes_resources():
    nodes = [{'CPU': 16.0, 'GPU': 1.0}, {'CPU': 3.0}]
    assert fit_slots(nodes, 1, 0) == 19
    assert fit_slots(nodes, 2, 0) == 8 + 1  # a fit does not straddle two nodes
    assert fit_slots(nodes, 1, 0.1) == 10  # the GPU holds ten; the node without one none
    assert fit_slots([{'CPU': 8.0, 'GPU': 0.3}], 0, 0.1) == 3  # not 2: 0.3 / 0.1 rounds below 3
