"""Exception hierarchy: the core raises these, nodes and CLIs catch them at their boundary."""
from __future__ import annotations


class StarsError(Exception):
    """Base class of every error stars_ros raises on purpose."""


class DataError(StarsError):
    """A dataset file is missing, malformed or inconsistent (the message names file and line)."""


class SceneGraphError(StarsError):
    """A scene graph does not follow msg_schemas/scene_graph.schema.json or has absurd values."""


class MessageError(StarsError):
    """A JSON message on a topic does not follow its schema."""


class UnknownActionError(StarsError):
    """A candidate action is not one the model was trained on."""


class CheckpointError(StarsError):
    """A checkpoint file is truncated, corrupted or incompatible with this version."""


class ConfigError(StarsError):
    """A configuration has unknown keys or invalid values."""


INSTALL_TRAIN = "pip install 'stars_ros[train]'"  # the extra of training, evaluation and tabular serving


class TrainExtraMissing(CheckpointError):
    """A checkpoint this install cannot serve: its tabular backbone runs on torch, which the
    serving install (``pip install stars_ros``) leaves out; the message names the extra."""


class TrainingDivergedError(StarsError):
    """Parameters became non-finite during training: lower the learning rate."""


class UnknownSceneError(StarsError):
    """A scene named by id is not in the data the ids are looked up in (give its content)."""


class NotFittedError(StarsError):
    """A model was asked to predict before fit() or load()."""


class BadMessage(MessageError):
    """A message the ranker refuses; ``kind`` is a short machine-readable category and
    ``scene_id`` the message's own scene id, when it has a usable one, so that the report
    on stars/errors can be matched to the request."""

    def __init__(self, kind: str, detail: str, scene_id: str | None = None):
        super().__init__(detail)
        self.kind = kind
        self.scene_id = scene_id


class BadMapRequest(BadMessage):
    """A placement map refused (``model.placement_map``): ``kind`` is ``too_large`` (more
    cells than it makes), ``non_finite``, ``schema`` (a value out of its range, an id too
    long), ``scene_graph`` (a scene the featuriser refuses) or ``model`` (one that reads no
    scene graphs), as the node reports its refusals on stars/errors."""


class NoQuestion(StarsError):
    """Nothing to ask about: no candidates given and no usable scene remembered."""


class KeyedError(ValueError):
    """Raised inside a config validator about a key below the validated value: ``loc`` (a
    tuple of keys) is appended to the validator's location. ``detail`` is a message, or the
    ValidationError of a nested model (``model``, a pydantic BaseModel) checked by hand. A
    ValueError, not a StarsError, because pydantic turns a validator's ValueError into its
    ValidationError, which ``model.config`` then reports as a ConfigError."""

    def __init__(self, loc: tuple, detail, model: type | None = None):
        super().__init__(str(detail))
        self.loc, self.detail, self.model = tuple(loc), detail, model


class OutOfScaleError(StarsError):
    """A rating's score lies outside the checkpoint's rating scale (the message names it)."""


class StoreError(StarsError):
    """The state store cannot be read or written (the message says what to do)."""


class StoreLockedError(ConfigError):
    """Another process holds the state store (one store per node)."""


class CommandLineError(Exception):
    """``--ros-args`` that rcl cannot parse, or a parameter value the node refuses."""


class LaunchArgumentError(ValueError):
    """A launch argument that is not a valid value of its parameter."""


class UntrackedPerson(ValueError):
    """A per-person ROS4HRI message for an id that ``/humans/persons/tracked`` does not list."""
