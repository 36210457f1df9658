"""Seeded mutations of valid /stars/scene messages, shared by the message and node fuzz tests.

Each mutation is a plausible way for a sender to get a message wrong: cut or corrupted
text, NaN and infinities, wrong types, missing or unknown keys, absurd sizes, unknown
actions, contradictory fields. Some mutations still give a valid message; the tests decide
validity with an independent reference (jsonschema on the 2020-12 files), not by kind.
"""
import copy
import json
import random

_WRONG_VALUES = (None, True, -1, 0, 3.5, 1e300, -1e300, '', 'x', [], {}, [1, 2], {'a': 1}, 10 ** 30)


def _paths(node, prefix=()):
    yield prefix
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _paths(value, prefix + (key,))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from _paths(value, prefix + (index,))


def _parent(doc, path):
    for step in path[:-1]:
        doc = doc[step]
    return doc


def _structural(payload: dict, rng: random.Random) -> str:
    doc = copy.deepcopy(payload)
    paths = [p for p in _paths(doc) if p]
    choice = rng.randrange(9)
    path = rng.choice(paths)
    parent = _parent(doc, path)
    if choice == 0:
        parent[path[-1]] = rng.choice(_WRONG_VALUES)
    elif choice == 1 and isinstance(parent, dict):
        del parent[path[-1]]
    elif choice == 1:
        parent.pop(path[-1])
    elif choice == 2:
        target = parent if isinstance(parent, dict) else doc
        target[rng.choice(['extra', 'Graph', 'candidate', 'userId'])] = 1
    elif choice == 3 and 'graph' in doc:
        humans = doc['graph'].get('humans') or [{'id': 1, 'xPos': 0, 'yPos': 100, 'orientation': 0}]
        doc['graph']['humans'] = [dict(humans[0], id=1000 + k) for k in range(rng.choice([201, 1000, 5000]))]
    elif choice == 4:
        doc['candidates'] = rng.choice([[], ['fly'], ['navigate', 'navigate'], ['navigate', 'dance'], [1]])
    elif choice == 5 and 'graph' in doc:
        doc['graph']['room'] = rng.choice([[], [[0, 0]], [[0, 0], [1, 1]], [[0, 0], [0, 0], [0, 0]],
                                           [[0, 0], [1e6, 0], [0, 1]]])
    elif choice == 6 and 'graph' in doc:
        doc['graph']['links'] = [[1, 999, 'interact']] if rng.random() < 0.5 else [[1, 2, 'hug']]
    elif choice == 7 and 'graph' in doc:
        doc['candidates'] = [{'candidate': 'a', 'graph': doc['graph']}]
        if rng.random() < 0.5:
            del doc['graph']
        doc['action'] = rng.choice(['navigate', 'dance'])
    else:
        leaf = [p for p in paths if isinstance(_parent(doc, p)[p[-1]], (int, float))
                and not isinstance(_parent(doc, p)[p[-1]], bool)]
        if leaf:
            p = rng.choice(leaf)
            _parent(doc, p)[p[-1]] = rng.choice([-1e6, 1e6, 0.5, -0.0, 123456789])
    return json.dumps(doc)


def _textual(text: str, rng: random.Random) -> str:
    choice = rng.randrange(7)
    cut = rng.randrange(len(text))
    if choice == 0:
        return text[:cut]
    if choice == 1:
        return text[:cut] + rng.choice('{}[]",:\\x\x00é') + text[cut + 1:]
    if choice == 2:
        numbers = [i for i, c in enumerate(text) if c.isdigit() and text[i - 1] in ' [:-']
        if numbers:
            at = rng.choice(numbers)
            end = at
            while end < len(text) and (text[end].isdigit() or text[end] in '.e'):
                end += 1
            return text[:at] + rng.choice(['NaN', 'Infinity', '-Infinity', '1e999', '1' * 5000]) + text[end:]
        return 'NaN'
    if choice == 3:
        return rng.choice(['', ' ', 'null', '[]', '"scene"', '42', '{}', '[' * 100000])
    if choice == 4:
        return text[:-1] + ', "pad": "' + 'x' * rng.choice([300000, 2000000]) + '"}'
    if choice == 5:
        return text + text
    return text.replace('"', "'", 1)


def mutate(payload: dict, rng: random.Random) -> str:
    """One mutated message text made from the valid ``payload``."""
    if rng.random() < 0.5:
        return _structural(payload, rng)
    return _textual(json.dumps(payload), rng)
