"""What signed feedback costs the ranker: per feedback message, per shared rating, in bytes.

    python benchmarks/feedback_auth.py [--checkpoint models/socnav1_gat_stars.pt] \
        [--data-root ../shared/datasets/socnav1] [--count 2000] [--out results/feedback_auth.json]

In this process, on one thread, with the ranker's own core (``RankerCore``, recording off,
fold-in on) and real SocNav1 scenes ranked first, so feedback finds them:
  * ``accept_feedback``: the whole handling of one stars/feedback message (parse, schema,
    fold-in bookkeeping; the solve comes later, off this path), unsigned to a ranker
    without a key file and signed to one with; measured in ``--blocks`` blocks that
    alternate between the two (this VM's speed drifts within minutes); the difference of
    the medians is what verification adds to each message;
  * ``check``: ``FeedbackAuthenticator.check`` alone (canonical form, HMAC-SHA256,
    constant-time compare, window, replay memory) on messages already parsed;
  * ``check_rating``: the check of one peer rating under fleet sharing;
  * bytes: a feedback message and a shared rating (with its scene) without and with the
    signature, i.e. what signing adds to stars/feedback and to each rating on stars/user_model.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros.evaluation.provenance import git_state, machine  # noqa: E402
from stars_ros import feedback_auth, messages  # noqa: E402
from stars_ros.data.scene_source import read_scenes, scene_request  # noqa: E402
from stars_ros.node.core import RankerCore  # noqa: E402
from stars_ros.node.parameters import PARAMETERS, TOPICS  # noqa: E402

SECRET = bytes(range(32))


class Quiet:
    """The node's logger and publishers, doing nothing."""

    def info(self, line):
        pass

    warning = error = info


def _core(checkpoint: str, key_file: str, now) -> RankerCore:
    params = {name: spec[0] for name, spec in PARAMETERS.items()}
    params.update(checkpoint=checkpoint, record_folder='', feedback_key_file=key_file, fold_in_max_users=10 ** 6)
    return RankerCore(params, {t: '/' + t for t in TOPICS}, '/ranker', lambda topic, text: None, Quiet(), now)


def _rank(core: RankerCore, scenes: list):
    for scene in scenes:
        core.accept_scene(messages.dumps(scene_request(scene['identifier'], scene, 'alice')), 0)
    while core.work():
        pass


def _percentiles(values_us: list) -> dict:
    return {'p50': float(np.percentile(values_us, 50)), 'p99': float(np.percentile(values_us, 99)),
            'n': len(values_us)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', default='', help='ranker checkpoint (default: the packaged model)')
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--count', type=int, default=2000, help='feedback messages timed per ranker')
    parser.add_argument('--blocks', type=int, default=10)
    parser.add_argument('--out', default=str(REPO / 'results' / 'feedback_auth.json'))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    scenes = {s['identifier']: s for s in read_scenes(Path(args.data_root) / 'raw' / 'b.jsonl')}
    scenes = list(scenes.values())[:200]
    now = [time.time_ns()]
    with tempfile.TemporaryDirectory() as folder:
        key_file = Path(folder) / 'keys.txt'
        key_file.write_text(f'bench:{SECRET.hex()}\n')
        key_file.chmod(0o600)
        cores = {'unsigned': _core(args.checkpoint, '', lambda: now[0]),
                 'signed': _core(args.checkpoint, str(key_file), lambda: now[0])}
    for core in cores.values():
        _rank(core, scenes)

    def message(k: int, signed: bool) -> str:
        fields = {'user_id': f'user-{k}', 'scene_id': scenes[k % len(scenes)]['identifier'], 'action': 'navigate',
                  'score': round((k % 101) / 100, 2)}
        return json.dumps(feedback_auth.sign(fields, 'bench', SECRET, now[0]) if signed else fields)

    per_block = args.count // args.blocks
    timed = {'unsigned': [], 'signed': []}
    block_medians = {'unsigned': [], 'signed': []}
    for block in range(args.blocks):
        for name in (('unsigned', 'signed') if block % 2 == 0 else ('signed', 'unsigned')):
            core, texts = cores[name], [message(block * per_block + k, name == 'signed') for k in range(per_block)]
            times = []
            for text in texts:
                started = time.perf_counter_ns()
                taken = core.accept_feedback(text)
                times.append((time.perf_counter_ns() - started) / 1e3)
                if not taken:
                    raise RuntimeError(f'{name} feedback was refused: {text}')
            timed[name] += times
            block_medians[name].append(float(np.median(times)))
            core.personalisation.pending.clear()  # the solves are not what is timed here

    authenticator = feedback_auth.FeedbackAuthenticator({'bench': SECRET}, lambda: 60.0)
    payloads = [json.loads(message(10 ** 6 + k, True)) for k in range(args.count)]
    check_us = []
    for payload in payloads:
        started = time.perf_counter_ns()
        refusal = authenticator.check(payload, now[0])
        check_us.append((time.perf_counter_ns() - started) / 1e3)
        assert refusal is None, refusal

    signed_core = cores['signed']
    user, [rating] = next((u, r[:1]) for u, (r, _) in signed_core.personalisation.histories.snapshot().items())
    rating_us = []
    for _ in range(args.count):
        started = time.perf_counter_ns()
        refusal = authenticator.check_rating(user, rating)
        rating_us.append((time.perf_counter_ns() - started) / 1e3)
        assert refusal is None, refusal
    unsigned_rating = json.dumps({k: v for k, v in rating.to_json().items() if k != 'feedback'})
    sizes = {'feedback_unsigned': len(message(0, False)), 'feedback_signed': len(message(0, True)),
             'shared_rating_unsigned': len(unsigned_rating), 'shared_rating_signed': len(json.dumps(rating.to_json()))}
    for core in cores.values():
        core.close()

    accept = {name: _percentiles(values) for name, values in timed.items()}
    results = {
        'accept_feedback_us': accept,
        'accept_feedback_block_p50_us': block_medians,
        'verification_adds_us_p50': accept['signed']['p50'] - accept['unsigned']['p50'],
        'check_us': _percentiles(check_us), 'check_rating_us': _percentiles(rating_us), 'bytes': sizes,
        'settings': {'count': args.count, 'blocks': args.blocks, 'checkpoint': args.checkpoint or 'packaged default',
                     'scenes': 'SocNav1 b.jsonl, 200 distinct', 'machine': machine(), 'git': git_state()}}
    print(f"accept_feedback p50 / p99: unsigned {accept['unsigned']['p50']:.1f} / {accept['unsigned']['p99']:.1f} us, "
          f"signed {accept['signed']['p50']:.1f} / {accept['signed']['p99']:.1f} us "
          f"(+{results['verification_adds_us_p50']:.1f} us p50)")
    print(f"check alone p50 {results['check_us']['p50']:.1f} us, p99 {results['check_us']['p99']:.1f} us; "
          f"one peer rating p50 {results['check_rating_us']['p50']:.1f} us")
    print(f"bytes: feedback {sizes['feedback_unsigned']} -> {sizes['feedback_signed']}, shared rating "
          f"{sizes['shared_rating_unsigned']} -> {sizes['shared_rating_signed']}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2) + '\n')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
