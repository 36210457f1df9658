"""The import structure: serving does not bring in training or pandas, and no two modules
import each other (issue 36)."""
import ast
import json
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / 'stars_ros'
# What a robot runs: the ranker node (its ROS-free core and its rclpy adapter), the predictor
# and the front door loading a checkpoint, replay and the markers.
SERVING = ('stars_ros.model.predictor', 'stars_ros.recommender', 'stars_ros.node.core', 'stars_ros.ros.ranker',
           'stars_ros.ros.replay', 'stars_ros.ros.markers')
TRAINING = ('stars_ros.model.training', 'stars_ros.data.ratings', 'stars_ros.evaluation.crowd_data')


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


MODULES = {module_name(path): path for path in sorted(PACKAGE.rglob('*.py'))}


def imported(name: str, top_level_only: bool = False) -> set:
    """The modules ``name``'s source imports (anywhere in it, or at its top level only),
    ``from package import module`` counted as the module."""
    tree = ast.parse(MODULES[name].read_text())
    nodes = tree.body if top_level_only else ast.walk(tree)
    found = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f'{node.module}.{alias.name}' for alias in node.names
                         if f'{node.module}.{alias.name}' in MODULES)
    return found


def test_serving_imports_neither_training_nor_pandas():
    """Importing the serving modules loads no training module, and none of the package's
    modules it loads imports pandas. (PyG, which the graph encoders are built with, imports
    pandas itself where it is installed: that is the library's, not a path of ours.)"""
    script = (f'import sys\nfor name in {SERVING!r}:\n    __import__(name)\n'
              "import json; print(json.dumps(sorted(m for m in sys.modules if m.startswith('stars_ros'))))")
    loaded = json.loads(subprocess.run([sys.executable, '-c', script], check=True, capture_output=True,
                                       text=True).stdout.splitlines()[-1])
    assert not set(TRAINING) & set(loaded), f'serving loads {set(TRAINING) & set(loaded)}'
    with_pandas = [name for name in loaded if name in MODULES and 'pandas' in imported(name, top_level_only=True)]
    assert not with_pandas, f'serving modules that import pandas: {with_pandas}'


def test_no_two_modules_import_each_other():
    graph = {name: {other for other in imported(name) if other in MODULES and other != name} for name in MODULES}
    pairs = sorted({tuple(sorted((a, b))) for a, targets in graph.items() for b in targets
                    if a in graph.get(b, ()) and not (a.startswith(b + '.') or b.startswith(a + '.'))})
    assert not pairs, f'modules that import each other: {pairs}'
