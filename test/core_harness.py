"""What a ranker node gives its ROS-free core, faked in one process: publishers that keep
what is published, a logger that keeps its lines and a ROS clock that ticks; and a core
made with the node's defaults. Used by the core's tests and by the fleet's and signing's."""
import itertools
import json
import threading

from stars_ros.node.core import RankerCore
from stars_ros.node.parameters import PARAMETERS, TOPICS


class Node:
    """What the node gives the core: its publishers, its logger and the ROS clock."""

    def __init__(self):
        self.published, self.lines = [], []
        self.clock = itertools.count(1_000_000_000, 1000)
        self.woken = threading.Event()  # set by the state store's thread when work waits for the executor

    def publish(self, topic, text):
        self.published.append((topic, json.loads(text)))

    def on(self, topic):
        return [payload for t, payload in self.published if t == topic]

    def info(self, line):
        self.lines.append(('info', line))

    def warning(self, line):
        self.lines.append(('warning', line))

    def error(self, line):
        self.lines.append(('error', line))


class SteppedClock:
    """A system clock (ns) that a test moves: by hand (``ns``), and by ``step`` at each read."""

    def __init__(self, step: int = 0, start: int = 10 ** 12):
        self.ns, self.step = start, step

    def __call__(self) -> int:
        self.ns += self.step
        return self.ns


def make_core(node, checkpoint, clock=None, **params):
    """A RankerCore on ``checkpoint`` with the node's defaults (no recording), talking to
    ``node``; ``clock``: the system clock it reads (default: the real one)."""
    values = {name: spec[0] for name, spec in PARAMETERS.items()}
    values.update({'checkpoint': str(checkpoint), 'record_folder': '', **params})
    return RankerCore(values, {topic: '/' + topic for topic in TOPICS}, '/ranker', node.publish, node,
                      lambda: next(node.clock), wake=node.woken.set, **({} if clock is None else {'clock': clock}))


def drain(core):
    """Let ``core`` work until nothing waits (what the node's guard condition does)."""
    while core.work():
        pass


def woken_and_drained(node, core) -> bool:
    """True once the state store's thread has woken the executor, whose work then ran:
    what the node's guard condition does when a commit lets a model go out."""
    if not node.woken.is_set():
        return False
    node.woken.clear()
    drain(core)
    return True


def published_models(node):
    """The stars/user_model messages ``node`` published, as text (what peers receive)."""
    return [json.dumps(p) for p in node.on('stars/user_model')]


def deliver(texts, core):
    """Hand peer messages ``texts`` to ``core`` and let it work; what each accept returned."""
    changed = [core.accept_user_model(text) for text in texts]
    drain(core)
    return changed
