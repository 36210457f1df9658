"""The models one protocol run trains and scores (``model_specs``): the baselines, each
backbone in its variants, and the ablations of StARS.

An ablation follows its StARS model: it takes that model's choice in each fold, so that it
differs from it in one part only. ``holdout_recipe`` needs no fit of its own: it is the
recipe's hold-out fit (``personalisation.recipe.Recipe.holdout``, on the rows less a seeded
tenth of each person's examples) with the prior it makes, the model the recipe before the
refit shipped, scored in its served form on the same test rows by the fit of the model it
follows; MF, which the recipe fits the same way (a prior, so a hold-out fit), gets the same
row where the run has MF.
"""
from __future__ import annotations

import itertools
import json
from dataclasses import dataclass, field

from stars_ros.evaluation import peers

BASELINES = ('population_mean', 'mf', *peers.PEERS)
DISPLAY = {'gcn': 'GCN', 'gin': 'GIN', 'graphsage': 'GraphSAGE', 'ggnn': 'GGNN', 'rgcn': 'RGCN',
           'gat': 'GAT', 'mlp': 'MLP', 'resmlp': 'ResMLP', 'dcnv2': 'DCNv2', 'graceae': 'GraceAE',
           'fttransformer': 'FT-Transformer'}
BASELINE_LABELS = {'population_mean': 'Population mean', 'mf': 'MF (biased, no content)', **peers.LABELS}
#: Peer libraries with a search space of their own (``peers.SETTINGS``); myfm_encoder follows base.
PEER_FAMILIES = ('surprise_svd', 'myfm')
#: The ablation scored from its model's own fit: the recipe's hold-out fit (module docstring).
HOLDOUT_RECIPE = 'holdout_recipe'
HOLDOUT_SUFFIX = 'hold-out recipe (fit on 90 %, its own prior)'
#: StARS ablations: label suffix and the settings that differ from full StARS (they win over
#: the settings it chose; ``stars_point`` is StARS as chosen with the posterior head off,
#: ``stars_prior_stranger`` with strangers served the prior's mean, never the plain encoder).
ABLATIONS = {
    'user_bias': ('user offsets only', {'variant': 'user_bias'}),
    'base_user_bias': ('base + user offset', {'variant': 'base_user_bias'}),
    'stars_no_q': ('StARS without q_i', {'variant': 'stars_no_q'}),
    'stars_no_residual': ('StARS without the h_i residual', {'variant': 'stars_no_residual'}),
    'stars_prefix': ('StARS, items keyed by prefix', {'item_key': 'prefix'}),
    'stars_point': ('StARS, trained point estimate (no posterior head)', {'posterior_sweeps': 0}),
    'stars_prior_stranger': ("StARS, strangers served the prior's mean", {'strangers': 'prior_mean'}),
    HOLDOUT_RECIPE: (f'StARS, {HOLDOUT_SUFFIX}', {}),
}


@dataclass(frozen=True)
class ModelSpec:
    label: str
    backbone: str | None
    variant: str            # 'base', 'stars', 'mf', 'population_mean' or an ablation's variant
    family: str = ''        # whose search space: FAMILIES, or '' for a follower / the mean
    model: dict = field(default_factory=dict)  # model settings that differ (an ablation's)
    follows: str | None = None  # label of the spec whose per-fold choice this one takes
    from_holdout: bool = False  # scored by the fit of ``follows``: its recipe's hold-out fit


def model_specs(config) -> list[ModelSpec]:
    """Baselines first, then each backbone in its variants (the paper's row order) and its
    ablations, for a ``protocol.ProtocolConfig``."""
    specs = []
    for baseline in BASELINES:
        if baseline in config.baselines and baseline in BASELINE_LABELS:
            label = BASELINE_LABELS[baseline]
            family = baseline if baseline in ('mf', *PEER_FAMILIES) else ''
            specs.append(ModelSpec(label, None, baseline, family))
            if baseline == 'mf' and HOLDOUT_RECIPE in config.ablations:
                specs.append(ModelSpec(f'{label}, {HOLDOUT_SUFFIX}', None, 'mf', follows=label,
                                       from_holdout=True))
    for backbone in config.backbones:
        name = DISPLAY.get(backbone, backbone)
        for variant in ('base', 'stars'):
            if variant in config.variants:
                specs.append(ModelSpec(f"{name} {'StARS' if variant == 'stars' else 'base'}", backbone, variant,
                                       variant))
        if 'myfm_encoder' in config.baselines and 'base' in config.variants:
            specs.append(ModelSpec(peers.encoder_label(name), backbone, 'myfm_encoder', follows=f'{name} base'))
        if backbone in config.ablation_backbones:
            for ablation in config.ablations:
                suffix, model = ABLATIONS[ablation]
                specs.append(ModelSpec(f'{name} {suffix}', backbone, model.get('variant', 'stars'), '',
                                       {k: v for k, v in model.items() if k != 'variant'}, f'{name} StARS',
                                       ablation == HOLDOUT_RECIPE))
    return specs


def settings_candidates(config, spec: ModelSpec) -> list[dict]:
    """The search space of ``spec``'s family as a list of settings (one empty: no search)."""
    space = config.search.get(spec.family, {}) if spec.family else {}
    return [dict(zip(space, values)) for values in itertools.product(*space.values())]


def candidates(config, spec: ModelSpec) -> list[tuple[dict, tuple[int, int]]]:
    """(settings, (T1, T2)) worth trying; a content-free model skips pre-training, so only
    distinct T2 matter to it."""
    if spec.variant in PEER_FAMILIES:  # no epochs to choose
        pairs = [(0, 0)]
    elif spec.variant == 'mf':
        pairs = list(dict.fromkeys((0, t2) for _, t2 in config.grid))
    else:
        pairs = list(dict.fromkeys(config.grid))
    return [(settings, pair) for settings in settings_candidates(config, spec) for pair in pairs]


def settings_key(settings: dict) -> str:
    """A candidate's settings as canonical text (records, resume keys, tables)."""
    return json.dumps(settings, sort_keys=True)
