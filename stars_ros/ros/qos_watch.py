"""QoS and type mismatches on a node's topics, found by asking the ROS graph instead of by
event handlers.

rclpy gives every publisher and subscription two default event handlers (incompatible QoS,
incompatible type) unless told otherwise. Each is a waitable that every executor turn adds to
its wait set and checks again: in a profile of the ranker, with its dozen endpoints, they were
the largest part of the executor's own work per service call (docs/performance.md). The ranker creates
its endpoints with ``NO_PUBLISHER_EVENTS`` / ``NO_SUBSCRIPTION_EVENTS`` and ``QosWatch``
checks instead, once per diagnostics period, every endpoint on the other side of each of its
topics: a publisher or subscriber whose QoS can never match, or whose type differs, is
reported once (kind ``qos``, a warning, on stars/errors, in the log and in /diagnostics).
The node on the other side still gets rclpy's own warning if it keeps the default handlers.
"""
from __future__ import annotations

from dataclasses import dataclass

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.qos import QoSCompatibility, QoSProfile, qos_check_compatible

NO_PUBLISHER_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)
NO_SUBSCRIPTION_EVENTS = SubscriptionEventCallbacks(use_default_callbacks=False)


@dataclass(frozen=True)
class Endpoint:
    """One of the node's own: its resolved ``topic``, message type name (``pkg/msg/Name``)
    and whether it publishes (else it subscribes)."""

    topic: str
    type_name: str
    publishes: bool


def type_name(msg_type) -> str:
    """``pkg/msg/Name`` of a message class, as the graph reports types."""
    return f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"


class QosWatch:
    """The node's endpoints (``watch``) and the mismatches not yet reported (``new_mismatches``)."""

    def __init__(self, node):
        self.node = node
        self.endpoints: list[Endpoint] = []
        self._checked = set()  # (own topic, side, the other endpoint's gid)

    def watch(self, entity, publishes: bool) -> None:
        """Check ``entity`` (a publisher or subscription of the node)."""
        self.endpoints.append(Endpoint(entity.topic_name, type_name(entity.msg_type), publishes))

    def forget(self, entities) -> None:
        """Stop checking ``entities`` (destroyed: a managed node's deactivate)."""
        gone = {(e.topic_name, type_name(e.msg_type)) for e in entities}
        self.endpoints = [e for e in self.endpoints if (e.topic, e.type_name) not in gone]

    def new_mismatches(self) -> list[tuple[str, str]]:
        """(topic, what is wrong) for each endpoint of another node, new since the last call,
        that cannot talk with one of this node's. An endpoint's QoS and type are fixed for its
        life, so each is checked once: a period costs one graph query per own endpoint, and the
        own endpoint's QoS is looked up only when something new has joined its topic."""
        found = []
        for own in self.endpoints:
            others = [info for info in (self.node.get_subscriptions_info_by_topic(own.topic) if own.publishes
                                        else self.node.get_publishers_info_by_topic(own.topic))
                      if (own.topic, own.publishes, bytes(info.endpoint_gid)) not in self._checked
                      and not self._is_mine(info)]
            if not others:
                continue
            mine = [info for info in (self.node.get_publishers_info_by_topic(own.topic) if own.publishes
                                      else self.node.get_subscriptions_info_by_topic(own.topic))
                    if self._is_mine(info) and info.topic_type == own.type_name]
            if not mine:  # not in the graph yet: the next period checks them
                continue
            for other in others:
                self._checked.add((own.topic, own.publishes, bytes(other.endpoint_gid)))
                problem = self._problem(own, mine[0].qos_profile, other)
                if problem is not None:
                    found.append((own.topic, problem))
        return found

    def _is_mine(self, info) -> bool:
        return info.node_name == self.node.get_name() and info.node_namespace == self.node.get_namespace()

    @staticmethod
    def _problem(own: Endpoint, own_qos: QoSProfile, other) -> str | None:
        """What stops ``other`` (the graph's endpoint info) and this node's endpoint, whose QoS
        as the graph reports it is ``own_qos``, from talking; None: nothing."""
        who = f"{'subscriber' if own.publishes else 'publisher'} {other.node_namespace.rstrip('/')}/{other.node_name}"
        if other.topic_type != own.type_name:
            return (f'{who} on {own.topic} uses type {other.topic_type}, this node {own.type_name}: '
                    'no message passes between them')
        publisher, subscription = (own_qos, other.qos_profile) if own.publishes else (other.qos_profile, own_qos)
        compatibility, reason = qos_check_compatible(publisher, subscription)
        if compatibility == QoSCompatibility.ERROR:
            return f'{who} on {own.topic} has QoS that can never match this node\'s: {reason}'
        return None
