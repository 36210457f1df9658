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

A row of the protocol is an *example*: one user's ratings of one scene, every action
(``RatingData.examples``). Three protocols differ only in how examples are grouped into
folds: ``rows`` (random examples, as published), ``cold-scene`` (grouped by scene, so no
test scene is seen in training) and ``cold-user`` (grouped by annotator). Inner folds are
grouped the same way, so the selection sees the situation it is selecting for; sweep samples
are drawn over whole examples, so an example's actions never straddle a split. The model
needs no special case: unseen scenes and users get zero embeddings and offsets.

Every model of a table is scored on the same folds: the chosen backbones in the ``base``
and ``stars`` variants, two baselines: ``population_mean`` (the training mean of each
action) and ``mf`` (biased matrix factorisation, no scene content), and for
``ablation_backbones`` the ``ablations`` of StARS, which take the full StARS model's choice
in each fold so that each differs from it in one part only. Fits are independent
jobs; with ``jobs > 1`` they run in worker processes (one torch thread each), which on a
CPU pays better than threads inside one small-graph model. With ``training.device`` 'cuda'
the workers share the one GPU, each with its own CUDA context. Any other
``concurrent.futures.Executor`` can run them instead (``stars_ros.evaluation.ray_executor``: Ray tasks).

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
import multiprocessing
import pickle
import time
from dataclasses import dataclass, field
from typing import Annotated, Any, Callable, Literal, NamedTuple, Sequence

import numpy as np
from pydantic import Field, field_validator, model_validator

from stars_ros.model.config import (EncoderConfig, ExperimentConfig, Float, Int, KeyedError, ModelConfig, Section, TrainConfig,
                     read_yaml, validate_under, validated)
from stars_ros.data.ratings import RatingData
from stars_ros.errors import ConfigError, TrainingDivergedError
from stars_ros.model.metrics import regression_report
from stars_ros.evaluation.stats import corrected_resampled_ttest, holm

log = logging.getLogger(__name__)

PROTOCOLS = ('rows', 'cold-scene', 'cold-user')
METRICS = ('mse', 'rmse', 'pearson_r', 'ccc')
BASELINES = ('population_mean', 'mf')
DISPLAY = {'gcn': 'GCN', 'gin': 'GIN', 'graphsage': 'GraphSAGE', 'ggnn': 'GGNN', 'rgcn': 'RGCN',
           'gat': 'GAT', 'mlp': 'MLP', 'resmlp': 'ResMLP', 'dcnv2': 'DCNv2', 'graceae': 'GraceAE',
           'fttransformer': 'FT-Transformer'}
BASELINE_LABELS = {'population_mean': 'Population mean', 'mf': 'MF (biased, no content)'}


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
SEARCHABLE = {'lr': 'training', 'weight_decay': 'training', 'embedding_l2': 'training', 'dim': 'model'}
#: Model families with a search space of their own; ablations follow StARS's choice.
FAMILIES = ('base', 'stars', 'mf')
#: StARS ablations: label suffix and the model settings that differ from full StARS.
ABLATIONS = {
    'user_bias': ('user offsets only', {'variant': 'user_bias'}),
    'base_user_bias': ('base + user offset', {'variant': 'base_user_bias'}),
    'stars_no_q': ('StARS without q_i', {'variant': 'stars_no_q'}),
    'stars_no_residual': ('StARS without the h_i residual', {'variant': 'stars_no_residual'}),
    'stars_prefix': ('StARS, items keyed by prefix', {'item_key': 'prefix'}),
}


