"""The recommender libraries a user would pick instead of StARS, as protocol baselines fitted
on exactly the same examples and scored the same way.

* ``surprise_svd``: scikit-surprise's SVD (biased matrix factorisation by SGD) on person ×
  (scene, action) items: content-free.
* ``myfm``: myFM's Bayesian factorisation machine (Gibbs sampling) on one-hot person, scene
  and action plus the scene's features, with all their pairwise interactions. Tabular
  scenes give their feature columns; scene graphs their fixed summary
  (``data.scene_summary``).
* ``myfm_encoder``: the same machine with h_i of a base model of the backbone (trained on
  the fold's training examples with the settings base chose there) in place of the
  features, so a table separates better features from better personalisation.

Both libraries are optional (``requirements-peers.txt``): ``require`` fails before any fit,
with the install line. A fit sees the scores of the training rows only; features are
standardised with the training scenes' statistics; myFM learns per-action z-scores (the
training rows' mean and standard deviation, as StARS does); predictions are clipped to the
data's rating scale, as StARS's are.
"""
from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import time
from typing import Annotated

import numpy as np
from pydantic import Field, model_validator
from scipy import sparse

from stars_ros.data.ratings import RatingData
from stars_ros.data.scene_summary import summarise_store
from stars_ros.errors import ConfigError
from stars_ros.model.config import ExperimentConfig, Float, Int, Section, validated
from stars_ros.model.metrics import normalised_rmse, regression_report

PEERS = ('surprise_svd', 'myfm', 'myfm_encoder')
LABELS = {'surprise_svd': 'Surprise SVD (no content)', 'myfm': 'myFM (scene features)'}
#: peer -> (module, the distribution that provides it)
LIBRARIES = {'surprise_svd': ('surprise', 'scikit-surprise'), 'myfm': ('myfm', 'myfm'),
             'myfm_encoder': ('myfm', 'myfm')}
INSTALL_LINE = 'pip install -r requirements-peers.txt'


def encoder_label(backbone_label: str) -> str:
    """The table label of ``myfm_encoder`` for one backbone ('GAT' -> 'myFM on GAT base h_i')."""
    return f'myFM on {backbone_label} base h_i'


class SurpriseSVDSettings(Section):
    """scikit-surprise SVD's settings (its defaults)."""

    n_factors: Annotated[Int, Field(ge=1)] = 100
    n_epochs: Annotated[Int, Field(ge=1)] = 20
    lr_all: Annotated[Float, Field(gt=0.0)] = 0.005
    reg_all: Annotated[Float, Field(ge=0.0)] = 0.02


class MyFMSettings(Section):
    """myFM's rank and Gibbs sampling: ``n_iter`` sweeps, the last ``n_kept_samples`` averaged."""

    rank: Annotated[Int, Field(ge=1)] = 8
    n_iter: Annotated[Int, Field(ge=1)] = 200
    n_kept_samples: Annotated[Int, Field(ge=1)] = 150

    @model_validator(mode='after')
    def _kept_within(self) -> 'MyFMSettings':
        if self.n_kept_samples > self.n_iter:
            raise ValueError(f'n_kept_samples ({self.n_kept_samples}) must not exceed n_iter ({self.n_iter})')
        return self


SETTINGS = {'surprise_svd': SurpriseSVDSettings, 'myfm': MyFMSettings, 'myfm_encoder': MyFMSettings}


def require(peers) -> None:
    """Raise ConfigError naming the install line when a library of ``peers`` is missing."""
    missing = sorted({LIBRARIES[p][1] for p in peers if p in LIBRARIES
                      and importlib.util.find_spec(LIBRARIES[p][0]) is None})
    if missing:
        raise ConfigError(f"baselines {[p for p in peers if p in LIBRARIES]} need {', '.join(missing)}, which "
                          f"is not installed: {INSTALL_LINE}")


def settings_of(peer: str, values: dict):
    """``values`` validated as ``peer``'s settings."""
    return validated(SETTINGS[peer], values, f'{peer} settings')


def _action_statistics(data: RatingData, train: np.ndarray) -> tuple:
    """Per-action mean and standard deviation of the training scores (1 where constant)."""
    mean, std = np.zeros(len(data.action_names)), np.ones(len(data.action_names))
    for a in np.unique(data.actions[train]):
        scores = data.scores[train][data.actions[train] == a]
        mean[a] = scores.mean()
        std[a] = scores.std() if scores.std() > 1e-8 else 1.0
    return mean, std


def _surprise_svd(data: RatingData, train, test, settings: SurpriseSVDSettings, seed: int) -> np.ndarray:
    import pandas as pd
    from surprise import SVD, Dataset, Reader
    scores = data.scores[train]
    scale = data.scale or (float(scores.min()), float(scores.max()))
    items = np.char.add(np.char.add(data.scenes.astype(str), ':'), data.actions.astype(str))
    frame = pd.DataFrame({'user': data.users[train].astype(str), 'item': items[train], 'score': scores})
    trainset = Dataset.load_from_df(frame, Reader(rating_scale=scale)).build_full_trainset()
    algorithm = SVD(**settings.model_dump(), random_state=seed).fit(trainset)
    return np.array([algorithm.predict(str(u), i).est for u, i in zip(data.users[test], items[test])])


