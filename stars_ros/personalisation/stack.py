"""The serving stack of a model, made one way for the node, the front door, k-shot and the
benchmarks: its ``Predictor``, the ``FoldIn`` over that predictor and the ``Uncertainty``
over that fold-in, so that every caller folds people in and scores their uncertainty with
the same arithmetic over the same weights.
"""
from __future__ import annotations

import os
from typing import NamedTuple

from stars_ros.errors import StarsError
from stars_ros.model.predictor import Predictor
from stars_ros.personalisation.foldin import FoldIn
from stars_ros.personalisation.uncertainty import Uncertainty


class ServingStack(NamedTuple):
    """``predictor``; ``foldin`` and ``uncertainty`` (None for a model without users, with
    ``no_foldin`` saying why)."""

    predictor: Predictor
    foldin: FoldIn | None
    uncertainty: Uncertainty | None
    no_foldin: str | None = None

    def require_foldin(self) -> FoldIn:
        """The fold-in; StarsError (why there is none) for a model without users."""
        if self.foldin is None:
            raise StarsError(self.no_foldin)
        return self.foldin


def serving_stack(model, scene_by_scene: bool = False, stored=None) -> ServingStack:
    """The stack serving ``model``: a ``Predictor``, a checkpoint's path, or a fitted model
    held in memory (``model.fitted.FittedModel``, served from the content its checkpoint would
    hold). ``scene_by_scene`` and ``stored`` (scenes -> their h a store keeps) go to the
    fold-in (``FoldIn``)."""
    if isinstance(model, Predictor):
        predictor = model
    elif isinstance(model, (str, os.PathLike)):
        predictor = Predictor.load(model)
    else:
        predictor = Predictor.from_model(model)
    try:
        foldin = FoldIn(predictor, scene_by_scene=scene_by_scene)
    except StarsError as error:  # a model without users: served, never folded in
        return ServingStack(predictor, None, None, str(error))
    foldin.stored = stored
    return ServingStack(predictor, foldin, Uncertainty(foldin))
