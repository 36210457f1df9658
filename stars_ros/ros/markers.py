"""stars/markers on the wire: the publisher of the MarkerArray bytes ``node.markers`` encodes,
and their type as a bag stores it (``recording.MessageType``: the ros2msg definition rosbag2
writes, made from the installed message classes, so it matches the ROS it runs on).
"""
from __future__ import annotations

import importlib

from visualization_msgs.msg import MarkerArray

from stars_ros.recording import MessageType

MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'
_BASIC = {'double': 'float64', 'float': 'float32', 'long double': 'float64', 'boolean': 'bool', 'octet': 'byte'}


def _field(idl: str) -> tuple:
    """(ros2msg type, 'pkg/Type' it uses or None) of a rosidl field type (``double``,
    ``string<10>``, ``sequence<geometry_msgs/Point>``, ``sequence<int32, 5>``, ``uint8[4]``)."""
    suffix = ''
    if idl.startswith('sequence<'):
        inner, _, bound = idl[len('sequence<'):-1].partition(', ')
        idl, suffix = inner, f'[<={bound}]' if bound else '[]'
    elif idl.endswith(']'):
        idl, size = idl[:-1].split('[')
        suffix = f'[{size}]'
    if idl.startswith(('string<', 'wstring<')):
        base, _, bound = idl[:-1].partition('<')
        return f'{base}<={bound}{suffix}', None
    return _BASIC.get(idl, idl) + suffix, idl if '/' in idl else None


def message_definition(message_class) -> str:
    """The ros2msg text of ``message_class`` and of every type it uses, depth first (each
    after a line of 80 '=' and ``MSG: pkg/Type``), as rosbag2 stores it in an MCAP schema
    (the fields: constants, which no reader needs to decode, are left out)."""
    sections, seen = [], set()

    def define(cls):
        lines, used = [], []
        for name, idl in cls.get_fields_and_field_types().items():
            text, nested = _field(idl)
            lines.append(f'{text} {name}')
            if nested is not None:
                used.append(nested)
        header = '' if not sections else '=' * 80 + f"\nMSG: {cls.__module__.split('.')[0]}/{cls.__name__}\n"
        sections.append(header + '\n'.join(lines) + '\n')
        for key in used:
            if key not in seen:
                seen.add(key)
                package, name = key.split('/')
                define(getattr(importlib.import_module(f'{package}.msg'), name))
    define(message_class)
    return ''.join(sections)


class MarkerOutput:
    """What ``RankerCore`` sends stars/markers through (its ``markers_out``): the node's
    MarkerArray publisher, which publishes the encoded bytes as they are; ``type_hash`` is the
    topic's RIHS01 hash (as the middleware reports it for the publisher)."""

    def __init__(self, publisher, type_hash: str):
        self.publisher = publisher
        self.message_type = MessageType(MARKER_ARRAY, message_definition(MarkerArray), type_hash)

    def publish(self, data: bytes):
        self.publisher.publish(data)
