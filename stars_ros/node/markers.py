"""What ``stars/markers`` shows of a ranked request, ROS-free: one ``Marker`` per scene entity
and per candidate, in REP 103 axes, and the visualization_msgs/MarkerArray they make (after a
DELETEALL, so the markers of the previous scene go) as CDR bytes, which the node publishes as
they are and the bag records (``encode_marker_array``; a test checks them against rclpy's).

SocNav1 scenes are in the robot's frame in centimetres with +y ahead, +x to the robot's right
(``docs/explanations.md``, "Scenes you can look at"); REP 103 is metres, x forward, y left,
z up. So a point (x, y) cm is (y / 100, −x / 100) m, and a heading of θ degrees (SocNav1
faces (sin θ, −cos θ), so θ = 0 faces the robot) is the yaw θ + 180° in ROS.

A candidate-scenes request is drawn in the frame of its first candidate (the robot where it
is, for ``scene_source.placement_candidates``): each candidate's robot pose there is the rigid
motion that carries its humans, objects and room corners onto the first candidate's.
"""
from __future__ import annotations

import functools
import struct
from dataclasses import dataclass

from stars_ros.data.frames import heading_yaw, robot_pose_in, to_rep103
from stars_ros.data.scene_graph import entity_nodes
from stars_ros.recording.bag import CDR_LITTLE_ENDIAN
from stars_ros.rotations import quaternion_of_yaw

KIND_COLOURS = {'robot': (0.2, 0.3, 0.9, 1.0), 'room': (0.6, 0.6, 0.6, 1.0), 'human': (1.0, 0.75, 0.1, 1.0),
                'object': (0.55, 0.35, 0.2, 1.0), 'wall': (0.3, 0.3, 0.3, 1.0),
                'interaction': (0.8, 0.2, 0.8, 1.0)}
RAISES, LOWERS = (0.1, 0.75, 0.2), (0.9, 0.15, 0.1)  # an entity that raises / lowers the score (effect > 0 / < 0)
TYPES = {'ARROW': 0, 'CUBE': 1, 'SPHERE': 2, 'CYLINDER': 3, 'LINE_STRIP': 4, 'LINE_LIST': 5}  # Marker.type
ADD, DELETEALL = 0, 3  # Marker.action
NAMESPACES = {'robot': 'robot', 'room': 'room', 'human': 'humans', 'object': 'objects', 'wall': 'walls',
              'interaction': 'interactions', 'candidate': 'candidates'}


@dataclass(frozen=True)
class Marker:
    """One visualization_msgs/Marker, in plain values: ``kind`` names its ``type``
    (ARROW, CUBE, CYLINDER, LINE_STRIP, LINE_LIST); ``position`` and ``points`` in metres,
    ``yaw`` in radians (REP 103), ``color`` RGBA in 0..1; ``label`` says what it shows."""

    ns: str
    id: int
    kind: str
    position: tuple = (0.0, 0.0, 0.0)
    yaw: float = 0.0
    scale: tuple = (1.0, 1.0, 1.0)
    color: tuple = (1.0, 1.0, 1.0, 1.0)
    points: tuple = ()
    label: str = ''


def _effect_style(base: tuple, effect: float | None, largest: float) -> tuple:
    """(colour, size factor) of an entity with ``effect`` (None: not explained)."""
    if effect is None or largest <= 0:
        return base, 1.0
    weight = abs(effect) / largest
    return (*(RAISES if effect > 0 else LOWERS), 0.35 + 0.65 * weight), 1.0 + 0.6 * weight


def _score_colour(score: float, low: float, high: float) -> tuple:
    """Red (lowest score of the request) to green (highest)."""
    t = 1.0 if high <= low else (score - low) / (high - low)
    return (1.0 - t, 0.2 + 0.6 * t, 0.1, 1.0)


