"""A walk over every object reachable from one root: attributes, containers, caches and
closures (a function's cells and defaults, a bound method's object), stopping at modules,
classes and module globals, which the whole process shares, and at ``outside`` (what a test
stands in for the world with: the publishers that keep what was published)."""
import gc
import sys
import types

import numpy as np

_ATOMS = (str, bytes, bytearray, int, float, complex, bool, type(None), range)


def reachable(root, outside=()) -> list:
    """Every object reachable from ``root`` (``root`` first), each once."""
    shared = {id(vars(module)) for module in list(sys.modules.values()) if module is not None}
    seen = {id(o) for o in outside} | shared
    found, todo = [], [root]
    while todo:
        obj = todo.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        found.append(obj)
        if isinstance(obj, _ATOMS + (type, types.ModuleType, types.CodeType, types.BuiltinFunctionType)):
            continue
        if isinstance(obj, np.ndarray):
            if obj.dtype == object:
                todo.extend(obj.ravel().tolist())
            continue
        if isinstance(obj, types.FunctionType):
            todo.extend(cell.cell_contents for cell in obj.__closure__ or () if _filled(cell))
            todo.extend([obj.__defaults__, obj.__kwdefaults__])
            continue
        todo.extend(gc.get_referents(obj))
    return found


def _filled(cell) -> bool:
    try:
        _ = cell.cell_contents
    except ValueError:
        return False
    return True


def naming(objects: list, user_id: str) -> list:
    """The strings and bytes among ``objects`` that hold ``user_id``."""
    encoded = user_id.encode()
    return [o for o in objects if (isinstance(o, str) and user_id in o)
            or (isinstance(o, (bytes, bytearray)) and encoded in o)]
