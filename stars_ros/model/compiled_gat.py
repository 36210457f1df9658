"""The whole GAT encoder as one compiled function (numba), GAT's serving form.

Scoring one scene of ~20 nodes through numpy array calls would pay each call's fixed cost
about ninety times (projections, per-head attention, softmax, readout); compiled, the same
arithmetic runs in one call over the scene's edge list (no padding). docs/performance.md
gives what it buys, measured, with the results file. Training keeps PyG's sparse form;
``test/model/test_dense_encoders.py`` checks the kernel against it.

numba caches the machine code beside this file (or in its user cache where that is not
writable): the first process compiles for a few seconds, later ones load it in under a
second. ``GATKernel`` runs it once when built, so a node pays that while loading its
checkpoint, never on a request.
"""
from __future__ import annotations

from typing import Sequence

import numba
import numpy as np

from stars_ros.data.placements import SceneBatch
from stars_ros.data.scene_graph import SceneGraph


@numba.njit(cache=True)
def _leaky_relu(value, slope):
    return value if value > 0 else slope * value


@numba.njit(cache=True)
def _gat_encode(x, node_starts, edge_source, edge_target, project_w, project_b, layer_w, attention_source,
                attention_target, layer_b, slope, hidden_w, hidden_b, output_w, output_b):
    """h [graphs, out_dim] of graphs stacked in ``x`` [nodes, features] (graph g owns rows
    node_starts[g]:node_starts[g + 1]); edges index rows of ``x``. Layer weights are stacked:
    ``layer_w`` [layers, hidden, hidden], attention [layers, heads, channels]."""
    nodes, hidden = x.shape[0], project_w.shape[1]
    layers, heads, channels = attention_source.shape
    # incoming edges grouped by target (counting sort): rows first[i]:first[i + 1] of sources
    first = np.zeros(nodes + 1, dtype=np.int64)
    for target in edge_target:
        first[target + 1] += 1
    first = np.cumsum(first)
    sources = np.empty(edge_source.shape[0], dtype=np.int64)
    filled = first[:-1].copy()
    for e in range(edge_source.shape[0]):
        sources[filled[edge_target[e]]] = edge_source[e]
        filled[edge_target[e]] += 1

    # large arrays are made once and updated in place: a fresh one per step cost more than its arithmetic
    h = x @ project_w
    for n in range(nodes):
        for c in range(hidden):
            h[n, c] = max(h[n, c] + project_b[c], np.float32(0.0))
    values = np.empty((nodes, hidden), dtype=np.float32)
    score_source = np.empty((nodes, heads), dtype=np.float32)
    score_target = np.empty((nodes, heads), dtype=np.float32)
    attended = np.empty(channels, dtype=np.float32)
    logits = np.empty(edge_source.shape[0], dtype=np.float32)  # of the incoming edges of one target
    for layer in range(layers):
        np.dot(h, layer_w[layer], values)  # [nodes, heads * channels]: the layer's input, kept as h changes
        for n in range(nodes):
            for k in range(heads):
                s, t = np.float32(0.0), np.float32(0.0)
                for c in range(channels):
                    s += values[n, k * channels + c] * attention_source[layer, k, c]
                    t += values[n, k * channels + c] * attention_target[layer, k, c]
                score_source[n, k], score_target[n, k] = s, t
        for i in range(nodes):
            for k in range(heads):
                # softmax over the sources of i: its own self loop (GATConv adds one), then its
                # incoming edges, each parallel edge a term of its own
                own = _leaky_relu(score_target[i, k] + score_source[i, k], slope)
                largest = own
                for e in range(first[i], first[i + 1]):
                    logits[e] = _leaky_relu(score_target[i, k] + score_source[sources[e], k], slope)
                    largest = max(largest, logits[e])
                weight = np.exp(own - largest)
                normaliser = weight
                for c in range(channels):
                    attended[c] = weight * values[i, k * channels + c]
                for e in range(first[i], first[i + 1]):
                    weight = np.exp(logits[e] - largest)
                    normaliser += weight
                    for c in range(channels):
                        attended[c] += weight * values[sources[e], k * channels + c]
                for c in range(channels):  # residual, as GraphEncoder.forward
                    update = attended[c] / normaliser + layer_b[layer, k * channels + c]
                    h[i, k * channels + c] += max(update, np.float32(0.0))

    graphs = node_starts.shape[0] - 1
    state = np.empty((graphs, 2 * hidden), dtype=np.float32)  # [robot node, mean over nodes]
    for g in range(graphs):
        start, stop = node_starts[g], node_starts[g + 1]
        state[g, :hidden] = h[start]
        for c in range(hidden):
            total = np.float32(0.0)
            for n in range(start, stop):
                total += h[n, c]
            state[g, hidden + c] = total / np.float32(stop - start)
    return np.maximum(state @ hidden_w + hidden_b, np.float32(0.0)) @ output_w + output_b


def _stacked(graphs: Sequence[SceneGraph]) -> tuple:
    """(x, node_starts, edge_source, edge_target) of ``graphs`` as one disjoint graph, always
    as contiguous float32 / int64 arrays: numba compiles once per layout, and the warm-up in
    ``GATKernel`` must have compiled the one every request uses."""
    if isinstance(graphs, SceneBatch):  # scenes of one layout (a placement map's): stacked without a loop
        x, node_starts, edges = graphs.stacked()
    elif len(graphs) == 1:  # the serving case: no copies
        graph = graphs[0]
        x, node_starts, edges = graph.x, np.array([0, graph.num_nodes]), graph.edge_index
    else:
        node_starts = np.concatenate([[0], np.cumsum([g.num_nodes for g in graphs])])
        edges = np.concatenate([g.edge_index + start for g, start in zip(graphs, node_starts)], axis=1)
        x = np.concatenate([g.x for g in graphs])
    return (np.ascontiguousarray(x, dtype=np.float32), np.ascontiguousarray(node_starts, dtype=np.int64),
            np.ascontiguousarray(edges[0], dtype=np.int64), np.ascontiguousarray(edges[1], dtype=np.int64))


class GATKernel:
    """``GAT``'s encoder over a snapshot of its weights: a function of a list of
    ``SceneGraph`` (or a ``placements.SceneBatch``) returning h [graphs, out_dim] (float32). Built
    from arrays laid out as ``x @ w + b`` multiplies them (see ``GAT.serving_form``)."""

    def __init__(self, project: tuple, layer_weights: list, attention_source: list, attention_target: list,
                 layer_biases: list, slope: float, hidden_layer: tuple, output_layer: tuple):
        def f32(array):
            return np.ascontiguousarray(array, dtype=np.float32)

        self._weights = (f32(project[0]), f32(project[1]), f32(np.stack(layer_weights)),
                         f32(np.stack(attention_source)), f32(np.stack(attention_target)),
                         f32(np.stack(layer_biases)), np.float32(slope),
                         f32(hidden_layer[0]), f32(hidden_layer[1]), f32(output_layer[0]), f32(output_layer[1]))
        features = self._weights[0].shape[0]
        self(  # compile (or load the cached machine code) now, not on the first request
            [SceneGraph(np.zeros((1, features), np.float32), np.zeros((2, 0), np.int64), np.zeros(0, np.int64))])

    def __call__(self, graphs: Sequence[SceneGraph]) -> np.ndarray:
        return _gat_encode(*_stacked(graphs), *self._weights)
