"""The evaluation protocol: outer cross-validation, nested selection of settings, sparsity sweep.

For every outer fold and model, a ``inner_folds``-fold cross-validation inside the
outer-train pool picks the candidate with the lowest validation RMSE on normalised scores
(z-scores under the training split's per-action mean and standard deviation, so actions
weigh the same). A candidate is a combination of the model family's ``search`` space (e.g.
learning rate, weight decay, embedding penalty, dim) and an epoch pair (T1, T2) of ``grid``;
pairs sharing T1 are scored in one inner fit, at each T2 along the way (the same seeds give
the same first epochs, so a point at T2 is the fit with T2 epochs). The model is then
retrained on the whole pool with the chosen candidate and scored on the outer test rows.
Nothing is chosen on rows that are test rows of the outer fold. The sparsity sweep retrains
with the chosen candidate on nested random subsets (``fractions`` of the pool, without
replacement) and scores them on the same outer test rows; fraction 1.0 is the main result.

Folds are dealt by ``folds`` (rows, cold-scene or cold-user); inner folds are grouped the
same way, so the selection sees the situation it is selecting for. The model needs no
special case: unseen scenes and users get zero embeddings and offsets.

Every model of a table (``specs``: the backbones' variants, the baselines, StARS's
ablations) is scored on the same folds. The fits run through ``executors``, at most
``jobs`` at a time.

A fit that raises, or whose worker dies, is a *failure*: reported by name, never recorded,
so a resumed run tries it again; the other fits go on. A selection that lost an inner fit
cannot choose, so that fold's final fits are not run. A fit that diverges is a result
instead (NaN scores with an ``error``), recorded like any other.
"""
from __future__ import annotations

import concurrent.futures as futures
import itertools
import json
import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Annotated, Any, Callable, Literal, Sequence

import numpy as np
from pydantic import Field, field_validator, model_validator

from stars_ros.data.ratings import RatingData
from stars_ros.errors import ConfigError
from stars_ros.evaluation import peers
from stars_ros.evaluation.executors import METRICS, FitFailure, FitTask, fit_executor, run_fits
from stars_ros.evaluation.folds import DEALS, PROTOCOLS, make_folds, sweep_samples
from stars_ros.evaluation.specs import (ABLATIONS, BASELINES, PEER_FAMILIES, ModelSpec, candidates,
                                       model_specs, settings_candidates, settings_key)
from stars_ros.model.config import (EncoderConfig, ExperimentConfig, Float, Int, KeyedError, ModelConfig, Section,
                                    TrainConfig, read_yaml, validate_under, validated)
from stars_ros.model.metrics import regression_report

log = logging.getLogger(__name__)



# -- configuration ----------------------------------------------------------------------
def _merge(base: dict, changes: dict) -> dict:
    """``base`` with ``changes`` merged in; nested mappings merge, anything else replaces."""
    merged = dict(base)
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = _merge(merged[key], value)
        else:
            merged[key] = value
    return merged


#: Settings a protocol's ``search`` may vary, and the config section each belongs to.
SEARCHABLE = {'lr': 'training', 'weight_decay': 'training', 'embedding_l2': 'training',
              'posterior_sweeps': 'training', 'posterior_burn_in': 'training', 'dim': 'model',
              'strangers': 'model'}
#: Model families with a search space of their own; ablations follow StARS's choice.
FAMILIES = ('base', 'stars', 'mf')


