"""Where the robot should be, for this person: the served score of the robot placed at every
cell of a square grid centred on it (``StarsRecommender.placement_map``).

Each cell's score and ``score_sd`` are what ranking its placement as a candidate scene gives
(``Predictor.rank_many``, which ``~/rank_candidates`` and ``StarsRecommender.rank_scenes``
use): the same served arithmetic over the same features, for a trained person, a folded-in
one or a stranger. Only its cost differs: the cells' scenes are featurised as arrays over
placements (``data.placements``), encoded in one pass of each encoder the person needs (GAT's
compiled kernel takes them stacked, with no per-cell work), and the person's part (θ, Σ) is
resolved once. Cells where the robot cannot be (``placements.valid_placements``) are not
scored: their score and ``score_sd`` are NaN.

The grid is in the scene's frame (SocNav1 axes, metres: +x to the robot's right, +y ahead):
``score[row, col]`` is the robot at x = origin_x + (col + ½)·resolution,
y = origin_y + (row + ½)·resolution, rows one after the other from the origin cell, as
nav_msgs/OccupancyGrid orders its data (turn it into REP 103 with ``data.frames``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stars_ros.data.placements import featurise_placements, valid_placements
from stars_ros.data.scene_graph import validate_scene
from stars_ros.errors import BadMapRequest, SceneGraphError, StarsError
from stars_ros.model.vocabulary import UNKNOWN

MAX_CELLS_PER_SIDE = 256
MAX_ID_LENGTH = 256  # characters, as msg_schemas' user_id


@dataclass(frozen=True)
class PlacementMap:
    """A person's map of placements (see the module docstring): ``score`` and ``score_sd``
    [rows, cols] on the rating scale (NaN where not ``valid``; ``score_sd`` NaN for a model
    without users), ``valid`` [rows, cols], ``origin`` (x, y) metres of the first cell's
    outer corner, ``resolution`` (metres per cell), the robot's ``heading`` at every cell (None:
    as it is), the ``action`` scored and the ``user`` it is for."""

    score: np.ndarray
    score_sd: np.ndarray
    valid: np.ndarray
    origin: tuple
    resolution: float
    heading: float | None
    action: str
    user: object

    @property
    def shape(self) -> tuple:
        return self.valid.shape

    def centres(self) -> tuple:
        """(x, y) [rows, cols] metres: where each cell puts the robot."""
        return cell_centres(self.origin, self.resolution, self.shape[0])


def cell_centres(origin: tuple, resolution: float, cells: int) -> tuple:
    """(x, y) [cells, cells] metres of the centres of a square grid of ``cells`` per side."""
    steps = (np.arange(cells) + 0.5) * resolution
    return np.meshgrid(origin[0] + steps, origin[1] + steps)


def _number(value, name: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise BadMapRequest('schema', f'{name} must be a number, got {value!r}') from None
    if not math.isfinite(number):
        raise BadMapRequest('non_finite', f'{name} is {number}: not a finite number')
    return number


def _cells(size, resolution) -> int:
    """Cells per side of a grid ``size`` metres wide at ``resolution``; BadMapRequest if refused."""
    size, resolution = _number(size, 'size'), _number(resolution, 'resolution')
    if size <= 0 or resolution <= 0:
        raise BadMapRequest('schema', f'size and resolution must be positive, got {size} and {resolution}')
    per_side = size / resolution
    if not per_side < MAX_CELLS_PER_SIDE + 0.5:
        most = f'{MAX_CELLS_PER_SIDE} × {MAX_CELLS_PER_SIDE}'
        raise BadMapRequest('too_large', f'size {size} m at resolution {resolution} m is {per_side:.0f} '
                                         f'cells a side; a map has at most {most}')
    return max(1, round(per_side))


def _check_scene(scene) -> None:
    """BadMapRequest for a scene that is not a scene-graph dict, or holds a non-finite number."""
    if not isinstance(scene, dict):
        raise BadMapRequest('schema', 'a placement map takes the scene\'s content (a scene-graph dict, '
                                      f'msg_schemas/scene_graph.schema.json), got {type(scene).__name__}')
    numbers = [v for key in ('humans', 'objects') for e in scene.get(key) or () if isinstance(e, dict)
               for v in (e.get('xPos'), e.get('yPos'), e.get('orientation'))]
    numbers += [v for point in scene.get('room') or () if isinstance(point, (list, tuple)) for v in point]
    if any(isinstance(v, float) and not math.isfinite(v) for v in numbers):
        raise BadMapRequest('non_finite', 'the scene holds a non-finite number (NaN or infinity)')


def placement_map(predictor, uncertainty, user, scene: dict, size: float = 8.0, resolution: float = 0.125,
                  heading: float | None = None, action: str | None = None) -> PlacementMap:
    """The ``PlacementMap`` of ``user`` in ``scene`` served by ``predictor`` (its ``score_sd``
    from ``uncertainty``, a ``personalisation.uncertainty.Uncertainty``; None: NaN). Raises
    BadMapRequest (its ``kind`` says why), UnknownActionError, or StarsError for a non-finite score."""
    if user is not None and len(str(user)) > MAX_ID_LENGTH:
        raise BadMapRequest('schema', f'user id of {len(str(user))} characters; at most {MAX_ID_LENGTH}')
    cells = _cells(size, resolution)
    resolution = float(resolution)
    if heading is not None:
        heading = _number(heading, 'heading')
    if predictor.input_kind != 'graph':
        raise BadMapRequest('model', 'a placement map needs a model that reads scene graphs')
    _check_scene(scene)
    action = predictor.ranking_action(action)
    column = predictor.action_columns([action])[0]
    origin = (-cells * resolution / 2, -cells * resolution / 2)
    x, y = cell_centres(origin, resolution, cells)
    try:
        validate_scene(scene)  # before the mask reads it; featurise_placements checks the rest
        valid = valid_placements(scene, x, y)
        batch = featurise_placements(scene, x[valid], y[valid], heading)
    except SceneGraphError as error:
        raise BadMapRequest('scene_graph', str(error)) from None
    score, score_sd = np.full((cells, cells), np.nan), np.full((cells, cells), np.nan)
    if len(batch):
        score[valid], sd = _scored(predictor, uncertainty, user, batch, column)
        if sd is not None:
            score_sd[valid] = sd
    return PlacementMap(score, score_sd, valid, origin, resolution, heading, action, user)


def _scored(predictor, uncertainty, user, batch, column: int) -> tuple:
    """(scores [n], score_sd [n] or None) of ``batch``'s n placements under ``column``, as
    ``Predictor.rank_many`` scores candidate scenes."""
    count = len(batch)
    inference = predictor.inference
    h = inference.encode(batch, count)
    plain = predictor.stranger_scores(batch, count) if predictor.hands_over(user) else None
    rows = np.full(count, UNKNOWN)
    unclipped = predictor.unclipped_scores(user, batch, h, rows, plain)
    scores = predictor.clip(unclipped)
    if not np.isfinite(scores).all():
        raise StarsError('the model produced a non-finite score')
    if uncertainty is None:
        return scores[:, column], None
    served_z = None  # one served around the plain encoder: their z, which their uncertainty centres on
    if plain is not None:
        served_z = (unclipped[:, column] - inference.target_mean[column]) / inference.target_std[column]
    spread = uncertainty.spread(predictor, user, h, rows, [column] * count, served_z=served_z)
    return scores[:, column], spread.sd