class ProtocolConfig(Section):
    """What one evaluation run trains and how (read from ``config/eval_*.yaml``).

    Args:
        name (str): run name, the default results folder.
        folds (int): outer folds k (the t-test has k·len(seeds) − 1 degrees of freedom).
        inner_folds (int): folds of the selection inside each outer-train pool.
        seeds (tuple of int): fold-assignment seeds; more than one repeats the whole CV.
        grid (tuple of (T1, T2)): candidate epoch pairs (T2 >= 1).
        search (dict): family (``base``, ``stars``, ``mf``) -> {setting: [values]}, a product
            of candidate values of SEARCHABLE settings; a family without one uses ``experiment``'s.
        fractions (tuple of float): training fractions of the sparsity sweep.
        backbones (dict): encoder name -> encoder settings that differ from ``experiment``.
        variants (tuple of str): ``base`` and/or ``stars``, trained for every backbone.
        baselines (tuple of str): ``population_mean`` and/or ``mf``.
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
    grid: Annotated[tuple[tuple[Int, Int], ...], Field(min_length=1)] = ((10, 100), (50, 100), (100, 100))
    search: dict[Literal[FAMILIES], dict[Literal[tuple(SEARCHABLE)], Annotated[list, Field(min_length=1)]]] = \
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
        if 'mf' in self.baselines and not self.backbones and 'name' not in (self.experiment.get('encoder') or {}):
            raise KeyedError(('baselines',), 'the mf baseline needs a backbone or experiment.encoder.name matching '
                                             'the data')
        experiment = validate_under(('experiment',), ExperimentConfig, self.experiment)
        for backbone, settings in self.backbones.items():
            validate_under(('backbones', backbone), EncoderConfig,
                           _merge(experiment.encoder.model_dump(), {**(settings or {}), 'name': backbone}))
        sections = {'training': TrainConfig, 'model': ModelConfig}
        for family, space in self.search.items():
            for key, values in space.items():
                section = SEARCHABLE[key]
                for value in values:
                    validate_under(('search', family), sections[section],
                                   {**getattr(experiment, section).model_dump(), key: value})
        try:  # anything left that only a whole model shows
            for spec in model_specs(self):
                if spec.variant != 'population_mean':
                    for settings in _settings_candidates(self, spec):
                        self.experiment_config(spec.backbone, spec.variant, {**spec.model, **settings})
        except ConfigError as error:
            raise ValueError(str(error)) from None
        return self

    def experiment_config(self, backbone: str | None, variant: str, settings: dict | None = None) -> ExperimentConfig:
        """The ExperimentConfig of one model (``backbone`` None: the experiment's encoder);
        ``settings`` (SEARCHABLE names, or ``item_key``) override the experiment's."""
        values = _merge(self.experiment, {'model': {'variant': variant}})
        if backbone is not None:
            values = _merge(values, {'encoder': {**(self.backbones[backbone] or {}), 'name': backbone}})
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


# -- folds ------------------------------------------------------------------------------
class Fold(NamedTuple):
    train: np.ndarray
    test: np.ndarray


def grouped_folds(rows: np.ndarray, groups: np.ndarray, k: int, seed) -> list[Fold]:
    """k folds of ``rows`` such that the rows of one group (``groups[row]``) share a fold.

    Groups are shuffled, then dealt largest first to the fold with the fewest rows so far,
    which balances the fold sizes when a few groups are large (annotators).
    """
    rows = np.asarray(rows)
    labels, inverse, counts = np.unique(np.asarray(groups)[rows], return_inverse=True, return_counts=True)
    if not 2 <= k <= len(labels):
        raise ValueError(f'cannot deal {len(labels)} groups into {k} folds')
    shuffled = np.random.default_rng(seed).permutation(len(labels))
    order = shuffled[np.argsort(-counts[shuffled], kind='stable')]
    fold_of_group = np.empty(len(labels), dtype=np.int64)
    sizes = np.zeros(k, dtype=np.int64)
    for group in order:
        target = int(np.argmin(sizes))
        fold_of_group[group] = target
        sizes[target] += counts[group]
    fold_of_row = fold_of_group[inverse.ravel()]
    return [Fold(np.sort(rows[fold_of_row != f]), np.sort(rows[fold_of_row == f])) for f in range(k)]


def fold_groups(data: RatingData, protocol: str) -> np.ndarray:
    """The group of every rating that a fold of ``protocol`` keeps together (see PROTOCOLS)."""
    if protocol == 'rows':
        return data.examples
    if protocol == 'cold-scene':
        return data.scenes
    if protocol == 'cold-user':
        return data.users
    raise ValueError(f"Could not resolve protocol '{protocol}' among choices {list(PROTOCOLS)}")


def make_folds(data: RatingData, protocol: str, k: int, seed, rows: np.ndarray | None = None) -> list[Fold]:
    """Folds of ``rows`` (all rows by default) for ``protocol``: examples, scenes or users
    never straddle a fold."""
    rows = np.arange(len(data)) if rows is None else np.asarray(rows)
    return grouped_folds(rows, fold_groups(data, protocol), k, seed)


def sweep_samples(pool: np.ndarray, fractions: Sequence[float], seed, groups: np.ndarray | None = None) -> dict:
    """Nested random subsets of ``pool`` (without replacement), sorted; fraction 1.0 is the
    pool. With ``groups`` (per rating, e.g. ``data.examples``) whole groups are sampled."""
    pool = np.asarray(pool)
    keys = pool if groups is None else np.asarray(groups)[pool]
    labels, inverse = np.unique(keys, return_inverse=True)
    rank = np.empty(len(labels), dtype=np.int64)
    rank[np.random.default_rng(seed).permutation(len(labels))] = np.arange(len(labels))
    rank_of_row = rank[inverse.ravel()]
    return {f: np.sort(pool[rank_of_row < max(1, int(round(f * len(labels))))]) for f in fractions}


# -- one fit, run in a worker -------------------------------------------------------------
@dataclass(frozen=True)
class FitTask:
    """Train one model on ``train`` rows, score it on ``test`` rows."""

    model: str
    fold: str
    stage: str          # 'inner' (selection), 'final' (fraction 1.0) or 'sweep'
    experiment: dict    # ExperimentConfig mapping with the epochs of this fit
    train: np.ndarray
    test: np.ndarray
    fraction: float = 1.0
    inner_fold: int = -1
    curve_at: tuple = ()  # joint epochs at which the test rows are also scored
    settings: str = '{}'  # the searched settings in the experiment, as settings_key text

    @property
    def name(self) -> str:
        """The fit in words, as failures are reported: 'GAT StARS fold 0:1 inner fold 0 (T1, T2) = (10, 100)'."""
        parts = {'inner': f'inner fold {self.inner_fold}', 'sweep': f'fraction {self.fraction:g}'}
        settings = '' if self.settings == '{}' else f' {self.settings}'
        training = self.experiment['training']
        return (f"{self.model} fold {self.fold} {parts.get(self.stage, self.stage)}{settings} "
                f"(T1, T2) = ({training['pretrain_epochs']}, {training['joint_epochs']})")


@dataclass(frozen=True)
class FitFailure:
    """What a fit that raised, or whose worker died, gives instead of scores. Unlike a
    diverged fit (scores with an ``error``) it is no result: it is never recorded."""

    error: str  # 'ValueError: no training rows'

    @classmethod
    def of(cls, error: BaseException) -> FitFailure:
        return cls(f'{type(error).__name__}: {error}')


def fit_outcome(future: futures.Future, name: str) -> Any:
    """The finished ``future``'s result, or a FitFailure carrying its exception (logged
    with its traceback under the fit's ``name``), so that one failed fit does not end a
    run of many."""
    try:
        return future.result()
    except Exception as error:  # noqa: BLE001 - any error of a fit is its own, reported by the caller
        log.warning('%s failed', name, exc_info=error)
        return FitFailure.of(error)


_WORKER_DATA: RatingData | None = None


def hold_worker_data(data: RatingData) -> None:
    """Keep ``data`` for the fits this worker process runs (see ``worker_data``)."""
    global _WORKER_DATA
    _WORKER_DATA = data


def _init_worker(data_blob: bytes, threads: int) -> None:
    import torch
    hold_worker_data(pickle.loads(data_blob))
    torch.set_num_threads(threads)


def normalised_rmse(y, p, actions, target_mean, target_std) -> float:
    """RMSE of z-scores (per-action mean/std of the training split), macro over actions."""
    y, p, actions = np.asarray(y, float), np.asarray(p, float), np.asarray(actions)
    errors = (p - y) / np.asarray(target_std, float)[actions]
    return float(np.mean([np.sqrt(np.mean(errors[actions == a] ** 2)) for a in np.unique(actions)]))


def worker_data() -> RatingData:
    """The data a ``fit_executor`` worker process holds (for tasks other than ``run_fit``)."""
    if _WORKER_DATA is None:
        raise RuntimeError('not in a fit_executor worker')
    return _WORKER_DATA


def run_fit(task: FitTask, data: RatingData | None = None) -> dict:
    """Fit ``task``'s model and return its test metrics, z-RMSE and seconds (and, with
    ``curve_at``, the same at those joint epochs under ``curve``)."""
    from stars_ros.model.training import StarsTrainer
    data = _WORKER_DATA if data is None else data
    config = ExperimentConfig.from_dict(task.experiment)
    started = time.perf_counter()
    recommender = StarsTrainer(config)
    y, actions = data.scores[task.test], data.actions[task.test]
    curve = []

    def scores():
        predictions = recommender.predict_rows(data, task.test)
        model = recommender.model
        return {**regression_report(y, predictions, actions),
                'z_rmse': normalised_rmse(y, predictions, actions, model.target_mean.cpu().numpy(),
                                          model.target_std.cpu().numpy())}

    def score_curve(stage, epoch):
        if stage == 'joint' and epoch in task.curve_at:
            curve.append({'epoch': epoch, **scores()})
    try:
        recommender.fit(data, task.train, on_epoch=score_curve if task.curve_at else None)
    except TrainingDivergedError as error:  # one diverged fit must not end a long run
        return {**{m: math.nan for m in METRICS}, 'n': len(task.test), 'z_rmse': math.inf,
                'fit_seconds': time.perf_counter() - started, 'predict_seconds': 0.0, 'epochs': 0,
                'error': str(error), **({'curve': []} if task.curve_at else {})}
    fitted = time.perf_counter()
    result = scores()
    predicted = time.perf_counter()
    model = recommender.model
    return {**result, 'fit_seconds': fitted - started, 'predict_seconds': predicted - fitted,
            'epochs': (config.training.pretrain_epochs if model.uses_content else 0) + config.training.joint_epochs,
            **({'curve': curve} if task.curve_at else {})}


def population_mean(data: RatingData, train: np.ndarray, test: np.ndarray) -> dict:
    """Scores of the constant predictor: each action's training mean."""
    started = time.perf_counter()
    means = {a: data.scores[train][data.actions[train] == a].mean() for a in np.unique(data.actions[train])}
    fallback = data.scores[train].mean()
    predictions = np.array([means.get(a, fallback) for a in data.actions[test]])
    # Pearson r of a constant is undefined; rounding in the mean can make it look computable.
    return {**regression_report(data.scores[test], predictions, data.actions[test]), 'pearson_r': math.nan,
            'fit_seconds': time.perf_counter() - started, 'predict_seconds': 0.0, 'epochs': 0}


class _InlineExecutor(futures.Executor):
    """Runs each task at submission, in this process (``jobs == 1``)."""

    def __init__(self, data: RatingData):
        self.data = data

    def submit(self, fn, /, *args, **kwargs):
        future = futures.Future()
        try:
            future.set_result(fn(*args, data=self.data, **kwargs))
        except BaseException as error:  # handed to the caller through the future
            future.set_exception(error)
        return future


def fit_executor(data: RatingData, jobs: int, threads: int) -> futures.Executor:
    """Where ``run_fit`` tasks run: inline for one job, else ``jobs`` worker processes
    holding ``data`` and using ``threads`` torch threads each. Workers are spawned, not
    forked: a forked child cannot use CUDA, a spawned one opens its own context."""
    if jobs == 1:
        return _InlineExecutor(data)
    return futures.ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context('spawn'),
                                       initializer=_init_worker, initargs=(pickle.dumps(data), threads))


