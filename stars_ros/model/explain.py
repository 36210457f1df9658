"""Why a score is what it is: its exact parts, and what each entity of the scene does to it.

StARS' score is a sum, so it splits exactly, on the rating scale (z × σ_a + μ_a):

* ``content``  = (h_iᵀ r_a + b) σ_a + μ_a — what the scene's content says for anybody
  (h_iᵀ r_a only in residual variants; a model without users puts its whole score here);
* ``personal`` = ((p_u ⊙ (q_i + h_i))ᵀ r_a + b_u) σ_a — what this person adds; a stranger is
  scored with the personalisation prior's mean, so theirs is the population's (``personal_from``);
  on a checkpoint that serves people it was not trained on around its plain encoder
  (``model.strangers``, ``Predictor.hands_over``) ``content`` is that encoder's score and
  ``personal`` their departure from the prior's mean, σ_a xᵀ(θ_u − θ₀): 0 for a stranger
  (``personal_from`` 'base_encoder') until ratings are folded in;
* ``scene``    = b_i σ_a — the identity offset of a scene seen in training (0 for a new one;
  q_i acts only through p_u, so it is in ``personal``).

The parts sum to the unclipped score; a published score is clipped to the rating scale, so
a clipped entry is one whose parts sum outside it. Entity effects are removal effects:
the unclipped score minus the score without the entity (its node and edges removed and the
scene encoded again; for tabular scenes the feature set to the training mean), every variant
of a request's scenes in one encoder pass. They are exact for what they ask, and cost one
batched forward pass (``docs/explanations.md``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stars_ros.data.scene_graph import SceneGraph, entity_nodes, featurise, without_node
from stars_ros.errors import StarsError
from stars_ros.model.vocabulary import UNKNOWN


@dataclass(frozen=True)
class Why:
    """One ranked entry's explanation: its score's parts on the rating scale, where the
    personal part comes from ('trained', 'folded_in', 'prior': a stranger, or 'none': a
    model without users; 'base_encoder': a stranger scored by the plain encoder), and the
    entities ((id, kind, effect), largest |effect| first)."""

    content: float
    personal: float
    scene: float
    personal_from: str
    entities: tuple = ()


def personal_source(predictor, user_id) -> str:
    """Where ``user_id``'s p_u, b_u come from (see ``Why``)."""
    if not predictor.inference.personalised:
        return 'none'
    if predictor.serves_stranger_encoder(user_id):
        return 'base_encoder'
    if predictor.user_model(user_id) is not None:
        return 'folded_in'
    return 'trained' if predictor.knows_user(user_id) else 'prior'


def score_parts(predictor, user_id, h: np.ndarray, scene_rows: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """(content, personal, scene) [3, R] (float64, rating scale) of one (scene, action) per
    row: ``h`` [R, dim], ``scene_rows`` [R] (UNKNOWN for new scenes), ``actions`` [R] columns."""
    inference = predictor.inference
    sd, mean = inference.target_std[actions], inference.target_mean[actions]
    h = np.asarray(h, dtype=np.float64)
    if not inference.personalised:
        scores = inference.scores(h, None, scene_rows)[np.arange(len(h)), actions]
        return np.stack([scores, np.zeros(len(h)), np.zeros(len(h))])
    theta = predictor.user_theta(user_id)
    q, scene_offset = inference.scene_terms(np.asarray(scene_rows))
    r = inference.action_rows[actions].astype(np.float64)
    content = (h * r).sum(1) if inference.residual else np.zeros(len(h))
    personal = (theta[:-1] * (np.asarray(q, dtype=np.float64) + h) * r).sum(1) + theta[-1]
    scene = np.broadcast_to(np.asarray(scene_offset, dtype=np.float64), (len(h),))
    return np.stack([(content + inference.bias) * sd + mean, personal * sd, scene * sd])


def scene_entities(predictor, scene) -> list:
    """(id, kind, index) of what can be removed from ``scene``: graph nodes (``entity_nodes``)
    or, for a tabular row, each feature (id: its column)."""
    if predictor.input_kind == 'graph':
        if isinstance(scene, SceneGraph):
            raise StarsError("explaining a scene needs its content (a scene-graph dict): a data set's scene id gives "
                             'only its featurised graph, which names no entities')
        return entity_nodes(scene)
    return [(column, 'feature', column) for column in range(len(scene))]


def _variants(predictor, scene, entities) -> list:
    """``scene`` without each of ``entities``, in the encoder's input form."""
    if predictor.input_kind == 'graph':
        graph = scene if isinstance(scene, SceneGraph) else featurise(scene, validate=False)
        return [graph] + [without_node(graph, node) for _, _, node in entities]
    reference = predictor.served.feature_mean
    rows = np.repeat(np.asarray(scene, dtype=np.float32)[None], len(entities) + 1, axis=0)
    for k, (_, _, column) in enumerate(entities, 1):
        rows[k, column] = reference[column]
    return list(rows)


def removal_effects(predictor, user_id, scenes, scene_ids=None) -> list:
    """Per scene of ``scenes`` (graph dicts or feature rows): (entities, effects [entities,
    actions]) with effect = unclipped score − unclipped score without the entity, for
    ``user_id``; ``scene_ids`` (optional) name training scenes. One encoder pass for all."""
    entities = [scene_entities(predictor, scene) for scene in scenes]
    inputs = [v for scene, found in zip(scenes, entities) for v in _variants(predictor, scene, found)]
    encoded = inputs if predictor.input_kind == 'graph' else np.stack(inputs)
    if predictor.serves_stranger_encoder(user_id):  # the plain encoder alone: no StARS pass
        scores = predictor.stranger_scores(encoded, len(inputs))
    else:
        h = predictor.inference.encode(encoded, len(inputs))
        rows = (np.full(len(scenes), UNKNOWN) if scene_ids is None
                else predictor.scene_rows(list(scene_ids)))
        scores = predictor.unclipped_scores(user_id, encoded, h, np.repeat(rows,
                                                                           [len(found) + 1 for found in entities]))
    results, start = [], 0
    for found in entities:
        block = scores[start:start + len(found) + 1]
        results.append((found, block[0] - block[1:]))
        start += len(found) + 1
    return results


def explain(predictor, user_id, h: np.ndarray, scene_rows: np.ndarray, actions: np.ndarray,
            entity_effects: list, top_entities: int, served: np.ndarray | None = None) -> list:
    """``Why`` of each (scene, action) row: ``h`` [R, dim], ``scene_rows`` [R], ``actions`` [R],
    and per row (entities, effects [entities]) of ``removal_effects``, cut to the
    ``top_entities`` largest |effect| (all with 0). ``served`` [R]: the unclipped scores of one
    ``Predictor.hands_over``: the plain encoder's score (content) plus their departure (personal)."""
    source = personal_source(predictor, user_id)
    if predictor.hands_over(user_id):
        personal = predictor.departure(user_id, h, scene_rows)[np.arange(len(h)), actions]
        parts = np.stack([np.asarray(served, dtype=np.float64) - personal, personal, np.zeros(len(h))])
    else:
        parts = score_parts(predictor, user_id, h, scene_rows, actions)
    whys = []
    for k, (found, effects) in enumerate(entity_effects):
        order = sorted(range(len(found)), key=lambda e: (-abs(effects[e]), e))
        order = order[:top_entities] if top_entities else order
        whys.append(Why(float(parts[0, k]), float(parts[1, k]), float(parts[2, k]), source,
                        tuple((found[e][0], found[e][1], float(effects[e])) for e in order)))
    return whys
