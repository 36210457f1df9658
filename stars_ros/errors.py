"""Exception hierarchy: the core raises these, nodes and CLIs catch them at their boundary."""


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


class TrainingDivergedError(StarsError):
    """Parameters became non-finite during training: lower the learning rate."""


class UnknownSceneError(StarsError):
    """A scene named by id is not in the data the ids are looked up in (give its content)."""
class NotFittedError(StarsError):
    """A model was asked to predict before fit() or load()."""
