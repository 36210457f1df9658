"""Seconds per training epoch with and without a competing CPU-bound process, per thread setting.

    python benchmarks/thread_load.py [--config config/socnav1_gat.yaml] [--epochs 3] \
        [--out results/thread_load.json]

Trains the config's model (as ``offline_training.train`` does, on its seeded split) in a
fresh process for each condition: torch threads 1 or 2, OpenMP's default wait policy or
``OMP_WAIT_POLICY=PASSIVE``, alone or beside one busy-looping process. OpenMP's threads
busy-wait between parallel regions by default; on a machine whose cores are all taken they
spin against the other load instead of sleeping, which is what makes a shared machine's
training collapse rather than slow down in proportion. Prints a table and writes JSON.
"""
import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # offline_training is the checkout's, not installed
from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros.evaluation.provenance import program_argv, run_record  # noqa: E402

FIT = '''
import sys, time
from stars_ros.model.config import ExperimentConfig
from stars_ros.data.ratings import load_dataset
from stars_ros.model.training import StarsTrainer, split_rows
config = ExperimentConfig.from_yaml(sys.argv[1]).replace(
    training={'pretrain_epochs': 0, 'joint_epochs': int(sys.argv[3]), 'threads': int(sys.argv[4])})
data = load_dataset(sys.argv[2])
train, _ = split_rows(data, config.split.test_fraction, config.split.seed)
started = time.perf_counter()
StarsTrainer(config).fit(data, train)
print((time.perf_counter() - started) / int(sys.argv[3]))
'''
BUSY = 'while True:\n    pass\n'


def seconds_per_epoch(args, threads: int, policy: str | None, busy: bool) -> float:
    env = {k: v for k, v in os.environ.items() if k != 'OMP_WAIT_POLICY'}
    env['PYTHONPATH'] = str(REPO)
    if policy:
        env['OMP_WAIT_POLICY'] = policy
    competitor = subprocess.Popen([sys.executable, '-c', BUSY]) if busy else None
    try:
        done = subprocess.run([sys.executable, '-c', FIT, args.config, args.data_root, str(args.epochs), str(threads)],
                              env=env, capture_output=True, text=True, timeout=args.timeout, check=True)
    finally:
        if competitor is not None:
            competitor.kill()
            competitor.wait()
    return float(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--config', default=str(REPO / 'config' / 'socnav1_gat.yaml'))
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--epochs', type=int, default=3)
    parser.add_argument('--timeout', type=int, default=900, help='seconds one condition may take')
    parser.add_argument('--out', default=str(REPO / 'results' / 'thread_load.json'))
    args = parser.parse_args()
    conditions = [(1, None), (2, None), (2, 'PASSIVE')]
    rows = []
    print(f'{args.config}, {args.epochs} epochs per condition, {os.cpu_count()} CPUs', flush=True)
    print('| torch threads | OMP_WAIT_POLICY | s/epoch alone | s/epoch beside a busy process | ratio |')
    print('| --- | --- | --- | --- | --- |', flush=True)
    for threads, policy in conditions:
        alone = seconds_per_epoch(args, threads, policy, busy=False)
        loaded = seconds_per_epoch(args, threads, policy, busy=True)
        rows.append({'threads': threads, 'omp_wait_policy': policy or 'default', 'alone': alone, 'busy': loaded})
        print(f"| {threads} | {policy or 'default'} | {alone:.2f} | {loaded:.2f} | {loaded / alone:.1f} |", flush=True)
    Path(args.out).write_text(json.dumps({**run_record(program_argv('benchmarks/thread_load.py')),
                                          'config': args.config, 'epochs': args.epochs,
                                          'load_average_start': os.getloadavg(), 'conditions': rows},
                                         indent=2) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
