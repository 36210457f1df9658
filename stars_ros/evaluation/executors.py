"""The evaluation's fits: what one is (``FitTask``), training and scoring it (``run_fit``),
and where fits run (``fit_executor``, ``run_fits``).

Fits are independent jobs; with ``jobs > 1`` they run in worker processes (one torch
thread each), which on a CPU pays better than threads inside one small-graph model. With
``training.device`` 'cuda' the workers share the one GPU, each with its own CUDA context.
Any other ``concurrent.futures.Executor`` can run them instead
(``stars_ros.evaluation.ray_executor``: Ray tasks). A fit that raises, or whose worker
dies, gives a ``FitFailure`` instead of scores; a fit that diverges gives scores (NaN, with
an ``error``).
"""
from __future__ import annotations

import concurrent.futures as futures
import logging
import math
import multiprocessing
import pickle
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from stars_ros.data.ratings import RatingData
from stars_ros.errors import TrainingDivergedError
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.metrics import normalised_rmse, regression_report

log = logging.getLogger(__name__)

METRICS = ('mse', 'rmse', 'pearson_r', 'ccc')


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
    peer: str = ''        # a peer library (``peers.PEERS``) fitted instead of a StARS model
    peer_settings: str = '{}'  # its settings, as settings_key text
    holdout: bool = False  # also score the recipe's hold-out fit (specs.HOLDOUT_RECIPE), under ``holdout``

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


_WORKER_DATA: RatingData | None = None  # set once in each worker process (fit_executor, RayExecutor)


def hold_worker_data(data: RatingData) -> None:
    """Keep ``data`` for the fits this worker process runs (see ``worker_data``)."""
    global _WORKER_DATA
    _WORKER_DATA = data


def _init_worker(data_blob: bytes, threads: int) -> None:
    import torch
    hold_worker_data(pickle.loads(data_blob))
    torch.set_num_threads(threads)


def worker_data() -> RatingData:
    """The data a ``fit_executor`` worker process holds (for tasks other than ``run_fit``)."""
    if _WORKER_DATA is None:
        raise RuntimeError('not in a fit_executor worker')
    return _WORKER_DATA


def run_fit(task: FitTask, data: RatingData | None = None) -> dict:
    """Fit ``task``'s model as ``train`` fits it (``StarsRecommender.fit``, the one recipe) and
    return its test metrics, z-RMSE and seconds (and, with ``curve_at``, the same at those
    joint epochs under ``curve``), every prediction the served form's (``fit_and_predict``);
    with ``holdout`` the same of the recipe's hold-out fit, with its ``n_train``, under ``holdout``."""
    data = worker_data() if data is None else data
    if task.peer:
        from stars_ros.evaluation.peers import run_peer
        return run_peer(task.peer, task.peer_settings, task.experiment, data, task.train, task.test, task.curve_at)
    config = ExperimentConfig.from_dict(task.experiment)
    started = time.perf_counter()
    try:
        fitted, predictions, curve = fit_and_predict(task, data)
    except TrainingDivergedError as error:  # one diverged fit must not end a long run
        return {**{m: math.nan for m in METRICS}, 'n': len(task.test), 'z_rmse': math.inf,
                'fit_seconds': time.perf_counter() - started, 'predict_seconds': 0.0, 'epochs': 0,
                'error': str(error), **({'curve': []} if task.curve_at else {})}
    inference, training = fitted.predictor.inference, config.training
    epochs = (training.pretrain_epochs if inference.uses_content else 0) + training.joint_epochs
    scores = {**_scores(data, task.test, predictions, inference), 'fit_seconds': fitted.fit_seconds,
              'predict_seconds': fitted.predict_seconds, 'epochs': epochs,
              **({'curve': curve} if task.curve_at else {})}
    if task.holdout:
        scores['holdout'] = holdout_scores(fitted.recommender.recipe, data, task.test, epochs)
    return scores


def holdout_scores(recipe, data: RatingData, test: np.ndarray, epochs: int) -> dict:
    """The test metrics of ``recipe``'s hold-out fit with its own prior (``Recipe.holdout_model``),
    scored in its served form, and the rows it was fitted on (``n_train``). Its fit is part of
    the shipped fit's seconds, so ``fit_seconds`` is 0."""
    from stars_ros.model.predictor import Predictor
    from stars_ros.model.scoring import served_predictions

    started = time.perf_counter()
    predictor = Predictor.from_model(recipe.holdout_model())
    predictions = served_predictions(predictor, data, test)
    return {**_scores(data, test, predictions, predictor.inference), 'n_train': len(recipe.holdout_rows),
            'fit_seconds': 0.0, 'predict_seconds': time.perf_counter() - started, 'epochs': epochs}


class Fitted:
    """``fit_and_predict``'s fitted front door (``recommender``), its ``predictor`` and the
    seconds its fit and its predictions took."""

    def __init__(self, recommender, fit_seconds: float, predict_seconds: float):
        self.recommender, self.predictor = recommender, recommender.predictor
        self.fit_seconds, self.predict_seconds = fit_seconds, predict_seconds


def _scores(data: RatingData, rows: np.ndarray, predictions: np.ndarray, inference) -> dict:
    y, actions = data.scores[rows], data.actions[rows]
    return {**regression_report(y, predictions, actions),
            'z_rmse': normalised_rmse(y, predictions, actions, inference.target_mean, inference.target_std)}


def fit_and_predict(task: FitTask, data: RatingData) -> tuple:
    """(``Fitted``, predictions of ``task.test``, curve points): the StARS fit of ``task``
    through the front door, each test rating scored as ``StarsRecommender.load`` of its
    checkpoint would serve it (``model.scoring``), the same at each joint epoch of
    ``curve_at`` from the model ``fit`` would return then (``fitted_now``)."""
    from stars_ros.model.predictor import Predictor
    from stars_ros.model.scoring import served_predictions
    from stars_ros.recommender import StarsRecommender

    front, curve = StarsRecommender(ExperimentConfig.from_dict(task.experiment)), []

    def score_curve(stage, epoch):
        if stage == 'joint' and epoch in task.curve_at:
            predictor = Predictor.from_model(front.fitted_now(stage, epoch))
            predictions = served_predictions(predictor, data, task.test)
            curve.append({'epoch': epoch, **_scores(data, task.test, predictions, predictor.inference)})
    started = time.perf_counter()
    front.fit(data, task.train, on_epoch=score_curve if task.curve_at else None)
    fitted = time.perf_counter()
    predictions = served_predictions(front.predictor, data, task.test)
    return Fitted(front, fitted - started, time.perf_counter() - fitted), predictions, curve


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