class ProtocolConfig(Section):
    """What one evaluation run trains and how (read from ``config/eval_*.yaml``).

    Args:
        name (str): run name, the default results folder.
        folds (int): outer folds k (the t-test has k·len(seeds) − 1 degrees of freedom).
        inner_folds (int): folds of the selection inside each outer-train pool.
        seeds (tuple of int): fold-assignment seeds; more than one repeats the whole CV.
        deal (str): how outer and inner folds deal their groups (``folds.grouped_folds``):
            'largest_first' (sizes balanced; SocNav1's cold-user folds then do not change
            with the seed) or 'shuffled' (new folds for each seed).
        grid (tuple of (T1, T2)): candidate epoch pairs (T2 >= 1).
        search (dict): family (``base``, ``stars``, ``mf``) -> {setting: [values]}, a product
            of candidate values of SEARCHABLE settings; a family without one uses ``experiment``'s.
            A peer (``surprise_svd``, ``myfm``) searches its own settings (``peers.SETTINGS``).
        fractions (tuple of float): training fractions of the sparsity sweep.
        backbones (dict): encoder name -> encoder settings that differ from ``experiment``,
            and under ``training`` the training settings that do (a backbone's packaged ones).
        variants (tuple of str): ``base`` and/or ``stars``, trained for every backbone.
        baselines (tuple of str): ``population_mean``, ``mf`` and the peer libraries
            (``peers``): ``surprise_svd``, ``myfm``, and ``myfm_encoder`` (one per backbone,
            on the h_i of the base model that backbone chose in each fold).
        ablations (tuple of str): keys of ABLATIONS, run for ``ablation_backbones``.
        ablation_backbones (tuple of str): backbones that get the ablations.
        sweep_backbones (tuple of str): backbones that get the sparsity sweep (with the
            baselines); empty for none.
        error (str): error column of the tables: ``mse`` ([0, 1] scales) or ``rmse``.
        experiment (dict): ExperimentConfig mapping shared by every model (sizes, lr, ...).
    """

    name: str = 'socnav1'
    folds: Annotated[Int, Field(ge=2)] = 5
    inner_folds: Annotated[Int, Field(ge=2)] = 2
    seeds: Annotated[tuple[Annotated[Int, Field(ge=0)], ...], Field(min_length=1)] = (0,)
    deal: Literal[DEALS] = 'largest_first'
    grid: Annotated[tuple[tuple[Int, Int], ...], Field(min_length=1)] = ((10, 100), (50, 100), (100, 100))
    search: dict[Literal[FAMILIES + PEER_FAMILIES], dict[str, Annotated[list, Field(min_length=1)]]] = \
        Field(default_factory=dict)
    fractions: tuple[Annotated[Float, Field(gt=0.0, le=1.0)], ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
    backbones: dict[str, dict[str, Any] | None] = Field(default_factory=lambda: {'gat': {}})
    variants: tuple[Literal['base', 'stars'], ...] = ('base', 'stars')
    baselines: tuple[Literal[BASELINES], ...] = BASELINES
    ablations: tuple[Literal[tuple(ABLATIONS)], ...] = ()
    ablation_backbones: tuple[str, ...] = ()
    sweep_backbones: tuple[str, ...] = ()
    error: Literal['mse', 'rmse'] = 'mse'
    experiment: dict[str, Any] = Field(default_factory=dict)

    @field_validator('grid')
    @classmethod
    def _epoch_pairs(cls, grid: tuple) -> tuple:
        for index, (t1, t2) in enumerate(grid):
            if t1 < 0 or t2 < 1:
                raise KeyedError((index,), f'need T1 >= 0 and T2 >= 1, got [{t1}, {t2}]')
        return grid

    @model_validator(mode='after')
    def _consistent(self) -> 'ProtocolConfig':
        """Cross-key checks, then every model the protocol trains is a valid experiment."""
        if not self.variants and self.backbones:
            raise KeyedError(('variants',), "must not be empty while there are backbones; give 'base' and/or 'stars'")
        if not (self.backbones or self.baselines):
            raise ValueError('there must be a backbone or a baseline')
        for name in ('sweep_backbones', 'ablation_backbones'):
            for index, backbone in enumerate(getattr(self, name)):
                if backbone not in self.backbones:
                    raise KeyedError((name, index), f'{backbone!r} is not among backbones {list(self.backbones)}')
        if self.ablation_backbones and 'stars' not in self.variants:
            raise KeyedError(('ablation_backbones',), 'ablations follow the StARS variant: variants must include stars')
        if 'myfm_encoder' in self.baselines and not (self.backbones and 'base' in self.variants):
            raise KeyedError(('baselines',), 'myfm_encoder takes the h_i of each backbone\'s base model: it needs '
                                             'backbones and the base variant')
        if 'mf' in self.baselines and not self.backbones and 'name' not in (self.experiment.get('encoder') or {}):
            raise KeyedError(('baselines',), 'the mf baseline needs a backbone or experiment.encoder.name matching '
                                             'the data')
        experiment = validate_under(('experiment',), ExperimentConfig, self.experiment)
        for backbone, settings in self.backbones.items():
            encoder = {key: value for key, value in (settings or {}).items() if key != 'training'}
            validate_under(('backbones', backbone), EncoderConfig,
                           _merge(experiment.encoder.model_dump(), {**encoder, 'name': backbone}))
            validate_under(('backbones', backbone, 'training'), TrainConfig,
                           _merge(experiment.training.model_dump(), (settings or {}).get('training') or {}))
        sections = {'training': TrainConfig, 'model': ModelConfig}
        for family, space in self.search.items():
            if family in PEER_FAMILIES:
                for values in itertools.product(*space.values()):
                    validate_under(('search', family), peers.SETTINGS[family], dict(zip(space, values)))
                continue
            for key, values in space.items():
                if key not in SEARCHABLE:
                    raise KeyedError(('search', family, key), f'not an allowed key; choices: {list(SEARCHABLE)}')
                section = SEARCHABLE[key]
                for value in values:
                    validate_under(('search', family), sections[section],
                                   {**getattr(experiment, section).model_dump(), key: value})
        try:  # anything left that only a whole model shows
            for spec in model_specs(self):
                if spec.variant not in ('population_mean', *peers.PEERS):
                    for settings in settings_candidates(self, spec):
                        self.experiment_config(spec.backbone, spec.variant, {**settings, **spec.model})
        except ConfigError as error:
            raise ValueError(str(error)) from None
        return self

    def experiment_config(self, backbone: str | None, variant: str, settings: dict | None = None) -> ExperimentConfig:
        """The ExperimentConfig of one model (``backbone`` None: the experiment's encoder);
        ``settings`` (SEARCHABLE names, or ``item_key``) override the experiment's."""
        values = _merge(self.experiment, {'model': {'variant': variant}})
        if backbone is not None:
            encoder = dict(self.backbones[backbone] or {})
            training = encoder.pop('training', None) or {}
            values = _merge(values, {'encoder': {**encoder, 'name': backbone}, 'training': training})
        for key, value in (settings or {}).items():
            values = _merge(values, {SEARCHABLE.get(key, 'model'): {key: value}})
        return ExperimentConfig.from_dict(values)

    def to_dict(self) -> dict:
        values = self.model_dump()
        for name in ('seeds', 'variants', 'baselines', 'ablations', 'ablation_backbones', 'sweep_backbones',
                     'fractions'):
            values[name] = list(values[name])
        values['grid'] = [list(pair) for pair in self.grid]
        return values

    @classmethod
    def from_dict(cls, values: dict, overrides: dict | None = None, source=None) -> 'ProtocolConfig':
        """Validate ``values`` with ``overrides`` merged in; ``source`` (e.g. the file) heads
        every error message."""
        if not isinstance(values, dict):
            raise ConfigError(f'{source or "protocol config"}: must be a mapping, got {type(values).__name__}')
        return validated(cls, _merge(values, overrides or {}), source)

    @classmethod
    def from_yaml(cls, path, overrides_path=None) -> 'ProtocolConfig':
        """Read ``path``; a second YAML ``overrides_path`` (e.g. the quick setting) merges in."""
        if overrides_path is None:
            return cls.from_dict(read_yaml(path), source=path)
        return cls.from_dict(read_yaml(path), read_yaml(overrides_path), source=f'{path} (with {overrides_path})')


# -- the protocol -----------------------------------------------------------------------
@dataclass
class EvaluationResult:
    """Everything a run measured: ``records`` one entry per (model, fold, fraction);
    ``inner`` one per selection fit; ``selection`` one per (candidate, fold, inner fold);
    ``choices`` the candidate each model took in each fold."""

    protocol: str
    config: ProtocolConfig
    records: list = field(default_factory=list)
    inner: list = field(default_factory=list)
    selection: list = field(default_factory=list)
    choices: list = field(default_factory=list)
    folds: list = field(default_factory=list)     # per outer fold: id, n_train, n_test
    wall_seconds: float = 0.0
    jobs: int = 1
    threads: int = 1
    resumed: int = 0  # fits taken from an earlier run's records, not run again
    failed: list = field(default_factory=list)    # per fit that raised or whose worker died: what, and the error
    unchosen: list = field(default_factory=list)  # per (model, fold) whose selection lost an inner fit

    def final(self) -> list:
        return [r for r in self.records if r['fraction'] == 1.0]


def _fit_key(model, fold, stage, fraction, inner_fold, t1, t2, settings) -> tuple:
    return (model, fold, stage, float(fraction), int(inner_fold), int(t1), int(t2), settings)


def population_mean(data: RatingData, train: np.ndarray, test: np.ndarray) -> dict:
    """Scores of the constant predictor: each action's training mean."""
    started = time.perf_counter()
    means = {a: data.scores[train][data.actions[train] == a].mean() for a in np.unique(data.actions[train])}
    fallback = data.scores[train].mean()
    predictions = np.array([means.get(a, fallback) for a in data.actions[test]])
    # Pearson r of a constant is undefined; rounding in the mean can make it look computable.
    return {**regression_report(data.scores[test], predictions, data.actions[test]), 'pearson_r': math.nan,
            'fit_seconds': time.perf_counter() - started, 'predict_seconds': 0.0, 'epochs': 0}


class ProtocolRun:
    """One run of the protocol on ``data`` (see ``run_protocol``): the folds, the queue of
    fits (at most ``jobs`` in flight, fits unlocked by a finished selection ahead of further
    selection fits, so complete results appear early) and what came back."""

    def __init__(self, data: RatingData, config: ProtocolConfig, protocol: str = 'rows', jobs: int = 1,
                 threads: int = 1, on_record: Callable[[dict], None] | None = None, resume: Sequence[dict] = (),
                 executor: futures.Executor | None = None, fitted_by: dict | None = None):
        if protocol not in PROTOCOLS:
            raise ValueError(f"Could not resolve protocol '{protocol}' among choices {list(PROTOCOLS)}")
        if jobs < 1 or threads < 1:
            raise ValueError('jobs and threads must be positive')
        peers.require(config.baselines)  # before any fit
        self.data, self.config, self.protocol = data, config, protocol
        self.jobs, self.threads, self.on_record = jobs, threads, on_record
        self.executor = executor
        self.fitted_by = fitted_by  # who ran this process's fits (commit, dirty, device), kept per record
        self.result = EvaluationResult(protocol, config, jobs=jobs, threads=threads)
        self.specs = model_specs(config)
        self.followers = {}  # label -> the specs that take its choice
        for spec in self.specs:
            if spec.follows:
                self.followers.setdefault(spec.follows, []).append(spec)
        self.holdout_of = {spec.follows: spec for spec in self.specs if spec.from_holdout}
        self.swept = {s.label for s in self.specs if (s.backbone in config.sweep_backbones and not s.follows)
                      or (s.backbone is None and config.sweep_backbones)}
        self.fractions = sorted(set(config.fractions) | {1.0})
        self.outer = self._outer_folds()
        self.earlier = _resumed_fits(resume)
        self.inner_scores = {}  # (label, fold id) -> {(settings key, (T1, T2)): [z-RMSE per inner fold]}
        self.waiting = []
        self.total = 0

    def run(self) -> EvaluationResult:
        started = time.perf_counter()
        self._score_population_means()
        self._queue_selections()
        self.total = len(self.waiting)
        fits = run_fits(self.executor or fit_executor(self.data, self.jobs, self.threads), self.waiting, self.jobs,
                        self._cached if self.earlier else None)
        for done, ((fit, spec, settings, pair), scores) in enumerate(fits, 1):
            if isinstance(scores, FitFailure):
                self.result.failed.append({'fit': fit.name, 'model': spec.label, 'fold': fit.fold, 'stage': fit.stage,
                                           'fraction': fit.fraction, 'inner_fold': fit.inner_fold,
                                           'settings': settings, 'T1': pair[0], 'T2': pair[1],
                                           'error': scores.error})
            elif fit.stage != 'inner':
                self._record(spec, fit.fold, fit.fraction, settings, pair, len(fit.train), len(fit.test), scores,
                             fit.stage)
                if fit.holdout and 'holdout' in scores:  # this fit's hold-out stage (specs.HOLDOUT_RECIPE)
                    held = scores['holdout']
                    self._record(self.holdout_of[spec.label], fit.fold, 1.0, settings, pair, held['n_train'],
                                 len(fit.test), {**scores, **held}, 'final')
                log.info('[%d/%d] %s fold %s fraction %g %s (T1, T2) = %s: %s %.4f (%.1f s)', done, self.total,
                         spec.label, fit.fold, fit.fraction, settings_key(settings), pair,
                         self.config.error.upper(), scores[self.config.error], scores['fit_seconds'])
            else:
                self._take_selection_fit(done, fit, spec, settings, pair, scores)
        self.result.unchosen = [{'model': label, 'fold': fold_id} for (label, fold_id), table
                                in self.inner_scores.items()
                                if any(len(v) < self.config.inner_folds for v in table.values())]
        self.result.wall_seconds = time.perf_counter() - started
        return self.result

    def _outer_folds(self) -> dict:
        """fold id 'seed:k' -> (outer fold, inner folds of its pool, sweep samples of its pool)."""
        config, data = self.config, self.data
        outer = {}
        for seed in config.seeds:
            for f, fold in enumerate(make_folds(data, self.protocol, config.folds, seed, deal=config.deal)):
                fold_id = f'{seed}:{f}'
                outer[fold_id] = (fold, make_folds(data, self.protocol, config.inner_folds, [seed, f, 1], fold.train,
                                                   config.deal),
                                  sweep_samples(fold.train, self.fractions, [seed, f, 2], data.examples))
                self.result.folds.append({'fold': fold_id, 'n_train': len(fold.train), 'n_test': len(fold.test)})
        return outer

    def _record(self, spec, fold_id, fraction, settings, pair, n_train, n_test, scores, stage):
        entry = {'protocol': self.protocol, 'model': spec.label, 'backbone': spec.backbone, 'variant': spec.variant,
                 'fold': fold_id, 'fraction': fraction, 'stage': stage, 'settings': settings,
                 'T1': pair[0], 'T2': pair[1], 'n_train': n_train, 'n_test': n_test,
                 **{k: scores[k] for k in (*METRICS, 'fit_seconds', 'predict_seconds', 'epochs')}}
        self._stamp(entry, scores)
        if 'error' in scores:
            entry['error'] = scores['error']
            log.warning('%s fold %s fraction %g: %s', spec.label, fold_id, fraction, scores['error'])
        self.result.records.append(entry)
        if self.on_record:
            self.on_record(entry)

    def _stamp(self, entry: dict, scores: dict) -> None:
        """``fitted_by``: the run whose process made the fit, so a resumed run's records say
        which fits an earlier process made (None: an earlier record that did not say)."""
        if 'fitted_by' in scores or self.fitted_by is not None:
            entry['fitted_by'] = scores.get('fitted_by', self.fitted_by)

    def _score_population_means(self):
        """The constant baseline, computed here: it takes no time."""
        for spec in self.specs:
            if spec.variant == 'population_mean':
                for fold_id, (fold, _, samples) in self.outer.items():
                    for fraction in (self.fractions if spec.label in self.swept else [1.0]):
                        train = samples[fraction]
                        self._record(spec, fold_id, fraction, {}, (0, 0), len(train), len(fold.test),
                                     population_mean(self.data, train, fold.test),
                                     'final' if fraction == 1.0 else 'sweep')

    def _queue_selections(self):
        """The inner fits of every model with its own search, one per start T1 (scored at
        every T2 of the grid); a model with a single candidate takes it at once."""
        for spec in self.specs:
            if spec.variant == 'population_mean' or spec.follows:
                continue
            options = candidates(self.config, spec)
            for fold_id, (_, inner, _) in self.outer.items():
                if len(options) == 1:
                    self.waiting.extend(self._choose(spec, fold_id, *options[0], math.nan))
                    continue
                self.inner_scores[spec.label, fold_id] = {(settings_key(s), p): [] for s, p in options}
                by_start = {}
                for settings, (t1, t2) in options:
                    by_start.setdefault((settings_key(settings), t1), (settings, []))[1].append(t2)
                for (_, t1), (settings, ends) in by_start.items():
                    pair = (t1, max(ends))
                    for i, (train, validation) in enumerate(inner):
                        self.waiting.append((self._task(spec, fold_id, 'inner', settings, pair, train, validation,
                                                        inner_fold=i, curve_at=tuple(sorted(ends))),
                                             spec, settings, pair))

    def _take_selection_fit(self, done, fit, spec, settings, pair, scores):
        """Record an inner fit and its points; once the fold's selection is complete, choose
        and put the final fits it unlocks at the front of the queue."""
        entry = {'stage': 'inner', 'model': spec.label, 'variant': spec.variant, 'fold': fit.fold,
                 'settings': settings, 'T1': pair[0], 'T2': pair[1], 'inner_fold': fit.inner_fold,
                 'z_rmse': scores['z_rmse'], 'curve': [{'epoch': c['epoch'], 'z_rmse': c['z_rmse']}
                                                      for c in scores['curve']],
                 'n_train': len(fit.train), 'n_test': len(fit.test), 'fit_seconds': scores['fit_seconds'],
                 'predict_seconds': scores['predict_seconds'], 'epochs': scores['epochs']}
        self._stamp(entry, scores)
        self.result.inner.append(entry)
        if self.on_record:
            self.on_record(entry)
        table = self.inner_scores[spec.label, fit.fold]
        reached = {c['epoch']: c['z_rmse'] for c in entry['curve']}
        for t2 in fit.curve_at:  # a diverged fit has no curve: every point it owed is lost
            z_rmse = reached.get(t2, math.inf)
            table[settings_key(settings), (pair[0], t2)].append(z_rmse)
            self.result.selection.append({'model': spec.label, 'fold': fit.fold, 'settings': settings_key(settings),
                                          'T1': pair[0], 'T2': t2, 'inner_fold': fit.inner_fold, 'z_rmse': z_rmse,
                                          'n_train': len(fit.train), 'n_test': len(fit.test)})
        log.info('[%d/%d] %s fold %s inner %d %s T1 %d: z-RMSE %s', done, self.total, spec.label, fit.fold,
                 fit.inner_fold, settings_key(settings), pair[0], {t: round(v, 4) for t, v in reached.items()})
        if all(len(v) == self.config.inner_folds for v in table.values()):
            means = {candidate: float(np.mean(v)) for candidate, v in table.items()}
            best = min(means, key=means.get)  # ties: first candidate
            log.info('%s fold %s: chose %s (T1, T2) = %s by inner z-RMSE %.4f', spec.label, fit.fold, best[0],
                     best[1], means[best])
            unlocked = self._choose(spec, fit.fold, json.loads(best[0]), best[1], means[best])
            self.waiting[:0] = unlocked
            self.total += len(unlocked)

    def _choose(self, spec, fold_id, settings, pair, z_rmse) -> list:
        """Note the choice of ``spec`` (and of those that follow it) in ``fold_id``; the final
        fits (and sweep) it unlocks."""
        self.result.choices.append({'model': spec.label, 'fold': fold_id, 'settings': settings, 'T1': pair[0],
                                    'T2': pair[1], 'inner_z_rmse': z_rmse})
        self.result.choices.extend({**self.result.choices[-1], 'model': follower.label, 'follows': spec.label}
                                   for follower in self.followers.get(spec.label, []))
        fold, _, samples = self.outer[fold_id]
        items = []
        for chosen_by in [spec, *self.followers.get(spec.label, [])]:
            if chosen_by.from_holdout:  # scored by the fit of the spec it follows
                continue
            chosen = self.fractions if chosen_by.label in self.swept else [1.0]
            holdout = chosen_by.label in self.holdout_of  # its final fit also scores the hold-out row
            items += [(self._task(chosen_by, fold_id, 'final' if f == 1.0 else 'sweep', settings, pair, samples[f],
                                  fold.test, fraction=f, holdout=holdout and f == 1.0),
                       chosen_by, settings, pair) for f in chosen]
        return items

    def _task(self, spec, fold_id, stage, settings, pair, train, test, **extra) -> FitTask:
        if spec.variant in PEER_FAMILIES:  # a content-free library: the experiment only carries the seed
            seed = (self.config.experiment.get('training') or {}).get('seed', 0)
            experiment = {'training': {'pretrain_epochs': 0, 'joint_epochs': 0, 'seed': seed}}
            return FitTask(spec.label, fold_id, stage, experiment, train, test, settings=settings_key(settings),
                           peer=spec.variant, peer_settings=settings_key(settings), **extra)
        if spec.variant == 'myfm_encoder':  # base's encoder (with base's choice), then myFM's defaults
            return replace(self._task(ModelSpec(spec.label, spec.backbone, 'base'), fold_id, stage, settings, pair,
                                      train, test, **extra), peer='myfm_encoder')
        base = self.config.experiment_config(spec.backbone, spec.variant, {**settings, **spec.model})
        experiment = base.replace(training={'pretrain_epochs': pair[0], 'joint_epochs': pair[1],
                                            'threads': self.threads}).to_dict()
        return FitTask(spec.label, fold_id, stage, experiment, train, test, settings=settings_key(settings), **extra)

    def _cached(self, task: FitTask) -> dict | None:
        """The scores an earlier run recorded for ``task``, if it did."""
        training = task.experiment['training']
        keys = (task.fold, task.stage, task.fraction, task.inner_fold, training['pretrain_epochs'],
                training['joint_epochs'], task.settings)
        found = self.earlier.get(_fit_key(task.model, *keys))
        if found is not None and task.holdout:  # its hold-out row came from the same fit, else it runs again
            held = self.earlier.get(_fit_key(self.holdout_of[task.model].label, *keys))
            found = None if held is None else {**found, 'holdout': held}
        self.result.resumed += found is not None
        return found


def _resumed_fits(resume: Sequence[dict]) -> dict:
    """An earlier run's entries by the fit that gave them (the population mean is computed again)."""
    earlier = {}
    for entry in resume:
        if entry.get('variant') == 'population_mean':
            continue
        entry = {'fitted_by': None, **entry}  # not this process's fit
        if entry['stage'] == 'inner' and 'curve' not in entry:  # written before curves: one point, at T2
            entry = {**entry, 'curve': [{'epoch': entry['T2'], 'z_rmse': entry['z_rmse']}]}
        earlier[_fit_key(entry['model'], entry['fold'], entry['stage'], entry.get('fraction', 1.0),
                         entry.get('inner_fold', -1), entry['T1'], entry['T2'],
                         settings_key(entry.get('settings', {})))] = entry
    return earlier


def run_protocol(data: RatingData, config: ProtocolConfig, protocol: str = 'rows', jobs: int = 1,
                 threads: int = 1, on_record: Callable[[dict], None] | None = None,
                 resume: Sequence[dict] = (), executor: futures.Executor | None = None,
                 fitted_by: dict | None = None) -> EvaluationResult:
    """Run the whole protocol on ``data``; ``on_record`` sees each entry as it arrives: the
    records, and the selection fits with ``stage`` 'inner'. ``resume`` takes such entries of
    an earlier run of the same config: their fits are not run again. Fits are seeded, so on
    the CPU a resumed run gives the results of an uninterrupted one. ``executor`` runs the
    fits, at most ``jobs`` at a time (default: ``fit_executor(data, jobs, threads)``); the
    run shuts it down. ``fitted_by`` (e.g. the commit, dirty flag and device) goes into each
    entry of a fit this call makes; a resumed entry keeps its own. Failed fits and the
    selections they stopped are in ``failed`` and ``unchosen`` of the result."""
    return ProtocolRun(data, config, protocol, jobs, threads, on_record, resume, executor, fitted_by).run()