def scene_markers(scene: dict, effects: dict | None = None, scene_id: str = 'robot') -> list:
    """One ``Marker`` per entity of ``scene`` (``scene_graph.entity_nodes``: the room, each
    human, object, wall segment and interaction) and one for the robot (labelled ``scene_id``,
    the request's, so a viewer or a test tells scenes apart); ``effects``: entity
    id -> removal effect (``why``), which tints (green: it raises the score, red: it lowers it)
    and sizes each entity named by its |effect|."""
    effects = effects or {}
    largest = max((abs(e) for e in effects.values()), default=0.0)
    humans = {h['id']: h for h in scene.get('humans') or []}
    objects = {o['id']: o for o in scene.get('objects') or []}
    room = [tuple(p) for p in scene['room']]
    if len(room) > 1 and room[0] == room[-1]:
        room = room[:-1]
    markers = [Marker('robot', 0, 'CYLINDER', (0.0, 0.0, 0.15), 0.0, (0.5, 0.5, 0.3), KIND_COLOURS['robot'],
                      label=scene_id)]
    walls = interactions = 0
    for entity_id, kind, _ in entity_nodes(scene):
        colour, grow = _effect_style(KIND_COLOURS[kind], effects.get(entity_id), largest)
        ns, label = NAMESPACES[kind], str(entity_id)
        if kind == 'room':
            outline = tuple((*to_rep103(*p), 0.0) for p in room + room[:1])
            markers.append(Marker(ns, 0, 'LINE_STRIP', scale=(0.02 * grow, 0.0, 0.0), color=colour, points=outline,
                                  label=label))
        elif kind in ('human', 'object'):
            entity = humans[entity_id] if kind == 'human' else objects[entity_id]
            x, y = to_rep103(entity['xPos'], entity['yPos'])
            yaw = heading_yaw(entity['orientation'])
            if kind == 'human':
                markers.append(Marker(ns, int(entity_id), 'ARROW', (x, y, 0.0), yaw,
                                      (0.6 * grow, 0.15 * grow, 0.15 * grow), colour, label=label))
            else:
                markers.append(Marker(ns, int(entity_id), 'CUBE', (x, y, 0.2), yaw, (0.4 * grow,) * 3, colour,
                                      label=label))
        elif kind == 'wall':
            start, end = room[walls], room[(walls + 1) % len(room)]
            points = ((*to_rep103(*start), 0.5), (*to_rep103(*end), 0.5))
            markers.append(Marker(ns, walls, 'LINE_LIST', scale=(0.06 * grow, 0.0, 0.0), color=colour, points=points,
                                  label=label))
            walls += 1
        else:
            first, second = (int(i) for i in entity_id.split('-'))
            ends = [humans.get(i) or objects[i] for i in (first, second)]
            points = tuple((*to_rep103(e['xPos'], e['yPos']), 0.05) for e in ends)
            markers.append(Marker(ns, interactions, 'LINE_LIST', scale=(0.03 * grow, 0.0, 0.0), color=colour,
                                  points=points, label=label))
            interactions += 1
    return markers


def ranking_markers(request, ranked: list) -> list:
    """The markers of one ranked request (``messages.SceneRequest``, ``predictor.Ranked``
    entries best first, with their ``why`` when explained): its scene, tinted by the best
    entry's entity effects, and for candidate scenes one flat disc per candidate at its robot
    pose, coloured by score (red lowest, green highest), the best one larger and opaque."""
    best = ranked[0] if ranked else None
    effects = None if best is None or best.why is None else {i: e for i, _, e in best.why.entities}
    reference = request.graphs[0]
    markers = scene_markers(reference, effects, request.scene_id)
    if not request.ranks_scenes:
        return markers
    scores = {r.name: r.score for r in ranked}
    low, high = min(scores.values(), default=0.0), max(scores.values(), default=0.0)
    for k, (label, graph) in enumerate(zip(request.labels, request.graphs)):
        x, y, rotation = robot_pose_in(reference, graph)
        position = (*to_rep103(x, y), 0.02)
        is_best = best is not None and label == best.name
        size = 0.45 if is_best else 0.3
        score = scores.get(label)  # None: cut by top_k
        colour = (0.5, 0.5, 0.5, 0.4) if score is None else _score_colour(score, low, high)
        if not is_best:
            colour = (*colour[:3], min(colour[3], 0.6))
        markers.append(Marker(NAMESPACES['candidate'], k, 'CYLINDER', position, rotation, (size, size, 0.04), colour,
                              label=f'{label} {score:.3f}' if score is not None else label))
    return markers


