"""How faithful the removal effects of ``model.explain`` are, and how they compare with PyTorch
Geometric's GNNExplainer, on scenes a model never trained on (ROS-free; graph models).

* **Faithfulness**: does removing the entity with the largest |effect| change the score more
  than removing another entity of the same scene, drawn at random? (The effect *is* that
  change, so for removal effects this fails only on ties; the question bites for an explainer
  that attributes otherwise, GNNExplainer here.)
* **Interaction share**: the effect of removing every entity at once (the robot alone left)
  against the sum of the single-entity effects: (all − Σ single) / |all|.
* **GNNExplainer**: a node mask learned to keep the score (``torch_geometric.explain``,
  regression, graph level); its Spearman rank agreement with |removal effect| over the
  entities, the faithfulness of its top entity, and milliseconds per scene for both.
"""
from __future__ import annotations

import time

import numpy as np
import torch
from scipy.stats import spearmanr

from stars_ros.data.scene_graph import SceneGraph, featurise
from stars_ros.data.scene_store import GraphBatch
from stars_ros.model.explain import removal_effects, score_parts
from stars_ros.model.vocabulary import UNKNOWN


def held_out_scenes(data, train_rows: np.ndarray, test_rows: np.ndarray) -> list:
    """(scene row, user) of every scene none of whose ratings is in ``train_rows``, with the
    first user who rated it in ``test_rows``."""
    trained = set(data.scenes[train_rows].tolist())
    found = {}
    for row in test_rows:
        scene = int(data.scenes[row])
        if scene not in trained:
            found.setdefault(scene, str(data.users[row]))
    return sorted(found.items())


def robot_only(graph: SceneGraph) -> SceneGraph:
    """``graph`` with every entity removed: the robot's node alone, no edges."""
    return SceneGraph(x=graph.x[:1], edge_index=np.zeros((2, 0), dtype=np.int64),
                      edge_type=np.zeros(0, dtype=np.int64))


def _beats_random(changes: np.ndarray, top: int) -> float:
    """The chance that removing entity ``top`` changes the score more (|change|) than removing
    another entity of the scene drawn uniformly."""
    others = np.delete(np.abs(changes), top)
    return float(np.mean(abs(changes[top]) > others)) if len(others) else float('nan')


def faithfulness(predictor, scenes: list, users: list, column: int) -> dict:
    """Per scene (JSON dicts, each with its user): the removal effects on action ``column``, the
    chance the top-|effect| entity beats a random other one, and the interaction share."""
    beats, shares, singles, alls, ms = [], [], [], [], []
    for scene, user in zip(scenes, users):
        started = time.perf_counter()
        (_, effects), = removal_effects(predictor, user, [scene])
        ms.append((time.perf_counter() - started) * 1e3)
        effects = effects[:, column]
        graph = featurise(scene, validate=False)
        h = predictor.inference.encode([graph, robot_only(graph)], 2)
        unclipped = score_parts(predictor, user, h, np.full(2, UNKNOWN), np.full(2, column)).sum(0)  # as effects are
        everything = float(unclipped[0] - unclipped[1])
        if len(effects):
            beats.append(_beats_random(effects, int(np.argmax(np.abs(effects)))))
        singles.append(float(effects.sum()))
        alls.append(everything)
        shares.append((everything - float(effects.sum())) / abs(everything) if everything else float('nan'))
    shares = np.array(shares)
    return {'scenes': len(scenes), 'top_beats_random': float(np.nanmean(beats)),
            'interaction_share_median': float(np.nanmedian(shares)),
            'interaction_share_abs_median': float(np.nanmedian(np.abs(shares))),
            'interaction_share_quartiles': [float(q) for q in np.nanpercentile(shares, [25, 75])],
            'sum_of_single_effects_median': float(np.median(singles)),
            'effect_of_removing_all_median': float(np.median(alls)),
            'removal_ms_per_scene_p50': float(np.median(ms))}


class _ScoreOf(torch.nn.Module):
    """The unclipped rating-scale score of one user and one action for one graph, as a function
    of its node features (what GNNExplainer masks)."""

    def __init__(self, model, predictor, user, column: int, edge_type: torch.Tensor):
        super().__init__()
        self.model, self.column, self.edge_type = model, column, edge_type
        theta = predictor.user_theta(user) if model.personalised else None
        self.user_rows = None if theta is None else (torch.tensor(theta[:-1], dtype=torch.float32)[None],
                                                     torch.tensor([[theta[-1]]], dtype=torch.float32))

    def forward(self, x, edge_index):
        graphs = GraphBatch(x=x, edge_index=edge_index, edge_type=self.edge_type,
                            batch=torch.zeros(len(x), dtype=torch.long), root=torch.zeros(1, dtype=torch.long),
                            num_graphs=1)
        h = self.model.encode(graphs)
        z = self.model(torch.zeros(1, dtype=torch.long), torch.full((1,), UNKNOWN), h, self.user_rows)
        return self.model.to_rating_scale(z)[:, self.column]


def compare_gnnexplainer(predictor, model, scenes: list, users: list, column: int, epochs: int = 100,
                         seed: int = 0) -> dict:
    """GNNExplainer's node mask against the removal effects on ``scenes``: Spearman ρ with
    |effect| over each scene's entities, how often its top entity beats a random other one
    (judged by the removal effects: what removing it does), and ms per scene for each."""
    from torch_geometric.explain import Explainer, GNNExplainer

    model.eval()
    rhos, beats, gnn_ms, removal_ms, same_top = [], [], [], [], []
    for k, (scene, user) in enumerate(zip(scenes, users)):
        started = time.perf_counter()
        (_, effects), = removal_effects(predictor, user, [scene])
        removal_ms.append((time.perf_counter() - started) * 1e3)
        effects = effects[:, column]
        graph = featurise(scene, validate=False)
        torch.manual_seed(seed + k)
        explainer = Explainer(_ScoreOf(model, predictor, user, column, torch.from_numpy(graph.edge_type)),
                              algorithm=GNNExplainer(epochs=epochs), explanation_type='model',
                              node_mask_type='object', edge_mask_type=None,
                              model_config={'mode': 'regression', 'task_level': 'graph', 'return_type': 'raw'})
        started = time.perf_counter()
        explanation = explainer(torch.from_numpy(graph.x), torch.from_numpy(graph.edge_index))
        gnn_ms.append((time.perf_counter() - started) * 1e3)
        mask = explanation.node_mask.detach().numpy().ravel()[1:1 + len(effects)]  # node 0: the robot
        if len(effects) > 2:
            rho = spearmanr(mask, np.abs(effects)).statistic
            if np.isfinite(rho):
                rhos.append(float(rho))
        if len(effects) > 1:
            top = int(np.argmax(mask))
            beats.append(_beats_random(effects, top))
            same_top.append(top == int(np.argmax(np.abs(effects))))
    return {'scenes': len(scenes), 'epochs': epochs,
            'spearman_with_removal_median': float(np.median(rhos)), 'spearman_with_removal_mean': float(np.mean(rhos)),
            'spearman_scenes': len(rhos), 'same_top_entity': float(np.mean(same_top)),
            'gnnexplainer_top_beats_random': float(np.mean(beats)),
            'gnnexplainer_ms_per_scene_p50': float(np.median(gnn_ms)),
            'removal_ms_per_scene_p50': float(np.median(removal_ms))}
