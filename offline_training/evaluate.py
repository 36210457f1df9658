"""Run the evaluation protocol (cross-validation, paired tests, sparsity sweep) and write a results folder.

    python -m offline_training.evaluate --config config/eval_socnav1.yaml \
        --protocol rows --jobs 2 --out OUT [--quick] [--backbones gcn,gat] [--device cuda] \
        [--executor ray [--ray-address HOST:PORT] [--cpus-per-fit 1] [--gpus-per-fit 0.1]] [--allow-dirty]

A run starts from a commit: with uncommitted changes to tracked files outside ``--out`` it is
refused (``--allow-dirty`` runs anyway, ``--quick`` always may; the records say which).

Writes into ``--out`` (required: a run never writes into the repository unasked): ``command.txt``,
``config.yaml`` (the resolved protocol), ``machine.json``, ``records.jsonl`` (each fit's
result as it arrives, selection fits too, so a long run that stops keeps what it finished
and ``--resume`` goes on from there; each says under ``fitted_by`` the commit, dirty flag and
device of the process that made it, so a resumed run's records name both), ``folds.csv`` (per model,
fold and training fraction), ``selection.csv`` (inner validation of every (T1, T2)),
``tests.csv``, ``results.json`` (everything), ``tables.md`` (the paper's tables, the
paired tests, the sparsity table and where the time went) and ``sparsity_<metric>.png``.
A fit that fails (raises, or its worker dies) is named on stderr and in ``failed.jsonl``;
the others go on, and the run ends with status 1 without tables, which would compare models
on different folds; ``--resume`` runs the failed fits again.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import yaml

from stars_ros.data.ratings import load_dataset
from stars_ros.errors import StarsError
from stars_ros.evaluation import peers
from stars_ros.evaluation.folds import PROTOCOLS
from stars_ros.evaluation.protocol import ProtocolConfig, model_specs, run_protocol
from stars_ros.evaluation.provenance import program_argv, refuse_uncommitted, run_record, write_run_files
from stars_ros.evaluation.report import SUMMARY_FILES, json_default, previous_entries, report_failures, write_results
from stars_ros.model.config import ExperimentConfig

from .common import DEFAULT_SOCNAV1, add_executor_options, build_executor, cuda_info, setup_logging

REPO = Path(__file__).resolve().parents[1]


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--config', default=str(REPO / 'config' / 'eval_socnav1.yaml'),
                        help='protocol YAML (default: %(default)s)')
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1),
                        help='SocNav1 root or generic-format root (default: %(default)s)')
    parser.add_argument('--protocol', choices=PROTOCOLS, default='rows',
                        help='fold grouping: annotation rows (published), scenes or annotators')
    parser.add_argument('--quick', action='store_true',
                        help='merge config/eval_quick.yaml (fewer folds and epochs, tiny model)')
    parser.add_argument('--backbones', help='comma-separated subset of the config\'s backbones')
    parser.add_argument('--threads', type=int, default=1,
                        help='torch threads per job (default: %(default)s; more busy-wait and collapse on a '
                             'shared machine)')
    parser.add_argument('--device', help="where every fit trains: 'cpu', 'cuda' or 'cuda:N' (default: the "
                                         "config's experiment.training.device, else cpu); jobs share the GPU")
    parser.add_argument('--out', required=True, help='results folder (created; the run name is the config\'s)')
    parser.add_argument('--resume', action='store_true',
                        help="reuse the fits in the folder's records.jsonl from an earlier run with the same "
                             'config.yaml (jobs, threads and the executor may differ) and run only the rest')
    parser.add_argument('--allow-dirty', action='store_true',
                        help='run although tracked files outside --out have uncommitted changes (the records say '
                             'dirty; a run that results cite starts from a commit, so without this it is refused; '
                             '--quick always may)')
    parser.add_argument('--verbose', action='store_true', help='log every fit')
    add_executor_options(parser)
    return parser.parse_args(argv)


def configure(args) -> ProtocolConfig:
    config = ProtocolConfig.from_yaml(args.config, REPO / 'config' / 'eval_quick.yaml' if args.quick else None)
    if args.backbones:
        chosen = [b.strip() for b in args.backbones.split(',') if b.strip()]
        unknown = sorted(set(chosen) - set(config.backbones))
        if unknown:
            raise StarsError(f'--backbones {unknown} not in the config (it has {list(config.backbones)})')
        values = config.to_dict()
        values['backbones'] = {b: config.backbones[b] for b in chosen}
        values['sweep_backbones'] = [b for b in config.sweep_backbones if b in chosen]
        values['ablation_backbones'] = [b for b in config.ablation_backbones if b in chosen]
        config = ProtocolConfig.from_dict(values)
    if args.device:
        config = ProtocolConfig.from_dict(config.to_dict(), {'experiment': {'training': {'device': args.device}}})
    peers.require(config.baselines)  # before anything is written: a resumed folder keeps its records
    return config


def main(argv=None) -> int:
    args = parse_args(argv)
    setup_logging(args.verbose)
    logging.getLogger('stars_ros.evaluation').setLevel(logging.INFO)
    try:
        config = configure(args)
        device = ExperimentConfig.from_dict(config.experiment).training.device
        if args.threads < 1:
            raise StarsError('--threads must be positive')
        refuse_uncommitted(Path(args.out), args.quick or args.allow_dirty)
        started = time.perf_counter()
        data = load_dataset(args.data_root)
        load_seconds = time.perf_counter() - started
        fits = build_executor(args, data, args.threads, [device])
    except (StarsError, OSError) as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    threads = args.threads
    name = f"{config.name}-{args.protocol}{'-quick' if args.quick else ''}"
    folder = Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    header = {**run_record(program_argv('offline_training.evaluate', argv), device),
              'load_start': [round(v, 2) for v in os.getloadavg()],
              'data': f'{data.source} ({len(data)} ratings, {len(set(data.users.tolist()))} users, '
                      f'{len(data.scene_keys)} scenes, fingerprint {data.fingerprint[:12]})'}
    settings = yaml.safe_load(yaml.safe_dump(  # as config.yaml reads back
        {'protocol': args.protocol, 'quick': args.quick, 'data_root': str(args.data_root),
         'data_fingerprint': data.fingerprint, 'jobs': fits.jobs, 'threads': threads, 'executor': fits.settings,
         'device': device, **config.to_dict()}, sort_keys=False))
    try:
        previous = previous_entries(folder, settings) if args.resume else []
    except StarsError as error:
        fits.executor.shutdown()
        print(f'error: {error}', file=sys.stderr)
        return 2
    for stale in SUMMARY_FILES:
        (folder / stale).unlink(missing_ok=True)
    (folder / 'config.yaml').write_text(yaml.safe_dump(settings, sort_keys=False))
    write_run_files(folder, header, load_average_start=header['load_start'])
    where = ' as Ray tasks' if args.executor == 'ray' else ''
    print(f'{name}: {len(model_specs(config))} models × {len(config.seeds) * config.folds} folds; '
          f'{fits.jobs} job(s) × {threads} thread(s) on {device}{where}; writing {folder}', flush=True)
    if previous:
        print(f'resuming: {len(previous)} entries in the earlier records.jsonl; their fits are not run again',
              flush=True)
    with (folder / 'records.jsonl').open('w') as stream:
        def keep(entry):
            stream.write(json.dumps(entry, default=json_default) + '\n')
            stream.flush()
        try:
            result = run_protocol(data, config, args.protocol, jobs=fits.jobs, threads=threads, on_record=keep,
                                  resume=previous, executor=fits.executor,
                                  fitted_by={**header['git'], 'device': device})
        except (StarsError, ValueError) as error:
            print(f'error: {error}', file=sys.stderr)
            return 1
    header['machine'].update(cuda_info(device))  # the GPU's name, now that the workers are done with it
    write_run_files(folder, header, load_average_start=header['load_start'])
    if result.failed:
        report_failures(folder, result)
        return 1

    write_results(folder, result, config, header, header['command'], args.protocol, load_seconds)
    print((folder / 'tables.md').read_text())
    return 0


if __name__ == '__main__':
    sys.exit(main())
