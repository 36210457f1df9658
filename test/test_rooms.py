"""The package's rooms (its top-level subpackages) and who owns a person's state, read from
the source: no two rooms import each other, and one module writes a person."""
import ast
import sys
from pathlib import Path

import stars_ros
from stars_ros import state

PACKAGE = Path(stars_ros.__file__).parent
# the store's methods that change a person (or the checkpoint the people rows belong to)
WRITES_OF_A_PERSON = {'write_person', 'forget_person', 'erase_person', 'erase_older', 'keep_tombstone',
                      'set_fingerprint'}
OWNER = {'stars_ros.personalisation.online', 'stars_ros.personalisation.keeping'}  # Personalisation's modules


def _modules():
    for path in sorted(PACKAGE.rglob('*.py')):
        parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
        yield '.'.join(parts[:-1] if parts[-1] == '__init__' else parts), path, ast.parse(path.read_text())


def _room(module: str) -> str | None:
    """The room of ``stars_ros.<room>....``; None for a top-level module (not a room)."""
    parts = module.split('.')
    return parts[1] if len(parts) > 1 and (PACKAGE / parts[1]).is_dir() else None


def _imported(module: str, path: Path, tree) -> set:
    names = set()
    package = module if path.name == '__init__.py' else module.rpartition('.')[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                parts = package.split('.')
                base = '.'.join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            names.update(f'{base}.{alias.name}' for alias in node.names)
            names.add(base)
    return {name for name in names if name.startswith('stars_ros.')}


def test_no_two_rooms_import_each_other():
    edges = {}
    for module, path, tree in _modules():
        room = _room(module)
        for name in _imported(module, path, tree):
            other = _room(name)
            if room and other and other != room:
                edges.setdefault((room, other), module)
    both_ways = sorted(f'{a} <-> {b} ({edges[(a, b)]}, {edges[(b, a)]})' for a, b in edges
                       if (b, a) in edges and a < b)
    assert both_ways == []
    assert ('personalisation', 'state') in edges and ('state', 'personalisation') not in edges


def test_one_module_writes_a_person():
    """In a serving process the owner of people (``Personalisation``) is the one caller of the
    state store's writes of a person; the other is the erasure with no node running, on a
    store it opened itself (refused while a node holds it). (The owner's and the core's own
    ``forget_person`` are not the store's: a store is what the call is made on.)"""
    writers = {(module, function.name) for module, _, tree in _modules() if _room(module) != 'state'
               for function in ast.walk(tree) if isinstance(function, ast.FunctionDef)
               for node in ast.walk(function)
               if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
               and node.func.attr in WRITES_OF_A_PERSON and ast.unparse(node.func.value).endswith('store')}
    assert {module for module, _ in writers} - OWNER == {'stars_ros.recording.erasure'}
    assert {module for module, _ in writers} & OWNER
    assert {name for module, name in writers if module == 'stars_ros.recording.erasure'} == {'_erase_offline'}


def test_people_are_written_only_through_the_store_s_queued_writes():
    """No way past the owner: ``write_people`` (which wrote rows through the store's private
    methods) is gone from ``stars_ros.state``; outside ``state`` no module imports the rows a
    store's writer changes (``state.rows``) or touches a private member of a store, and only
    the node's records and the offline erasure open one."""
    assert 'write_people' not in state.__all__ and not hasattr(state, 'write_people')
    assert not any(hasattr(module, 'write_people') for name, module in list(sys.modules.items())
                   if name.startswith('stars_ros.state'))
    outside = [(module, path, tree) for module, path, tree in _modules() if _room(module) != 'state']
    internals = {'stars_ros.state.rows', 'stars_ros.state.legacy', 'stars_ros.state.locking'}
    assert {module for module, path, tree in outside if _imported(module, path, tree) & internals} == set()
    defined = {node.attr if isinstance(node, ast.Attribute) else node.name for module, _, tree in _modules()
               if _room(module) == 'state' for node in ast.walk(tree) if isinstance(node, ast.FunctionDef)
               or isinstance(node, ast.Attribute) and ast.unparse(node.value) == 'self'}
    private = {name for name in defined if name.startswith('_') and not name.startswith('__')}
    assert {'_rows', '_queue', '_connection'} <= private
    reached = {(module, ast.unparse(node)) for module, _, tree in outside for node in ast.walk(tree)
               if isinstance(node, ast.Attribute) and node.attr in private
               and ast.unparse(node.value) != 'self'}
    assert reached == set()
    openers = {module for module, _, tree in outside for node in ast.walk(tree)
               if isinstance(node, ast.Call) and ast.unparse(node.func).endswith('StateStore')}
    assert openers == {'stars_ros.node.records', 'stars_ros.recording.erasure'}
