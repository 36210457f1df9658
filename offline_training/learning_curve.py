"""Test-fold learning curves of one backbone's base and StARS variants on the outer CV folds.

    python -m offline_training.learning_curve --config config/learning_curve_socnav1.yaml \
        --jobs 1 --out results/learning_curve_socnav1 [--executor ray]

Answers "would more epochs, or another learning rate, close the gap to the published
figures?" without choosing anything on the test folds: every fit runs the full
``joint_epochs`` and reports its test metrics every ``every`` epochs. A point at epoch T2
is exactly the fit with (T1, T2) — the same seeds give the same first T2 epochs — so the
curves line up with the evaluation tables. Writes ``command.txt``, ``config.yaml``,
``machine.json``, ``records.jsonl`` (each fit as it finishes), ``curve.csv``,
``results.json``, ``results.md`` and ``curve_<metric>.png``. A fit that fails (raises, or
its worker dies) is named on stderr; the others go on, and the run ends with status 1
without curves.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import Field, PrivateAttr, ValidationInfo, model_validator

from stars_ros.model.config import Int, KeyedError, Section, TrainConfig, read_yaml, validate_under, validated
from stars_ros.errors import ConfigError, StarsError
from stars_ros.evaluation.executors import FitFailure, FitTask, run_fits
from stars_ros.evaluation.folds import make_folds
from stars_ros.evaluation.protocol import ProtocolConfig
from stars_ros.evaluation.specs import DISPLAY
from stars_ros.evaluation.stats import mean_sd
from stars_ros.evaluation.plots import label_axis, mean_band, pyplot, save_png
from stars_ros.evaluation.provenance import program_argv, run_record, write_run_files
from stars_ros.evaluation.report import METRIC_NAMES, write_csv

from .common import DEFAULT_SOCNAV1, add_executor_options, build_executor, read_inputs, setup_logging

REPO = Path(__file__).resolve().parents[1]
CURVE_COLUMNS = ('setting', 'variant', 'fold', 'epoch', 'mse', 'rmse', 'pearson_r', 'ccc', 'n')


class CurveConfig(Section):
    """A learning-curve run (``config/learning_curve_*.yaml``); every key is required.

    ``protocol`` is a protocol file relative to this one, whose outer row folds, seeds and
    model sizes the curves use; ``backbone`` one of its backbones; ``settings`` maps a name
    to training settings replacing the protocol's.
    """

    protocol: str
    backbone: str
    variants: Annotated[tuple[Literal['base', 'stars'], ...], Field(min_length=1)]
    pretrain_epochs: Annotated[Int, Field(ge=0)]
    joint_epochs: Annotated[Int, Field(ge=1)]
    every: Annotated[Int, Field(ge=1)]
    settings: Annotated[dict[str, dict[str, Any]], Field(min_length=1)]
    _protocol: ProtocolConfig | None = PrivateAttr(None)

    @model_validator(mode='after')
    def _consistent(self, info: ValidationInfo) -> 'CurveConfig':
        if self.every > self.joint_epochs:
            raise KeyedError(('every',), f'must not exceed joint_epochs ({self.joint_epochs}), got {self.every}')
        try:
            protocol = ProtocolConfig.from_yaml(Path((info.context or {}).get('folder', '.')) / self.protocol)
        except ConfigError as error:
            raise KeyedError(('protocol',), error) from None
        if self.backbone not in protocol.backbones:
            raise KeyedError(('backbone',), f'{self.backbone!r} is not among the backbones of {self.protocol}: '
                                            f'{list(protocol.backbones)}')
        for name, training in self.settings.items():
            for variant in self.variants:
                base = protocol.experiment_config(self.backbone, variant).training.model_dump()
                validate_under(('settings', name), TrainConfig, {**base, **training})
        self._protocol = protocol
        return self

    @property
    def protocol_config(self) -> ProtocolConfig:
        return self._protocol

    def to_dict(self) -> dict:
        return self.model_dump(mode='json')


def read_config(path: Path) -> CurveConfig:
    """The learning-curve config in ``path``, its protocol file read and checked too."""
    return validated(CurveConfig, read_yaml(path), path, folder=Path(path).parent)


def build_tasks(data, config: CurveConfig) -> list[tuple[str, str, FitTask]]:
    """(setting, variant, task) for every setting × variant × outer fold."""
    protocol = config.protocol_config
    tasks = []
    for setting, training in config.settings.items():
        for variant in config.variants:
            experiment = protocol.experiment_config(config.backbone, variant).replace(
                training={**training, 'pretrain_epochs': config.pretrain_epochs,
                          'joint_epochs': config.joint_epochs, 'threads': 1})
            for seed in protocol.seeds:
                for f, fold in enumerate(make_folds(data, 'rows', protocol.folds, seed)):
                    tasks.append((setting, variant, FitTask(f'{setting} {variant}', f'{seed}:{f}', 'curve',
                                                            experiment.to_dict(), fold.train, fold.test,
                                                            curve_at=tuple(range(config.every, config.joint_epochs + 1,
                                                                                 config.every)))))
    return tasks


def summarise(points: list) -> dict:
    """(setting, variant) -> epoch -> metric -> (mean, sd) over folds."""
    summary = {}
    for point in points:
        series = summary.setdefault((point['setting'], point['variant']), {})
        series.setdefault(point['epoch'], []).append(point)
    return {key: {epoch: {m: mean_sd([p[m] for p in entries]) for m in METRIC_NAMES}
                  for epoch, entries in sorted(series.items())} for key, series in summary.items()}


def write_markdown(path: Path, summary: dict, config: CurveConfig, header: dict) -> None:
    name = DISPLAY.get(config.backbone, config.backbone)
    keys = list(summary)
    lines = [f"# Learning curves: {name} on the outer row folds of {config.protocol}", '',
             f"Command: `{header['command']}`", '',
             f"Git: {header['git']}; machine: {header['machine']}; wall {header['wall_seconds']:.0f} s.", '',
             f"T1 = {config.pretrain_epochs} pre-training epochs, then test metrics (rating scale, macro over "
             f"actions, mean ± sd over folds) every {config.every} joint epochs. Settings: "
             + '; '.join(f'**{s}** {t}' for s, t in config.settings.items()) + '.', '',
             '## MSE by joint epoch (T2)', '',
             '| T2 | ' + ' | '.join(f'{s} {v}' for s, v in keys) + ' |',
             '| --- |' + ' --- |' * len(keys)]
    epochs = sorted({e for series in summary.values() for e in series})
    for epoch in epochs:
        cells = []
        for key in keys:
            stat = summary[key].get(epoch, {}).get('mse')
            cells.append('—' if stat is None else f'{stat[0]:.4f} ± {stat[1]:.4f}')
        lines.append(f'| {epoch} | ' + ' | '.join(cells) + ' |')
    lines += ['', '## Best epoch of each curve (watched on the test folds: not a fair selection)', '',
              '| setting | variant | best T2 | MSE | r | CCC |', '| --- | --- | --- | --- | --- | --- |']
    for (setting, variant), series in summary.items():
        best = min(series, key=lambda e: series[e]['mse'][0])
        stats = series[best]
        lines.append(f"| {setting} | {variant} | {best} | {stats['mse'][0]:.4f} | {stats['pearson_r'][0]:.3f} | "
                     f"{stats['ccc'][0]:.3f} |")
    path.write_text('\n'.join(lines) + '\n')


def plot(folder: Path, summary: dict) -> list[str]:
    plt = pyplot()
    written = []
    for metric in ('mse', 'pearson_r', 'ccc'):
        figure, axis = plt.subplots(figsize=(6, 4))
        for (setting, variant), series in summary.items():
            epochs = list(series)
            means = np.array([series[e][metric][0] for e in epochs])
            sds = np.array([series[e][metric][1] for e in epochs])
            mean_band(axis, epochs, means, sds, f'{setting} {variant}', marker='.', alpha=0.15)
        label_axis(axis, 'joint epochs (T2)', METRIC_NAMES[metric], legend_size=8)
        written.append(save_png(figure, folder / f'curve_{metric}.png'))
    return written


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--config', default=str(REPO / 'config' / 'learning_curve_socnav1.yaml'))
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--out', required=True, help='results folder')
    parser.add_argument('--verbose', action='store_true')
    add_executor_options(parser)
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    inputs = read_inputs(lambda: read_config(Path(args.config)), args.data_root)
    if inputs is None:
        return 2
    config, data = inputs
    tasks = build_tasks(data, config)
    try:
        fits = build_executor(args, data, devices=[task.experiment['training']['device'] for _, _, task in tasks])
    except StarsError as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    folder = Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    header = run_record(program_argv('offline_training.learning_curve', argv))
    (folder / 'config.yaml').write_text(yaml.safe_dump(
        {**config.to_dict(), 'protocol_resolved': config.protocol_config.to_dict(),
         'data_fingerprint': data.fingerprint},
        sort_keys=False))
    write_run_files(folder, header)
    print(f'{len(tasks)} fits of {config.joint_epochs} joint epochs; {fits.jobs} job(s) ({fits.settings["kind"]}); '
          f'writing {folder}', flush=True)
    started = time.perf_counter()
    points, curves, failed = [], [], []
    waiting = [(task, setting, variant) for setting, variant, task in tasks]
    with (folder / 'records.jsonl').open('w') as stream:  # each fit kept as it finishes
        for done, ((task, setting, variant), scores) in enumerate(
                run_fits(fits.executor, waiting, fits.jobs), 1):
            if isinstance(scores, FitFailure):
                failed.append(f'{task.name}: {scores.error}')
                continue
            if 'error' in scores:
                print(f'{task.model} fold {task.fold}: {scores["error"]}', file=sys.stderr)
                continue
            fit = {'setting': setting, 'variant': variant, 'fold': task.fold,
                   'fit_seconds': scores['fit_seconds'], 'curve': scores['curve']}
            curves.append(fit)
            points += [{'setting': setting, 'variant': variant, 'fold': task.fold, **p} for p in scores['curve']]
            stream.write(json.dumps(fit) + '\n')
            stream.flush()
            last = scores['curve'][-1]
            print(f"[{done}/{len(tasks)}] {task.model} fold {task.fold}: MSE at T2 = {last['epoch']} "
                  f"{last['mse']:.4f} ({scores['fit_seconds']:.0f} s)", flush=True)
    header['wall_seconds'] = time.perf_counter() - started
    if failed:
        print('\n'.join([f'error: {len(failed)} fit(s) failed:', *(f'  {line}' for line in failed),
                         'No curves: their means would mix folds; the completed fits are in records.jsonl.']),
              file=sys.stderr)
        return 1
    summary = summarise(points)
    write_csv(folder / 'curve.csv', points, CURVE_COLUMNS)
    write_markdown(folder / 'results.md', summary, config, header)
    plots = plot(folder, summary)
    (folder / 'results.json').write_text(json.dumps(
        {**header, 'config': config.to_dict(), 'fits': curves,
         'summary': {f'{s} {v}': series for (s, v), series in summary.items()}, 'plots': plots}, indent=1))
    print((folder / 'results.md').read_text())
    return 0


if __name__ == '__main__':
    sys.exit(main())