def run_fits(executor: futures.Executor, waiting: list, jobs: int,
             cached: Callable[[FitTask], dict | None] | None = None):
    """Run the ``(FitTask, *context)`` items of ``waiting`` with at most ``jobs`` in flight,
    yielding ``(item, scores)`` as each fit finishes. ``waiting`` is read as the run goes, so
    the caller may put new items in front of it between two results. A task for which
    ``cached`` returns scores (an earlier run's) is yielded without being run. A fit that
    raises, or whose worker dies, yields a FitFailure instead of scores; so does every fit
    submitted after the executor broke (a process pool whose worker died)."""
    in_flight = {}
    try:
        while waiting or in_flight:
            while waiting and len(in_flight) < jobs:
                item = waiting.pop(0)
                scores = cached(item[0]) if cached else None
                if scores is not None:
                    yield item, scores
                    continue
                try:
                    in_flight[executor.submit(run_fit, item[0])] = item
                except futures.BrokenExecutor as error:
                    yield item, FitFailure.of(error)
            if not in_flight:
                continue
            finished, _ = futures.wait(list(in_flight), return_when=futures.FIRST_COMPLETED)
            for future in finished:
                item = in_flight.pop(future)
                yield item, fit_outcome(future, item[0].name)
    finally:
        executor.shutdown(cancel_futures=True)


