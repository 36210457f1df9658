"""One scene for several people, side by side, as a PNG: the scene from above in REP 103 axes
(x forward up the page, y left to the left; ``node.markers`` converts from SocNav1), each
person's ranked placements of the robot (or ranked actions), and every entity coloured by its
removal effect on that person's best entry (``model.explain``; one colour scale for all
panels, so the people compare). ROS-free; matplotlib only when drawing.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stars_ros.data.scene_source import placement_candidates
from stars_ros.errors import StarsError
from stars_ros.model.explain import removal_effects
from stars_ros.data.frames import heading_yaw, robot_pose_in, to_rep103

MATPLOTLIB = 'matplotlib==3.11.2'  # requirements-train.txt's pin (the train extra)


def pyplot():
    """matplotlib's pyplot on the file-only Agg backend; StarsError with the install line
    when matplotlib is missing (a robot need not have it)."""
    try:
        import matplotlib
    except ImportError:
        raise StarsError(f'drawing a scene needs matplotlib: pip install {MATPLOTLIB}') from None
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


@dataclass(frozen=True)
class PersonView:
    """What one person's panel shows: the ranking [(name, score)] best first, the robot poses
    of the candidates {name: (x m, y m)} (empty for action ranking), and the removal effect of
    each entity (id -> effect) on the best entry's score."""

    user: str
    ranking: list
    poses: dict
    effects: dict


def person_view(predictor, user: str, scene: dict, placements: int = 0, action: str | None = None) -> PersonView:
    """``user``'s ranking of ``placements`` robot placements of ``scene`` by ``action``'s score
    (default: the model's first), or with ``placements`` 0 of the model's actions in it."""
    if placements:
        candidates = placement_candidates(scene, placements)
        graphs = [c['graph'] for c in candidates]
        column = predictor.action_columns([action or predictor.actions[0]])[0]
        scores = predictor.score(user, graphs)[:, column]
        order = np.argsort(-scores, kind='stable')
        best = int(order[0])
        entities, effects = removal_effects(predictor, user, [graphs[best]])[0]
        poses = {c['candidate']: to_rep103(*robot_pose_in(scene, c['graph'])[:2]) for c in candidates}
        ranking = [(candidates[k]['candidate'], float(scores[k])) for k in order]
        return PersonView(user, ranking, poses, {e[0]: float(v) for e, v in zip(entities, effects[:, column])})
    scores = predictor.score(user, [scene])[0]
    order = np.argsort(-scores, kind='stable')
    entities, effects = removal_effects(predictor, user, [scene])[0]
    return PersonView(user, [(predictor.actions[k], float(scores[k])) for k in order], {},
                      {e[0]: float(v) for e, v in zip(entities, effects[:, int(order[0])])})


