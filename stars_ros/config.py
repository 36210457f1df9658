"""Experiment configuration as frozen dataclasses: read from YAML, stored in checkpoints.

Unknown keys are refused so that a typo in a YAML file never silently falls back to a
default.
"""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from .errors import ConfigError

#: The parts of each personalised variant: ``content`` (h_i), ``p`` (p_u), ``q`` (q_i), the
#: offsets ``b_u`` and ``b_i``, and ``residual`` (the h_i added inside the final product).
#: ``base`` is the encoder with a linear head and has none of them.
PARTS = {
    'stars': frozenset({'content', 'p', 'q', 'b_u', 'b_i', 'residual'}),
    'mf': frozenset({'p', 'q', 'b_u', 'b_i'}),
    'user_bias': frozenset({'b_u'}),
    'base_user_bias': frozenset({'content', 'b_u', 'residual'}),
    'stars_no_q': frozenset({'content', 'p', 'b_u', 'b_i', 'residual'}),
    'stars_no_residual': frozenset({'content', 'p', 'q', 'b_u', 'b_i'}),
}
VARIANTS = ('base', *PARTS)
ITEM_KEYINGS = ('identifier', 'prefix')


def _build(cls, values, where):
    if values is None:
        return cls()
    if not isinstance(values, dict):
        raise ConfigError(f'{where}: expected a mapping, got {type(values).__name__}')
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ConfigError(f'{where}: unknown keys {unknown}; allowed: {sorted(names)}')
    return cls(**values)


@dataclass(frozen=True)
class EncoderConfig:
    """Scene encoder φθ: a registered backbone name and its sizes.

    ``options`` go to the backbone unchanged (e.g. ``heads`` for GAT and FT-Transformer).
    """

    name: str = 'gat'
    hidden: int = 64
    layers: int = 3
    dropout: float = 0.0
    options: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ModelConfig:
    """``variant``: ``base`` (encoder + linear head), ``stars`` (encoder fused with MF) or
    ``mf`` (biased matrix factorisation alone: StARS with h_i = 0, a content-free baseline).

    The other variants are ablations of StARS (``stars_ros.model.PARTS``), for evaluation.
    ``dim`` is the size of h_i and of the user, scene and action embeddings. ``item_key``
    names the data's keying of items for q_i and b_i (``RatingData.item_keys``).
    """

    variant: str = 'stars'
    dim: int = 64
    item_key: str = 'identifier'

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ConfigError(f"model.variant must be one of {list(VARIANTS)}, got '{self.variant}'")
        if self.dim < 1:
            raise ConfigError('model.dim must be positive')
        if self.item_key not in ITEM_KEYINGS:
            raise ConfigError(f"model.item_key must be one of {list(ITEM_KEYINGS)}, got '{self.item_key}'")


@dataclass(frozen=True)
class TrainConfig:
    """Two-step training: ``pretrain_epochs`` (T1) of encoder + temporary head, then
    ``joint_epochs`` (T2) of the whole model. AdamW defaults are the published ones.
    ``embedding_l2`` weighs the L2 penalty on the user and scene rows of each batch during
    joint training (0 leaves only AdamW's weight decay). ``device`` is where ``fit`` trains
    ('cpu', 'cuda' or 'cuda:N'); the fitted model comes back on the CPU, so checkpoints,
    fold-in and serving never see a GPU tensor."""

    pretrain_epochs: int = 10
    joint_epochs: int = 100
    batch_size: int = 256
    lr: float = 5e-5
    weight_decay: float = 1e-5
    grad_clip: float = 1.0
    embedding_l2: float = 0.0
    seed: int = 0
    threads: int = 1
    device: str = 'cpu'

    def __post_init__(self):
        if self.pretrain_epochs < 0 or self.joint_epochs < 0:
            raise ConfigError('epochs must be non-negative')
        if self.embedding_l2 < 0:
            raise ConfigError('embedding_l2 must be non-negative')
        if self.batch_size < 1 or self.lr <= 0 or self.threads < 1:
            raise ConfigError('batch_size, lr and threads must be positive')
        if not isinstance(self.device, str) or not re.fullmatch(r'cpu|cuda(:\d+)?', self.device):
            raise ConfigError(f"training.device must be 'cpu', 'cuda' or 'cuda:N', got {self.device!r}")


@dataclass(frozen=True)
class SplitConfig:
    """Seeded random split of annotation rows into train and test."""

    test_fraction: float = 0.2
    seed: int = 0

    def __post_init__(self):
        if not 0.0 < self.test_fraction < 1.0:
            raise ConfigError('split.test_fraction must lie in (0, 1)')


@dataclass(frozen=True)
class ExperimentConfig:
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    training: TrainConfig = field(default_factory=TrainConfig)
    split: SplitConfig = field(default_factory=SplitConfig)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> 'ExperimentConfig':
        sections = {'encoder': EncoderConfig, 'model': ModelConfig,
                    'training': TrainConfig, 'split': SplitConfig}
        top = values or {}
        if not isinstance(top, dict):
            raise ConfigError(f'config must be a mapping, got {type(top).__name__}')
        unknown = sorted(set(top) - set(sections))
        if unknown:
            raise ConfigError(f'unknown top-level keys {unknown}; allowed: {sorted(sections)}')
        try:
            return cls(**{name: _build(section, top.get(name), name) for name, section in sections.items()})
        except TypeError as error:
            raise ConfigError(str(error)) from error

    @classmethod
    def from_yaml(cls, path) -> 'ExperimentConfig':
        try:
            values = yaml.safe_load(Path(path).read_text())
        except (OSError, yaml.YAMLError) as error:
            raise ConfigError(f'cannot read config {path}: {error}') from error
        return cls.from_dict(values or {})

    def replace(self, **sections) -> 'ExperimentConfig':
        """Copy with some sections changed, e.g. ``replace(model={'variant': 'base'})``."""
        values = self.to_dict()
        for name, changes in sections.items():
            values[name] = {**values[name], **changes}
        return ExperimentConfig.from_dict(values)