# -- the protocol -----------------------------------------------------------------------
@dataclass(frozen=True)
class ModelSpec:
    label: str
    backbone: str | None
    variant: str            # 'base', 'stars', 'mf', 'population_mean' or an ablation's variant
    family: str = ''        # whose search space: FAMILIES, or '' for a follower / the mean
    model: dict = field(default_factory=dict)  # model settings that differ (an ablation's)
    follows: str | None = None  # label of the spec whose per-fold choice this one takes


def model_specs(config: ProtocolConfig) -> list[ModelSpec]:
    """Baselines first, then each backbone in its variants (the paper's row order) and its
    ablations."""
    specs = [ModelSpec(BASELINE_LABELS[b], None, b, 'mf' if b == 'mf' else '') for b in BASELINES
             if b in config.baselines]
    for backbone in config.backbones:
        name = DISPLAY.get(backbone, backbone)
        for variant in ('base', 'stars'):
            if variant in config.variants:
                specs.append(ModelSpec(f"{name} {'StARS' if variant == 'stars' else 'base'}", backbone, variant,
                                       variant))
        if backbone in config.ablation_backbones:
            for ablation in config.ablations:
                suffix, model = ABLATIONS[ablation]
                specs.append(ModelSpec(f'{name} {suffix}', backbone, model.get('variant', 'stars'), '',
                                       {k: v for k, v in model.items() if k != 'variant'}, f'{name} StARS'))
    return specs