def _draw(axis, scene: dict, view: PersonView, colour, title: str, listed: bool = True):
    """One panel: walls, room, interactions, objects, humans (with heading), robot, candidates
    (``listed``: with the ranking written in a corner)."""
    room = [tuple(p) for p in scene['room']]
    if len(room) > 1 and room[0] == room[-1]:
        room = room[:-1]
    points = [to_rep103(*p) for p in room]
    for k, (start, end) in enumerate(zip(points, points[1:] + points[:1])):
        axis.plot([start[1], end[1]], [start[0], end[0]], color=colour(view.effects.get(f'wall-{k}')), lw=4,
                  solid_capstyle='round', zorder=1)
    centre = np.mean(points, axis=0)
    axis.scatter([centre[1]], [centre[0]], marker='+', s=80, color=colour(view.effects.get('room')), zorder=2)
    entities = {e['id']: e for e in (scene.get('humans') or []) + (scene.get('objects') or [])}
    for a, b in sorted({(min(s, t), max(s, t)) for s, t, _ in scene.get('links') or () if s != t}):
        (xa, ya), (xb, yb) = (to_rep103(entities[i]['xPos'], entities[i]['yPos']) for i in (a, b))
        axis.plot([ya, yb], [xa, xb], ls='--', lw=2, color=colour(view.effects.get(f'{a}-{b}')), zorder=2)
    for kind, marker in (('objects', 's'), ('humans', 'o')):
        for entity in scene.get(kind) or []:
            x, y = to_rep103(entity['xPos'], entity['yPos'])
            axis.scatter([y], [x], marker=marker, s=140, color=colour(view.effects.get(entity['id'])),
                         edgecolor='black', zorder=3)
            if kind == 'humans':
                yaw = heading_yaw(entity['orientation'])
                axis.annotate('', xy=(y + 0.45 * np.sin(yaw), x + 0.45 * np.cos(yaw)), xytext=(y, x),
                              arrowprops={'arrowstyle': '->', 'lw': 1.5}, zorder=4)
    axis.scatter([0], [0], marker='^', s=160, color='tab:blue', edgecolor='black', zorder=5, label='robot')
    if view.poses:
        scores = dict(view.ranking)
        low, high = min(scores.values()), max(scores.values())
        for rank, (name, score) in enumerate(view.ranking, 1):
            x, y = view.poses[name]
            shade = 0.5 if high <= low else (score - low) / (high - low)
            axis.scatter([y], [x], marker='*' if rank == 1 else 'D', s=260 if rank == 1 else 60,
                         color=(1 - shade, 0.2 + 0.6 * shade, 0.1), edgecolor='black', zorder=6)
            axis.annotate(str(rank), (y, x), textcoords='offset points', xytext=(6, 6), fontsize=8, zorder=7)
    if listed:
        lines = [f'{rank}. {name} {score:.4f}' for rank, (name, score) in enumerate(view.ranking, 1)]
        axis.text(0.02, 0.02, '\n'.join(lines), transform=axis.transAxes, fontsize=7, va='bottom',
                  family='monospace', bbox={'facecolor': 'white', 'alpha': 0.8, 'edgecolor': 'none'}, zorder=8)
    axis.set_title(title, fontsize=10)
    axis.set_aspect('equal')
    axis.invert_xaxis()  # y (left) to the left, as seen from above
    axis.set_xlabel('y (m, left)')
    axis.set_ylabel('x (m, forward)')
    axis.grid(alpha=0.3)


def plot_people(predictor, scene: dict, users: list, path: Path, placements: int = 0, action: str | None = None,
                title: str = '') -> Path:
    """Draw ``scene`` for each of ``users`` (one panel each, ``person_view``) into the PNG ``path``."""
    plt = pyplot()
    from matplotlib.colors import TwoSlopeNorm

    views = [person_view(predictor, user, scene, placements, action) for user in users]
    largest = max((abs(e) for v in views for e in v.effects.values()), default=0.0) or 1e-9
    norm, cmap = TwoSlopeNorm(0.0, -largest, largest), plt.get_cmap('RdYlGn')

    def colour(effect):
        return 'lightgrey' if effect is None else cmap(norm(effect))
    figure, axes = plt.subplots(1, len(views), figsize=(5.2 * len(views) + 1.2, 5.8), squeeze=False,
                                layout='constrained')
    for axis, view in zip(axes[0], views):
        best = view.ranking[0]
        _draw(axis, scene, view, colour, f'{view.user}: best {best[0]} ({best[1]:.4f})')
    bar = figure.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=list(axes[0]), shrink=0.8)
    bar.set_label("removal effect on the person's best score (green: it raises it)")
    if title:
        figure.suptitle(title, fontsize=11)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def question_png(scene: dict, placement: dict | None = None) -> bytes:
    """``scene`` drawn as in ``plot_people`` without a model (the touchscreen page's picture of
    a question): with ``placement`` (the candidate scene asked about) its robot pose is marked
    by a star. PNG bytes."""
    import io

    plt = pyplot()
    poses = {'asked': to_rep103(*robot_pose_in(scene, placement)[:2])} if placement is not None else {}
    view = PersonView('', [('asked', 1.0)] if poses else [], poses, {})
    figure, axis = plt.subplots(figsize=(4.8, 4.8), layout='constrained')
    _draw(axis, scene, view, lambda effect: 'lightgrey', '', listed=False)
    buffer = io.BytesIO()
    figure.savefig(buffer, format='png', dpi=100)
    plt.close(figure)
    return buffer.getvalue()