def _one_hot(values: np.ndarray, known: np.ndarray) -> sparse.csr_matrix:
    """Rows one-hot over the distinct ``known`` values; a value not among them is all zeros."""
    vocabulary = {v: j for j, v in enumerate(np.unique(known))}
    columns = np.array([vocabulary.get(v, -1) for v in values])
    rows = np.flatnonzero(columns >= 0)
    return sparse.csr_matrix((np.ones(len(rows)), (rows, columns[rows])), shape=(len(values), len(vocabulary)))


def _myfm(data: RatingData, train, test, features: np.ndarray, settings: MyFMSettings, seed: int) -> np.ndarray:
    """myFM on [person, scene, action one-hots, the scene's standardised ``features``]."""
    import myfm
    train_scenes = np.unique(data.scenes[train])
    centre = features[train_scenes].mean(axis=0)
    spread = features[train_scenes].std(axis=0)
    standard = (features - centre) / np.where(spread > 1e-8, spread, 1.0)
    mean, std = _action_statistics(data, train)

    def design(rows):
        blocks = [_one_hot(data.users[rows], data.users[train]), _one_hot(data.scenes[rows], data.scenes[train]),
                  _one_hot(data.actions[rows], np.arange(len(data.action_names))),
                  sparse.csr_matrix(standard[data.scenes[rows]])]
        return sparse.hstack(blocks, format='csr'), [b.shape[1] for b in blocks]
    x_train, groups = design(train)
    z = (data.scores[train] - mean[data.actions[train]]) / std[data.actions[train]]
    machine = myfm.MyFMRegressor(rank=settings.rank, random_seed=seed)
    with contextlib.redirect_stderr(io.StringIO()):  # its progress bar, one line per sweep
        machine.fit(x_train, z, n_iter=settings.n_iter, n_kept_samples=settings.n_kept_samples, group_shapes=groups)
    x_test, _ = design(test)
    return machine.predict(x_test) * std[data.actions[test]] + mean[data.actions[test]]


def _encoded_scenes(data: RatingData, train, experiment: dict) -> tuple:
    """(h_i of every scene, epochs) under a base model trained on ``train`` by the one recipe,
    each scene encoded by its served form (``model.scoring``)."""
    from stars_ros.model.predictor import Predictor
    from stars_ros.personalisation.recipe import Recipe
    from stars_ros.model.scoring import served_encodings
    config = ExperimentConfig.from_dict(experiment)
    trainer = Recipe(config).fit(data, train)
    epochs = config.training.pretrain_epochs + config.training.joint_epochs
    return served_encodings(Predictor.from_model(trainer), data), epochs


def peer_predictions(peer: str, settings_text: str, experiment: dict, data: RatingData, train: np.ndarray,
                     test: np.ndarray) -> tuple:
    """(rating-scale predictions for ``test`` rows, epochs of an encoder trained for them) of
    ``peer`` fitted on ``train`` rows: no score of a test row is read."""
    settings = settings_of(peer, json.loads(settings_text))
    seed = int(experiment.get('training', {}).get('seed', 0))
    epochs = 0
    if peer == 'surprise_svd':
        predictions = _surprise_svd(data, train, test, settings, seed)
    else:
        if peer == 'myfm_encoder':
            features, epochs = _encoded_scenes(data, train, experiment)
        elif data.kind == 'graph':
            features = summarise_store(data.store)
        else:
            features = data.store.features.numpy().astype(np.float64)
        predictions = _myfm(data, train, test, features, settings, seed)
    return (predictions if data.scale is None else np.clip(predictions, *data.scale)), epochs


def run_peer(peer: str, settings_text: str, experiment: dict, data: RatingData, train: np.ndarray,
             test: np.ndarray, curve_at: tuple = ()) -> dict:
    """Fit ``peer`` on ``train`` rows and score it on ``test`` rows: the record's metrics,
    the selection's z-RMSE, seconds (``fit_seconds`` covers predicting too; for
    ``myfm_encoder`` training the encoder) and ``curve`` at ``curve_at`` for an inner fit."""
    started = time.perf_counter()
    predictions, epochs = peer_predictions(peer, settings_text, experiment, data, train, test)
    finished = time.perf_counter()
    y, actions = data.scores[test], data.actions[test]
    mean, std = _action_statistics(data, train)
    z_rmse = normalised_rmse(y, predictions, actions, mean, std)
    return {**regression_report(y, predictions, actions), 'z_rmse': z_rmse, 'fit_seconds': finished - started,
            'predict_seconds': 0.0, 'epochs': epochs,
            **({'curve': [{'epoch': t2, 'z_rmse': z_rmse} for t2 in curve_at]} if curve_at else {})}
