"""Experiment configuration as frozen pydantic models: read from YAML, stored in checkpoints.

Every section says its keys, types and ranges once. Unknown keys are refused, so that a
typo in a YAML file never silently falls back to a default; a missing key takes its
default (a checkpoint written before a key existed still loads). Numbers are strict: an
integer setting refuses ``'64'`` and ``64.7``, a float setting refuses text. Every error
names the file and the dotted key, e.g. ``config/socnav1_gat.yaml: training.lr: Input
should be a valid number, got 'fast'``.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationError, field_validator, model_validator

from stars_ros.errors import ConfigError, KeyedError

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
#: What a person with no ratings is served (``ModelConfig.strangers``).
STRANGER_SERVING = ('prior_mean', 'base_encoder')
#: Strict numbers: an int field refuses '64', 64.7 and True; a float field refuses text
#: (an int is a float), NaN and infinities.
Int = Annotated[int, Strict()]
Float = Annotated[float, Strict(), Field(allow_inf_nan=False)]


# -- errors -------------------------------------------------------------------------------
def _key(loc) -> str:
    text = ''
    for part in loc:
        text += f'[{part}]' if isinstance(part, int) else (f'.{part}' if text else str(part))
    return text


def _allowed(model: type[BaseModel] | None, path) -> list | None:
    """The keys of the model found at ``path`` below ``model`` (None if not a model)."""
    for part in path:
        field = model.model_fields.get(part) if model is not None else None
        annotation = getattr(field, 'annotation', None)
        model = annotation if isinstance(annotation, type) and issubclass(annotation, BaseModel) else None
    return list(model.model_fields) if model is not None else None


def _messages(error: ValidationError, model: type[BaseModel] | None, prefix: tuple = ()) -> list[str]:
    """One ``dotted.key: message`` line per error of ``error`` (raised by ``model``)."""
    lines, items = [], error.errors(include_url=False)
    deeper = [item['loc'] for item in items]
    for item in items:
        loc, message, kind = prefix + tuple(item['loc']), item['msg'], item['type']
        if kind == 'too_short' and any(len(other) > len(item['loc']) and other[:len(item['loc'])] == item['loc']
                                       for other in deeper):
            continue  # a sequence left short by its invalid items: those items are reported
        given = item.get('input')
        cause = (item.get('ctx') or {}).get('error')
        if isinstance(cause, KeyedError):
            if isinstance(cause.detail, ValidationError):
                lines += _messages(cause.detail, cause.model, loc + cause.loc)
                continue
            loc, message = loc + cause.loc, str(cause.detail)
        elif kind in ('value_error', 'assertion_error'):
            message = str(cause) if cause is not None else message.split(', ', 1)[-1]
        elif kind == 'extra_forbidden':
            allowed = _allowed(model, item['loc'][:-1])
            message = 'unknown key' + (f"; allowed: {', '.join(allowed)}" if allowed else '')
        elif kind in ('model_type', 'model_attributes_type', 'dict_type'):
            message = f'expected a mapping, got {type(given).__name__}'
        elif kind == 'missing':
            message = 'item missing' if isinstance(loc[-1], int) else 'required key missing'
        elif loc and loc[-1] == '[key]':
            loc, message = loc[:-1], f'not an allowed key: {message}'
        if kind in _SHOW_INPUT:
            message += f', got {given!r}'
            if kind == 'float_type' and isinstance(given, str) and _is_number(given):
                message += ' (YAML reads 1e-3 as text: write 1.0e-3)'
        lines.append(f'{_key(loc)}: {message}' if loc else message)
    return lines


_SHOW_INPUT = {'int_type', 'float_type', 'bool_type', 'string_type', 'finite_number', 'literal_error',
               'greater_than', 'greater_than_equal', 'less_than', 'less_than_equal'}


def _is_number(text: str) -> bool:
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def validated(model: type[BaseModel], values, source=None, **context):
    """``model`` validated from ``values``; a ValidationError becomes a ConfigError whose
    lines read ``<source>: <dotted key>: <message>``."""
    try:
        return model.model_validate(values, context=context or None)
    except ValidationError as error:
        lines = _messages(error, model)
    head = f'{source}: ' if source is not None else ''
    raise ConfigError('\n'.join(head + line for line in lines))


def validate_under(loc: tuple, model: type[BaseModel], values):
    """Inside a validator: ``model`` validated from ``values``, its errors reported under
    ``loc`` (e.g. a protocol's ``('backbones', 'gcn')``)."""
    try:
        return model.model_validate(values)
    except ValidationError as error:
        raise KeyedError(loc, error, model) from None


def read_yaml(path) -> dict:
    """The mapping in the YAML file ``path`` ({} for an empty file)."""
    try:
        values = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as error:
        raise ConfigError(f'cannot read config {path}: {error}') from error
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise ConfigError(f'{path}: a config must be a mapping, got {type(values).__name__}')
    return values


class Section(BaseModel):
    """Base of every config model: immutable, unknown keys refused."""

    model_config = ConfigDict(extra='forbid', frozen=True)


# -- the sections -------------------------------------------------------------------------
class EncoderConfig(Section):
    """Scene encoder φθ: a registered backbone name and its sizes.

    ``options`` go to the backbone unchanged (e.g. ``heads`` for GAT and FT-Transformer).
    """

    name: str = 'gat'
    hidden: Annotated[Int, Field(ge=1)] = 64
    layers: Annotated[Int, Field(ge=1)] = 3
    dropout: Annotated[Float, Field(ge=0.0, lt=1.0)] = 0.0
    options: dict[str, Any] = Field(default_factory=dict)

    @field_validator('name')
    @classmethod
    def _registered(cls, name: str) -> str:
        from stars_ros.model.backbones import BACKBONES, normalise_name
        if normalise_name(name) not in BACKBONES:
            raise ValueError(f'unknown encoder {name!r}; registered: {", ".join(sorted(BACKBONES))}')
        return name


class ModelConfig(Section):
    """``variant``: ``base`` (encoder + linear head), ``stars`` (encoder fused with MF) or
    ``mf`` (biased matrix factorisation alone: StARS with h_i = 0, a content-free baseline).

    The other variants are ablations of StARS (``PARTS``), for evaluation.
    ``dim`` is the size of h_i and of the user, scene and action embeddings. ``item_key``
    names the data's keying of items for q_i and b_i (``RatingData.item_keys``).
    ``strangers`` says what a person with no ratings is served: ``prior_mean``, the model with
    the fold-in prior's mean as their row; or ``base_encoder``, the prediction of a plain
    encoder (the ``base`` variant, same settings, fitted on the same ratings beside the model
    and kept in its checkpoint), the fold-in taking over from a person's first rating.
    """

    variant: Literal[VARIANTS] = 'stars'
    dim: Annotated[Int, Field(ge=1)] = 64
    item_key: Literal[ITEM_KEYINGS] = 'identifier'
    strangers: Literal[STRANGER_SERVING] = 'prior_mean'

    @model_validator(mode='before')
    @classmethod
    def _base_serves_everyone_alike(cls, values):
        """``base`` serves everyone its one prediction, so ``strangers`` means nothing to it (a
        StARS config run as ``--variant base`` is the plain encoder, not an error)."""
        if isinstance(values, dict) and values.get('variant') == 'base':
            return {**values, 'strangers': 'prior_mean'}
        return values

    @property
    def parts(self) -> frozenset:
        """What the variant has of StARS (``PARTS``); ``base`` has only the content."""
        return PARTS.get(self.variant, frozenset({'content'}))


class TrainConfig(Section):
    """Two-step training: ``pretrain_epochs`` (T1) of encoder + temporary head, then
    ``joint_epochs`` (T2) of the whole model. AdamW defaults are the published ones.
    ``embedding_l2`` weighs the L2 penalty on the user and scene rows of each batch during
    joint training (0 leaves only AdamW's weight decay). ``posterior_sweeps`` > 0: after joint
    training, with the encoder frozen, a blocked Gibbs sampler with learned prior precisions
    runs that many sweeps over the factorisation part (user, scene and action rows and
    offsets) from the trained weights, and the fitted rows are the means of the draws after
    the first ``posterior_burn_in`` sweeps (``model.posterior``): a Bayesian head with myFM's
    edge, one model served at the same cost; 0 keeps the trained point estimate. Not for
    ``base``, which has no factorisation part. ``device`` is where ``fit`` trains ('cpu',
    'cuda' or 'cuda:N'); the fitted model comes back on the CPU, so checkpoints, fold-in and
    serving never see a GPU tensor."""

    pretrain_epochs: Annotated[Int, Field(ge=0)] = 10
    joint_epochs: Annotated[Int, Field(ge=0)] = 100
    batch_size: Annotated[Int, Field(ge=1)] = 256
    lr: Annotated[Float, Field(gt=0.0)] = 5e-5
    weight_decay: Annotated[Float, Field(ge=0.0)] = 1e-5
    grad_clip: Annotated[Float, Field(gt=0.0)] = 1.0
    embedding_l2: Annotated[Float, Field(ge=0.0)] = 0.0
    posterior_sweeps: Annotated[Int, Field(ge=0)] = 0
    posterior_burn_in: Annotated[Int, Field(ge=0)] = 50
    seed: Annotated[Int, Field(ge=0)] = 0
    threads: Annotated[Int, Field(ge=1)] = 1
    device: str = 'cpu'

    @field_validator('device')
    @classmethod
    def _device(cls, device: str) -> str:
        if not re.fullmatch(r'cpu|cuda(:\d+)?', device):
            raise ValueError(f"must be 'cpu', 'cuda' or 'cuda:N', got {device!r}")
        return device

    @model_validator(mode='after')
    def _burn_in_below_sweeps(self) -> 'TrainConfig':
        if self.posterior_sweeps and self.posterior_burn_in >= self.posterior_sweeps:
            raise ValueError(f'posterior_burn_in ({self.posterior_burn_in}) must be below posterior_sweeps '
                             f'({self.posterior_sweeps}): no draw would be kept')
        return self


class SplitConfig(Section):
    """Seeded random split of annotation rows into train and test."""

    test_fraction: Annotated[Float, Field(gt=0.0, lt=1.0)] = 0.2
    seed: Annotated[Int, Field(ge=0)] = 0


class ExperimentConfig(Section):
    encoder: EncoderConfig = Field(default_factory=EncoderConfig)
    model: ModelConfig = Field(default_factory=ModelConfig)
    training: TrainConfig = Field(default_factory=TrainConfig)
    split: SplitConfig = Field(default_factory=SplitConfig)

    @model_validator(mode='before')
    @classmethod
    def _empty_sections(cls, values):
        """A section written as an empty YAML key (``encoder:``) takes its defaults."""
        if isinstance(values, dict):
            return {key: {} if value is None and key in cls.model_fields else value for key, value in values.items()}
        return values

    @model_validator(mode='after')
    def _posterior_needs_factors(self) -> 'ExperimentConfig':
        if self.training.posterior_sweeps and self.model.variant == 'base':
            raise ValueError("training.posterior_sweeps: the 'base' variant has no factorisation part to sample")
        return self

    def stranger_encoder(self) -> 'ExperimentConfig':
        """The plain encoder with these settings (the ``base`` variant, as an evaluation's
        ``base`` row trains it): what strangers are served where ``model.strangers`` is
        'base_encoder'."""
        return self.replace(model={'variant': 'base'}, training={'posterior_sweeps': 0})

    def to_dict(self) -> dict:
        return self.model_dump()

    @classmethod
    def from_dict(cls, values: dict | None, source=None) -> 'ExperimentConfig':
        """Validate a mapping (a YAML file's, or a checkpoint's ``to_dict``); ``source``
        (e.g. the file) heads every error message."""
        if values is not None and not isinstance(values, dict):
            raise ConfigError(f'{source or "config"}: a config must be a mapping, got {type(values).__name__}')
        return validated(cls, values or {}, source)

    @classmethod
    def from_checkpoint(cls, values: dict, source=None) -> 'ExperimentConfig':
        """``from_dict`` of a checkpoint's config, less the training settings this version does
        not know: those of experiments that did not ship, which an older checkpoint may hold
        (what they did is in its weights and prior; serving never reads training settings).
        A YAML file naming one is refused, as any unknown key is."""
        if isinstance(values, dict) and isinstance(values.get('training'), dict):
            values = {**values, 'training': {key: value for key, value in values['training'].items()
                                             if key in TrainConfig.model_fields}}
        return cls.from_dict(values, source)

    @classmethod
    def from_yaml(cls, path) -> 'ExperimentConfig':
        return cls.from_dict(read_yaml(path), source=path)

    def replace(self, **sections) -> 'ExperimentConfig':
        """Copy with some sections changed, e.g. ``replace(model={'variant': 'base'})``."""
        values = self.to_dict()
        for name, changes in sections.items():
            values[name] = {**values.get(name, {}), **changes}
        return ExperimentConfig.from_dict(values)
