"""What a robot gets from the serving install alone: a venv holding `pip install .` (no
`train` extra), rclpy's PyPI wheels and stars_ros_msgs built into it, and nothing else.

    python benchmarks/serving_install.py --venv /tmp/serving-venv --make [--train] [--full .venv] \
        [--starts 5] [--out results/serving_install.json]

``--make`` creates the venv first: ``python3.11 -m venv``, ``pip install -r requirements-rclpy.txt``,
``pip install`` of the checkout's committed tree (``git archive HEAD``), then stars_ros_msgs as
scripts/build_interfaces.sh builds it (``STARS_VENV`` naming the venv). Then, run from that venv
and from a scratch folder (so that nothing of the checkout is importable): ``python -c "import
torch"``, which must fail; the venv's size (``du -sm``) against ``--full``'s; ``--starts`` starts of
``ranker`` serving the packaged model, each timed from its process's start to the first ranking
that a client, already running in the same venv and domain, receives (the first start is the first
after the install when ``--make`` is given), then as many of ``--full``'s ranker for comparison;
and ``hri_bridge`` and ``feedback_page`` started for ``--watch`` seconds: whether each is still
running then, and its last lines. ``--train`` then installs the ``train`` extra into the venv
(``pip install '<tree>[train]'``) and, from a scratch folder holding copies of offline_training/
and config/, trains the quick-start model on SocNav1 (``--data-root``) and runs the quick
evaluation of one backbone: exit status, seconds and last lines of each.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def client(domain: int) -> None:
    """In the serving venv: publish one scene request every 50 ms once the ranker subscribes,
    until its ranking comes back; print when it did (time.time())."""
    import numpy as np
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    from stars_ros.data.scene_source import random_scene, scene_request

    rclpy.init(domain_id=domain)
    node = Node('serving_install_client')
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    publisher = node.create_publisher(String, 'stars/scene', qos)
    answered = []

    def on_ranking(message):
        if json.loads(message.data).get('scene_id') == 'probe' and not answered:
            answered.append(time.time())
    node.create_subscription(String, 'stars/ranking', on_ranking, qos)
    scene = random_scene(np.random.default_rng(0))
    request = String(data=json.dumps(scene_request('probe', scene, 'someone')))
    print('ready', flush=True)
    deadline = time.monotonic() + 120
    while not answered and time.monotonic() < deadline:
        if publisher.get_subscription_count():
            publisher.publish(request)
        rclpy.spin_once(node, timeout_sec=0.05)
    print(json.dumps({'answered_at': answered[0] if answered else None}), flush=True)


def run(command, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(command, capture_output=True, text=True, **kwargs)


def make(venv: Path) -> dict:
    """The serving-only venv at ``venv`` (replaced); seconds each step took."""
    if venv.exists():
        shutil.rmtree(venv)
    python, took = venv / 'bin' / 'python', {}
    source = Path(tempfile.mkdtemp(prefix='stars-ros-source-'))
    steps = [
        ('venv', [shutil.which('python3.11') or sys.executable, '-m', 'venv', str(venv)], {}),
        ('rclpy wheels',
         [str(python), '-m', 'pip', 'install', '--quiet', '-r', str(REPO / 'requirements-rclpy.txt')], {}),
        ('checkout', ['bash', '-c', f'git -C {REPO} archive HEAD | tar -x -C {source}'], {}),
        ('pip install .', [str(python), '-m', 'pip', 'install', '--quiet', str(source)], {}),
        ('stars_ros_msgs', ['bash', 'scripts/build_interfaces.sh', 'interfaces/stars_ros_msgs'],
         {'cwd': REPO, 'env': dict(os.environ, STARS_VENV=str(venv))}),
    ]
    for name, command, options in steps:
        started = time.perf_counter()
        done = run(command, **options)
        if done.returncode:
            raise SystemExit(f'{name}: {done.stderr[-2000:]}')
        took[name] = round(time.perf_counter() - started, 1)
        if name == 'pip install .':
            took['size_mb_before_stars_ros_msgs'] = megabytes(venv)  # the build tools come next
    shutil.rmtree(source)
    return took


def child_env(domain: int, home: Path) -> dict:
    env = {key: value for key, value in os.environ.items()
           if not key.startswith(('PYTHON', 'AMENT', 'VIRTUAL_ENV'))}
    return dict(env, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_HOME=str(home),
                PYTHONUNBUFFERED='1')


def first_answer(venv: Path, domain: int, scratch: Path) -> float:
    """Seconds from the ranker's process start to the client's receiving its first ranking."""
    env = child_env(domain, scratch / 'ros_home')
    waiting = subprocess.Popen([str(venv / 'bin' / 'python'), str(Path(__file__).resolve()), '--client',
                                str(domain)], cwd=scratch, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    if waiting.stdout.readline().strip() != 'ready':
        raise SystemExit(f'the client did not start: {waiting.stderr.read()[-2000:]}')
    started = time.time()
    ranker = subprocess.Popen([str(venv / 'bin' / 'ranker')], cwd=scratch, env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
    try:
        answered = json.loads(waiting.communicate(timeout=150)[0].splitlines()[-1])['answered_at']
    finally:
        ranker.send_signal(signal.SIGINT)
        try:
            ranker.wait(timeout=30)
        except subprocess.TimeoutExpired:
            ranker.kill()
            ranker.wait()
    if answered is None:
        raise SystemExit(f'the ranker did not answer: {ranker.stderr.read()[-2000:]}')
    return round(answered - started, 2)


def watch(venv: Path, executable: str, domain: int, scratch: Path, seconds: float) -> dict:
    """``executable`` started with its defaults: running after ``seconds``, or its exit and last lines."""
    process = subprocess.Popen([str(venv / 'bin' / executable), '--ros-args', '-p', 'port:=0']
                               if executable == 'feedback_page' else [str(venv / 'bin' / executable)],
                               cwd=scratch, env=child_env(domain, scratch / 'ros_home'),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        process.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        return {'running_after_s': seconds, 'last_lines': process.stdout.read().strip().splitlines()[-3:]}
    return {'exited': process.returncode, 'last_lines': process.stdout.read().strip().splitlines()[-3:]}


def train_extra(venv: Path, data_root: Path) -> dict:
    """The train extra installed into ``venv``, then a training and a quick evaluation run there."""
    source = Path(tempfile.mkdtemp(prefix='stars-ros-source-'))
    scratch = Path(tempfile.mkdtemp(prefix='train-'))
    run(['bash', '-c', f'git -C {REPO} archive HEAD | tar -x -C {source}'], check=True)
    for folder in ('offline_training', 'config'):
        shutil.copytree(source / folder, scratch / folder)
    python, record = str(venv / 'bin' / 'python'), {}
    steps = {
        'pip install .[train]': [python, '-m', 'pip', 'install', '--quiet', f'{source}[train]'],
        'train': [python, '-m', 'offline_training.train', '--config', 'config/quickstart.yaml', '--data-root',
                  str(data_root), '--out', str(scratch / 'model.pt')],
        'evaluate': [python, '-m', 'offline_training.evaluate', '--config', 'config/eval_socnav1.yaml',
                     '--quick', '--backbones', 'gcn', '--jobs', '1', '--data-root', str(data_root), '--out',
                     str(scratch / 'evaluation')],
    }
    for name, command in steps.items():
        started = time.perf_counter()
        done = run(command, cwd=scratch, env=child_env(0, scratch / 'ros_home'))
        record[name] = {'exit': done.returncode, 'seconds': round(time.perf_counter() - started, 1),
                        'last_lines': (done.stdout + done.stderr).strip().splitlines()[-3:]}
        if name == 'pip install .[train]':
            record[name]['size_mb_after'] = megabytes(venv)
        if done.returncode:
            break
    shutil.rmtree(source)
    shutil.rmtree(scratch)
    return record


def megabytes(folder: Path) -> int:
    return int(run(['du', '-sm', str(folder)], check=True).stdout.split()[0])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--venv', type=Path, required=True)
    parser.add_argument('--make', action='store_true', help='create the venv first (replacing it)')
    parser.add_argument('--full', type=Path, default=REPO / '.venv', help="the full venv (setup_venv.sh's)")
    parser.add_argument('--starts', type=int, default=5)
    parser.add_argument('--watch', type=float, default=8.0, help='seconds hri_bridge and feedback_page run')
    parser.add_argument('--train', action='store_true',
                        help='then install the train extra, train and evaluate')
    parser.add_argument('--data-root', type=Path, default=REPO.parent / 'shared' / 'datasets' / 'socnav1')
    parser.add_argument('--out', type=Path, default=REPO / 'results' / 'serving_install.json')
    args = parser.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from stars_ros.evaluation.provenance import program_argv, run_record
    from stars_ros.files import atomic_write
    from test_support.loopback import domain_id

    venv = args.venv.resolve()
    record = {**run_record(program_argv('benchmarks/serving_install.py', argv)), 'venv': str(venv),
              'made_s': make(venv) if args.make else None}
    scratch = Path(tempfile.mkdtemp(prefix='serving-install-'))
    python = str(venv / 'bin' / 'python')
    torch = run([python, '-c', 'import torch'], cwd=scratch, env=child_env(domain_id(0), scratch))
    record['import_torch'] = {'exit': torch.returncode, 'last_line': torch.stderr.strip().splitlines()[-1]}
    record['size_mb'] = {'serving': megabytes(venv),
                         'full': megabytes(args.full) if args.full.is_dir() else None}
    record['first_answer_s'] = [first_answer(venv, domain_id(1 + k), scratch) for k in range(args.starts)]
    if args.full.is_dir():  # the full venv's ranker, started the same way on this machine now, for comparison
        record['full_first_answer_s'] = [first_answer(args.full.resolve(), domain_id(1 + k), scratch)
                                         for k in range(args.starts)]
    record['hri_bridge'] = watch(venv, 'hri_bridge', domain_id(1 + args.starts), scratch, args.watch)
    record['feedback_page'] = watch(venv, 'feedback_page', domain_id(2 + args.starts), scratch, args.watch)
    shutil.rmtree(scratch)
    if args.train:
        record['train_extra'] = train_extra(venv, args.data_root.resolve())
    print(json.dumps(record, indent=2))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out, lambda handle: handle.write((json.dumps(record, indent=2) + '\n').encode()))
    return 0


if __name__ == '__main__':
    if sys.argv[1:2] == ['--client']:
        client(int(sys.argv[2]))
    else:
        sys.exit(main())
