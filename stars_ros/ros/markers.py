"""stars/markers on the wire: the publisher of the MarkerArray bytes ``node.markers`` encodes,
and their type as a bag stores it (``recording.MessageType``: the ros2msg definition rosbag2
writes, made from the installed message classes, so it matches the ROS it runs on).
"""
from __future__ import annotations

import importlib

from rosidl_parser import definition
from visualization_msgs.msg import MarkerArray

from stars_ros.recording import MessageType

MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'
_BASIC = {'double': 'float64', 'float': 'float32', 'long double': 'float64', 'boolean': 'bool', 'octet': 'byte',
          'char': 'char', 'wchar': 'wchar'}


def _type_text(slot) -> str:
    """A field type in ros2msg syntax (``float64``, ``string<=10``, ``geometry_msgs/Point[]``)."""
    if isinstance(slot, definition.BasicType):
        return _BASIC.get(slot.typename, slot.typename)
    if isinstance(slot, definition.NamespacedType):
        return f'{slot.namespaces[0]}/{slot.name}'
    if isinstance(slot, definition.AbstractGenericString):
        base = 'wstring' if isinstance(slot, definition.AbstractWString) else 'string'
        return f'{base}<={slot.maximum_size}' if slot.has_maximum_size() else base
    inner = _type_text(slot.value_type)
    if isinstance(slot, definition.Array):
        return f'{inner}[{slot.size}]'
    if isinstance(slot, definition.BoundedSequence):
        return f'{inner}[<={slot.maximum_size}]'
    return f'{inner}[]'


def _nested(slot):
    while isinstance(slot, definition.AbstractNestedType):
        slot = slot.value_type
    return slot if isinstance(slot, definition.NamespacedType) else None


def message_definition(message_class) -> str:
    """The ros2msg text of ``message_class`` and of every type it uses, depth first (each
    after a line of 80 '=' and ``MSG: pkg/Type``), as rosbag2 stores it in an MCAP schema
    (the fields: constants, which no reader needs to decode, are left out)."""
    sections, seen = [], set()

    def define(cls):
        lines, used = [], []
        for name, slot in zip(cls.get_fields_and_field_types(), cls.SLOT_TYPES):
            lines.append(f'{_type_text(slot)} {name}')
            nested = _nested(slot)
            if nested is not None:
                used.append((nested.namespaces[0], nested.name))
        header = '' if not sections else '=' * 80 + f"\nMSG: {cls.__module__.split('.')[0]}/{cls.__name__}\n"
        sections.append(header + '\n'.join(lines) + '\n')
        for key in used:
            if key not in seen:
                seen.add(key)
                define(getattr(importlib.import_module(f'{key[0]}.msg'), key[1]))
    define(message_class)
    return ''.join(sections)


class MarkerOutput:
    """What ``RankerCore`` sends stars/markers through (its ``markers_out``): the node's
    MarkerArray publisher, which publishes the encoded bytes as they are; ``type_hash`` is the
    topic's RIHS01 hash (as the middleware reports it for the publisher)."""

    def __init__(self, publisher, type_hash: str):
        self.publisher = publisher
        self.message_type = MessageType(MARKER_ARRAY, message_definition(MarkerArray), type_hash)

    def subscribed(self) -> bool:
        return self.publisher.get_subscription_count() > 0

    def publish(self, data: bytes):
        self.publisher.publish(data)