def _settings_candidates(config: ProtocolConfig, spec: ModelSpec) -> list[dict]:
    """The search space of ``spec``'s family as a list of settings (one empty: no search)."""
    space = config.search.get(spec.family, {}) if spec.family else {}
    return [dict(zip(space, values)) for values in itertools.product(*space.values())]


def _candidates(config: ProtocolConfig, spec: ModelSpec) -> list[tuple[dict, tuple[int, int]]]:
    """(settings, (T1, T2)) worth trying; a content-free model skips pre-training, so only
    distinct T2 matter to it."""
    if spec.variant == 'mf':
        pairs = list(dict.fromkeys((0, t2) for _, t2 in config.grid))
    else:
        pairs = list(dict.fromkeys(config.grid))
    return [(settings, pair) for settings in _settings_candidates(config, spec) for pair in pairs]


def settings_key(settings: dict) -> str:
    """A candidate's settings as canonical text (records, resume keys, tables)."""
    return json.dumps(settings, sort_keys=True)


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


def run_protocol(data: RatingData, config: ProtocolConfig, protocol: str = 'rows', jobs: int = 1,
                 threads: int = 1, on_record: Callable[[dict], None] | None = None,
                 resume: Sequence[dict] = (), executor: futures.Executor | None = None) -> EvaluationResult:
    """Run the whole protocol on ``data``; ``on_record`` sees each entry as it arrives: the
    records, and the selection fits with ``stage`` 'inner'. ``resume`` takes such entries of
    an earlier run of the same config: their fits are not run again. Fits are seeded, so on
    the CPU a resumed run gives the results of an uninterrupted one. ``executor`` runs the
    fits, at most ``jobs`` at a time (default: ``fit_executor(data, jobs, threads)``); the
    run shuts it down. Failed fits and the selections they stopped are in ``failed`` and
    ``unchosen`` of the result."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"Could not resolve protocol '{protocol}' among choices {list(PROTOCOLS)}")
    if jobs < 1 or threads < 1:
        raise ValueError('jobs and threads must be positive')
    started = time.perf_counter()
    result = EvaluationResult(protocol, config, jobs=jobs, threads=threads)
    specs = model_specs(config)
    followers = {}
    for spec in specs:
        if spec.follows:
            followers.setdefault(spec.follows, []).append(spec)
    swept = {s.label for s in specs if (s.backbone in config.sweep_backbones and not s.follows)
             or (s.backbone is None and config.sweep_backbones)}
    fractions = sorted(set(config.fractions) | {1.0})
    examples = data.examples

    outer = {}
    for seed in config.seeds:
        for f, fold in enumerate(make_folds(data, protocol, config.folds, seed)):
            fold_id = f'{seed}:{f}'
            outer[fold_id] = (fold, make_folds(data, protocol, config.inner_folds, [seed, f, 1], fold.train),
                              sweep_samples(fold.train, fractions, [seed, f, 2], examples))
            result.folds.append({'fold': fold_id, 'n_train': len(fold.train), 'n_test': len(fold.test)})

    def record(spec, fold_id, fraction, settings, pair, n_train, n_test, scores, stage):
        entry = {'protocol': protocol, 'model': spec.label, 'backbone': spec.backbone, 'variant': spec.variant,
                 'fold': fold_id, 'fraction': fraction, 'stage': stage, 'settings': settings,
                 'T1': pair[0], 'T2': pair[1], 'n_train': n_train, 'n_test': n_test,
                 **{k: scores[k] for k in (*METRICS, 'fit_seconds', 'predict_seconds', 'epochs')}}
        if 'error' in scores:
            entry['error'] = scores['error']
            log.warning('%s fold %s fraction %g: %s', spec.label, fold_id, fraction, scores['error'])
        result.records.append(entry)
        if on_record:
            on_record(entry)

    for spec in specs:
        if spec.variant == 'population_mean':
            for fold_id, (fold, _, samples) in outer.items():
                for fraction in (fractions if spec.label in swept else [1.0]):
                    train = samples[fraction]
                    record(spec, fold_id, fraction, {}, (0, 0), len(train), len(fold.test),
                           population_mean(data, train, fold.test), 'final' if fraction == 1.0 else 'sweep')

    def experiment(spec, settings, pair):
        base = config.experiment_config(spec.backbone, spec.variant, {**spec.model, **settings})
        return base.replace(training={'pretrain_epochs': pair[0], 'joint_epochs': pair[1], 'threads': threads}).to_dict()

    # Own queue, at most `jobs` tasks in flight: fits unlocked by a finished selection
    # jump ahead of further selection fits, so complete results appear early.
    waiting = []
    inner_scores = {}
    earlier = {}
    for entry in resume:
        if entry.get('variant') == 'population_mean':  # recomputed: it takes no time
            continue
        if entry['stage'] == 'inner' and 'curve' not in entry:  # written before curves: one point, at T2
            entry = {**entry, 'curve': [{'epoch': entry['T2'], 'z_rmse': entry['z_rmse']}]}
        earlier[_fit_key(entry['model'], entry['fold'], entry['stage'], entry.get('fraction', 1.0),
                         entry.get('inner_fold', -1), entry['T1'], entry['T2'],
                         settings_key(entry.get('settings', {})))] = entry

    def cached(task):
        training = task.experiment['training']
        found = earlier.get(_fit_key(task.model, task.fold, task.stage, task.fraction, task.inner_fold,
                                     training['pretrain_epochs'], training['joint_epochs'], task.settings))
        result.resumed += found is not None
        return found

    def task(spec, fold_id, stage, settings, pair, train, test, **extra):
        return FitTask(spec.label, fold_id, stage, experiment(spec, settings, pair), train, test,
                       settings=settings_key(settings), **extra)

    def final_tasks(spec, fold_id, settings, pair):
        """The final fit (and sweep) of ``spec`` and of the specs that follow its choice."""
        fold, _, samples = outer[fold_id]
        items = []
        for chosen_by in [spec, *followers.get(spec.label, [])]:
            chosen = fractions if chosen_by.label in swept else [1.0]
            items += [(task(chosen_by, fold_id, 'final' if f == 1.0 else 'sweep', settings, pair, samples[f],
                            fold.test, fraction=f), chosen_by, settings, pair) for f in chosen]
        return items

    def choose(spec, fold_id, settings, pair, z_rmse):
        result.choices.append({'model': spec.label, 'fold': fold_id, 'settings': settings, 'T1': pair[0],
                               'T2': pair[1], 'inner_z_rmse': z_rmse})
        result.choices.extend({**result.choices[-1], 'model': follower.label, 'follows': spec.label}
                              for follower in followers.get(spec.label, []))
        return final_tasks(spec, fold_id, settings, pair)

    for spec in specs:
        if spec.variant == 'population_mean' or spec.follows:
            continue
        candidates = _candidates(config, spec)
        for fold_id, (_, inner, _) in outer.items():
            if len(candidates) == 1:
                waiting.extend(choose(spec, fold_id, *candidates[0], math.nan))
                continue
            inner_scores[spec.label, fold_id] = {(settings_key(s), p): [] for s, p in candidates}
            by_start = {}
            for settings, (t1, t2) in candidates:
                by_start.setdefault((settings_key(settings), t1), (settings, []))[1].append(t2)
            for (_, t1), (settings, ends) in by_start.items():
                pair = (t1, max(ends))  # one fit per start, scored at every T2 of the grid
                for i, (train, validation) in enumerate(inner):
                    waiting.append((task(spec, fold_id, 'inner', settings, pair, train, validation, inner_fold=i,
                                         curve_at=tuple(sorted(ends))), spec, settings, pair))
    total = len(waiting)
    fits = run_fits(executor or fit_executor(data, jobs, threads), waiting, jobs, cached if earlier else None)
    for done, ((fit, spec, settings, pair), scores) in enumerate(fits, 1):
        if isinstance(scores, FitFailure):
            result.failed.append({'fit': fit.name, 'model': spec.label, 'fold': fit.fold, 'stage': fit.stage,
                                  'fraction': fit.fraction, 'inner_fold': fit.inner_fold, 'settings': settings,
                                  'T1': pair[0], 'T2': pair[1], 'error': scores.error})
            continue
        if fit.stage != 'inner':
            record(spec, fit.fold, fit.fraction, settings, pair, len(fit.train), len(fit.test), scores, fit.stage)
            log.info('[%d/%d] %s fold %s fraction %g %s (T1, T2) = %s: %s %.4f (%.1f s)', done, total,
                     spec.label, fit.fold, fit.fraction, settings_key(settings), pair, config.error.upper(),
                     scores[config.error], scores['fit_seconds'])
            continue
        entry = {'stage': 'inner', 'model': spec.label, 'variant': spec.variant, 'fold': fit.fold,
                 'settings': settings, 'T1': pair[0], 'T2': pair[1], 'inner_fold': fit.inner_fold,
                 'z_rmse': scores['z_rmse'], 'curve': [{'epoch': c['epoch'], 'z_rmse': c['z_rmse']}
                                                      for c in scores['curve']],
                 'n_train': len(fit.train), 'n_test': len(fit.test), 'fit_seconds': scores['fit_seconds'],
                 'predict_seconds': scores['predict_seconds'], 'epochs': scores['epochs']}
        result.inner.append(entry)
        if on_record:
            on_record(entry)
        table = inner_scores[spec.label, fit.fold]
        reached = {c['epoch']: c['z_rmse'] for c in entry['curve']}
        for t2 in fit.curve_at:  # a diverged fit has no curve: every point it owed is lost
            z_rmse = reached.get(t2, math.inf)
            table[settings_key(settings), (pair[0], t2)].append(z_rmse)
            result.selection.append({'model': spec.label, 'fold': fit.fold, 'settings': settings_key(settings),
                                     'T1': pair[0], 'T2': t2, 'inner_fold': fit.inner_fold, 'z_rmse': z_rmse,
                                     'n_train': len(fit.train), 'n_test': len(fit.test)})
        log.info('[%d/%d] %s fold %s inner %d %s T1 %d: z-RMSE %s', done, total, spec.label, fit.fold,
                 fit.inner_fold, settings_key(settings), pair[0], {t: round(v, 4) for t, v in reached.items()})
        if all(len(v) == config.inner_folds for v in table.values()):
            means = {candidate: float(np.mean(v)) for candidate, v in table.items()}
            best = min(means, key=means.get)  # ties: first candidate
            chosen_settings = json.loads(best[0])
            log.info('%s fold %s: chose %s (T1, T2) = %s by inner z-RMSE %.4f', spec.label, fit.fold, best[0],
                     best[1], means[best])
            unlocked = choose(spec, fit.fold, chosen_settings, best[1], means[best])
            waiting[:0] = unlocked
            total += len(unlocked)
    result.unchosen = [{'model': label, 'fold': fold_id} for (label, fold_id), table in inner_scores.items()
                       if any(len(v) < config.inner_folds for v in table.values())]
    result.wall_seconds = time.perf_counter() - started
    return result


# -- summaries --------------------------------------------------------------------------
def _fold_order(entry: dict) -> tuple:
    return tuple(int(part) for part in entry['fold'].split(':'))


def by_model(records: list) -> dict:
    """model label -> records sorted by fold, in first-seen order."""
    grouped = {}
    for entry in records:
        grouped.setdefault(entry['model'], []).append(entry)
    return {label: sorted(entries, key=_fold_order) for label, entries in grouped.items()}


def corrected_test(result: EvaluationResult, label: str, reference: str, metric: str) -> dict | None:
    """``label`` − ``reference`` on ``metric`` over the outer folds (corrected resampled
    t-test); None when either lacks finite scores."""
    final = by_model(result.final())
    if label not in final or reference not in final:
        return None
    one, other = final[label], final[reference]
    if [e['fold'] for e in one] != [e['fold'] for e in other]:
        raise ValueError(f'{label} and {reference} were scored on different folds')
    values = ([e[metric] for e in one], [e[metric] for e in other])
    if not all(math.isfinite(v) for side in values for v in side):
        return None
    test = corrected_resampled_ttest(*values, [e['n_train'] for e in one], [e['n_test'] for e in one])
    return {'metric': metric, 'delta': test.delta, 't': test.t, 'df': test.df, 'p': test.p}


def paired_tests(result: EvaluationResult, metrics: Sequence[str]) -> list[dict]:
    """StARS − base per backbone and metric; Holm within each metric over the backbones."""
    tests = []
    for metric in metrics:
        family = []
        for backbone in result.config.backbones:
            name = DISPLAY.get(backbone, backbone)
            test = corrected_test(result, f'{name} StARS', f'{name} base', metric)
            if test is not None:
                family.append({'backbone': backbone, **test})
        for entry, adjusted in zip(family, holm([e['p'] for e in family])):
            entry['p_holm'] = float(adjusted)
        tests.extend(family)
    return tests


def ablation_tests(result: EvaluationResult, metrics: Sequence[str]) -> list[dict]:
    """Every model of an ablation backbone (MF, StARS and its ablations) against that
    backbone's base, per metric; Holm within each (backbone, metric) over the models."""
    tests = []
    labels = [spec.label for spec in model_specs(result.config)]
    for backbone in result.config.ablation_backbones:
        name = DISPLAY.get(backbone, backbone)
        compared = [BASELINE_LABELS['mf'], *(label for label in labels
                                              if label.startswith(f'{name} ') and label != f'{name} base')]
        for metric in metrics:
            family = [{'backbone': backbone, 'model': label, 'reference': f'{name} base', **test}
                      for label in compared
                      if (test := corrected_test(result, label, f'{name} base', metric)) is not None]
            for entry, adjusted in zip(family, holm([e['p'] for e in family])):
                entry['p_holm'] = float(adjusted)
            tests.extend(family)
    return tests