class _Cdr:
    """Little-endian plain CDR (what rclpy's Fast DDS type support writes): each number aligned
    to its size from the start of the payload, strings as uint32 length (with the NUL) + UTF-8 + NUL."""

    def __init__(self, phase: int = 0):
        self.buffer = bytearray(phase)  # ``phase`` bytes stand for what precedes (see _constant)

    def _align(self, size: int):
        self.buffer += bytes(-len(self.buffer) % size)

    def numbers(self, code: str, *values):
        self._align(struct.calcsize(code))
        self.buffer += struct.pack(f'<{len(values)}{code}', *values)

    def string(self, text: str):
        data = text.encode()
        self.numbers('I', len(data) + 1)
        self.buffer += data + b'\0'

    def boolean(self, value: bool):
        self.buffer.append(1 if value else 0)


def _texture_on(out: _Cdr):
    """colors, texture_resource, texture (sensor_msgs/CompressedImage) and uv_coordinates, all empty."""
    out.numbers('I', 0)
    out.string('')
    out.numbers('i', 0)
    out.numbers('I', 0)
    out.string('')
    out.string('')
    out.numbers('I', 0)
    out.numbers('I', 0)


def _mesh_on(out: _Cdr):
    """mesh_resource, mesh_file (visualization_msgs/MeshFile) and mesh_use_embedded_materials, empty."""
    out.string('')
    out.string('')
    out.numbers('I', 0)
    out.boolean(False)


@functools.lru_cache(maxsize=64)
def _constant(part, phase: int, *args) -> bytes:
    """The bytes ``part(out, *args)`` writes at an offset ``phase`` (mod 8) into the payload:
    the same wherever that is, so they are made once."""
    out = _Cdr(phase)
    part(out, *args)
    return bytes(out.buffer[phase:])


def _header_on(out: _Cdr, frame_id: str, sec: int, nanosec: int):
    out.numbers('i', sec)
    out.numbers('I', nanosec)
    out.string(frame_id)


def _marker_cdr(out: _Cdr, marker: Marker | None, frame_id: str, sec: int, nanosec: int):
    """One visualization_msgs/Marker, field by field; None: a DELETEALL."""
    buffer = out.buffer
    buffer += _constant(_header_on, len(buffer) % 8, frame_id, sec, nanosec)
    ns = b'' if marker is None else marker.ns.encode()
    out.numbers('I', len(ns) + 1)
    buffer += ns + b'\0'
    if marker is None:
        codes, values = (0, 0, DELETEALL), (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)  # identity pose
        points, colour = (), (0.0,) * 4
    else:
        codes = (marker.id, TYPES[marker.kind], ADD)
        values = (*marker.position, *quaternion_of_yaw(marker.yaw), *marker.scale)
        points, colour = marker.points, marker.color
    offset = len(buffer)
    pad4 = -offset % 4
    pad8 = -(offset + pad4 + 12) % 8  # pose, scale: float64
    # id, type, action; pose, scale; color (float32); lifetime (0: until the next DELETEALL); frame_locked
    layout = f'<{pad4}x3i{pad8}x10d4f2i?'
    after = offset + struct.calcsize(layout)
    layout += f'{-after % 4}xI'  # points
    flat = ()
    if points:
        after += -after % 4 + 4
        layout += f'{-after % 8}x{3 * len(points)}d'
        flat = tuple(value for point in points for value in point)
    buffer += struct.pack(layout, *codes, *values, *colour, 0, 0, False, len(points), *flat)
    buffer += _constant(_texture_on, len(buffer) % 8)
    out.string('' if marker is None else marker.label)  # text
    buffer += _constant(_mesh_on, len(buffer) % 8)


def encode_marker_array(markers: list, frame_id: str, stamp_ns: int) -> bytes:
    """The CDR bytes of a visualization_msgs/MarkerArray: a DELETEALL, then ``markers``, every
    header in ``frame_id`` at ``stamp_ns`` (ns of ROS time); ``label`` goes in ``text``."""
    out = _Cdr()
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    out.numbers('I', len(markers) + 1)
    _marker_cdr(out, None, frame_id, sec, nanosec)
    for marker in markers:
        _marker_cdr(out, marker, frame_id, sec, nanosec)
    return CDR_LITTLE_ENDIAN + bytes(out.buffer)
