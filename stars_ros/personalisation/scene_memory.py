"""The scene requests a node remembers for the feedback that names them (``SceneMemory``).

Accepted feedback on a scene the node ranked is matched against its request text and the h
its ranking computed, kept in a bounded LRU map: strings and arrays cost the garbage
collector little, parsed JSON would cost it much more."""
from __future__ import annotations

import collections
from typing import Callable

from stars_ros import messages

SCENE_MEMORY = 4096  # scene requests remembered for feedback (least recently received go)


class SceneMemory:
    """The latest ``size`` scene requests by scene id: the request (its text, or a typed
    request's ``messages.Twin``; ``messages.parse_scene_request`` takes either) and, once it
    is ranked, the predictor that ranked it and the h of its scenes (so feedback on them is
    folded in without encoding them again)."""

    def __init__(self, size: int = SCENE_MEMORY):
        self.size = size
        self._scenes = collections.OrderedDict()  # scene_id -> [request, (predictor, h) once ranked]

    def __len__(self) -> int:
        return len(self._scenes)

    def received(self, scene_id: str, request) -> None:
        self._scenes[scene_id] = [request, None]
        self._scenes.move_to_end(scene_id)
        if len(self._scenes) > self.size:
            self._scenes.popitem(last=False)

    def ranked(self, scene_id: str, request, predictor, h, plain=None) -> None:
        """Keep the h [len(graphs), dim] that ranking ``request`` computed (and the plain
        encoder's scores, ``Scored.plain``, where it computed them), unless a newer request took
        its scene id since."""
        remembered = self._scenes.get(scene_id)
        if remembered is not None and remembered[0] is request:
            remembered[1] = (predictor, h, plain)

    def recent(self, count: int) -> list:
        """[(scene_id, request, (predictor, h, plain) or None)] of the ``count`` latest, newest first."""
        latest = []
        for scene_id in reversed(self._scenes):
            if len(latest) == count:
                break
            latest.append((scene_id, *self._scenes[scene_id]))
        return latest

    def get(self, scene_id: str) -> tuple:
        """(request, (predictor, h, plain) or None); (None, None) for a scene not remembered."""
        return tuple(self._scenes.get(scene_id, (None, None)))

    def forget(self, named: Callable[[bytes], bool]) -> int:
        """Let go of the requests whose text ``named`` finds a person in; how many."""
        gone = [scene_id for scene_id, (request, _) in self._scenes.items()
                if named(messages.text_of(request).encode('utf-8'))]
        for scene_id in gone:
            del self._scenes[scene_id]
        return len(gone)
