"""StARS: socially appropriate robot actions ranked per user (ROS-free core).

The front door: ``from stars_ros import StarsRecommender, load_dataset`` (``stars_ros.recommender``).
Imported on first use, so ``import stars_ros`` alone stays light (no torch)."""
__version__ = '0.1.0'

_EXPORTS = {
    'StarsRecommender': 'stars_ros.recommender',
    'Prediction': 'stars_ros.recommender',
    'Ranking': 'stars_ros.recommender',
    'PlacementMap': 'stars_ros.model.placement_map',
    'load_dataset': 'stars_ros.data.ratings',
    'RatingData': 'stars_ros.data.ratings',
    'ExperimentConfig': 'stars_ros.model.config',
}
__all__ = ['__version__', *_EXPORTS]


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    import importlib
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