def sparsity_summary(result: EvaluationResult) -> dict:
    """model label -> fraction -> metric -> per-fold values, for swept models."""
    summary = {}
    for entry in result.records:
        summary.setdefault(entry['model'], {}).setdefault(entry['fraction'], {m: [] for m in METRICS})
        for metric in METRICS:
            summary[entry['model']][entry['fraction']][metric].append(entry[metric])
    return {label: dict(sorted(by_fraction.items())) for label, by_fraction in summary.items()
            if len(by_fraction) > 1}


def time_accounting(result: EvaluationResult) -> dict:
    """Worker seconds by stage and by model, s/epoch on full pools, and the wall time."""
    stages, models = {}, {}
    for entry in result.inner + result.records:
        stage = entry.get('stage', 'inner')
        seconds = entry['fit_seconds'] + entry['predict_seconds']
        stages[stage] = stages.get(stage, 0.0) + seconds
        models.setdefault(entry['model'], {}).setdefault(stage, 0.0)
        models[entry['model']][stage] += seconds
    order = [spec.label for spec in model_specs(result.config)]
    models = {label: models[label] for label in order if label in models}
    per_epoch = {}
    for label, entries in by_model([e for e in result.final() if e['epochs']]).items():
        per_epoch[label] = float(np.mean([e['fit_seconds'] / e['epochs'] for e in entries]))
    busy = sum(stages.values())
    return {'wall_seconds': result.wall_seconds, 'worker_seconds': busy, 'jobs': result.jobs,
            'threads_per_job': result.threads,
            'utilisation': busy / (result.wall_seconds * result.jobs) if result.wall_seconds and not result.resumed
            else math.nan, 'resumed_fits': result.resumed,
            'by_stage': stages, 'by_model': models, 'seconds_per_epoch_full_pool': per_epoch}
