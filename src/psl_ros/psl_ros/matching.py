"""What a node's publishers and subscriptions have matched, reported so that others can wait
for it instead of sleeping.

DDS matches a writer with a reader on each side on its own. A subscription created in process
A is matched by A's reader as soon as A knows the writer, but the writer in process B matches
it only when B has received A's announcement of the reader; until then B sends A nothing, and
a volatile reader never gets what was published before. rclpy shows each process only its own
half (``Publisher.get_subscription_count``, ``Subscription.get_publisher_count``), so a client
that needs every message of the next episode used to sleep "a moment" after seeing its own
half (0.2-0.3 s, never a promise on a loaded machine).

`MatchReport`: a node's report of its halves, on the latched topic ``matched_endpoints``
(relative: a rollout worker's nodes report under its namespace) as one
diagnostic_msgs/DiagnosticStatus per node: ``name`` the node's fully qualified name, one
KeyValue per watched endpoint, key ``publisher <topic>`` or ``subscription <topic>`` (the
resolved topic name), value the number of endpoints it has matched, and the same count again
under ``publisher as <name>`` / ``subscription as <name>`` (the name as the node asked for it:
a robot's topic remapped anywhere is still found as ``joint_states``), and the facts the node
states about itself that never change while it runs, key ``fact <name>`` (the executor's
``clock``: a client learns it from this latched report instead of asking a parameter service,
whose answers rclpy loses while the two ends are not yet matched in DDS). It is published
again on every matched event of a watched endpoint (DDS's publication/subscription matched
status, rclpy's ``matched`` event callbacks), so it costs nothing while nothing changes.

`MatchedEndpoints`: the client side, a subscription to the reports of one namespace and the
counts they hold (`psl_ros.client` waits on it).
"""
from __future__ import annotations

import threading
from typing import Callable

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from psl_ros import names
from psl_ros.guard import guard_subscription
from psl_ros.qos import LATCHED

PUBLISHER, SUBSCRIPTION = 'publisher', 'subscription'
# a reader keeps the last report of every node (keyless topic: one history for all writers)
REPORTS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def key(kind: str, topic: str) -> str:
    """The report's key of an endpoint: ``publisher /joint_states``."""
    return f'{kind} {topic}'


def fact_key(name: str) -> str:
    """The report's key of a fact the node states about itself: ``fact clock``."""
    return f'fact {name}'


def key_as_asked(kind: str, name: str) -> str:
    """The report's second key of an endpoint, by the name its node asked for, before the
    namespace and any remapping: ``subscription as joint_states`` (a client that does not
    know where a robot's topic was remapped finds the endpoint by what it is)."""
    return f'{kind} as {name}'


class MatchReport:
    """One node's report on ``matched_endpoints`` of what its watched endpoints matched.

    The node creates the endpoints to watch through it (`create_publisher`,
    `create_subscription`, `subscribe` for a hot-path subscription): each is created with a
    matched event that updates the report. `facts`: what the node states about itself
    (name -> text), fixed for its life, sent with every report."""

    def __init__(self, node: Node, facts: dict[str, str] | None = None):
        self._node = node
        self._facts = [KeyValue(key=fact_key(name), value=str(value))
                       for name, value in (facts or {}).items()]
        self._lock = threading.Lock()
        self._endpoints: list[tuple[str, Callable[[], int]]] = []    # (key, count)
        self._sent: dict[str, int] | None = None
        self._publisher = node.create_publisher(DiagnosticStatus, names.MATCHED_ENDPOINTS,
                                                LATCHED)
        if self._facts:         # stated before any endpoint is watched
            self.update()

    def create_publisher(self, msg_type, topic: str, qos: QoSProfile):
        """``node.create_publisher``, watched."""
        publisher = self._node.create_publisher(
            msg_type, topic, qos, event_callbacks=PublisherEventCallbacks(matched=self.update))
        self._watch((key(PUBLISHER, publisher.topic_name), key_as_asked(PUBLISHER, topic)),
                    publisher.get_subscription_count)
        return publisher

    def create_subscription(self, msg_type, topic: str, callback: Callable, qos,
                            **kwargs):
        """``node.create_subscription``, watched, its callback guarded (`psl_ros.guard`)."""
        subscription = self._node.create_subscription(
            msg_type, topic, guard_subscription(self._node.get_logger(), topic, callback), qos,
            event_callbacks=SubscriptionEventCallbacks(matched=self.update), **kwargs)
        self._watch((key(SUBSCRIPTION, subscription.topic_name),
                     key_as_asked(SUBSCRIPTION, topic)), subscription.get_publisher_count)
        return subscription

    def subscribe(self, hot_path, msg_type, topic: str, callback: Callable, qos: QoSProfile,
                  **kwargs):
        """``hot_path.subscribe`` (`psl_ros.hot_path.HotPath`), watched."""
        handle = hot_path.subscribe(msg_type, topic, callback, qos, matched=self.update,
                                    **kwargs)
        self._watch((key(SUBSCRIPTION, handle.get_topic_name()),
                     key_as_asked(SUBSCRIPTION, topic)), handle.get_publisher_count)
        return handle

    def _watch(self, keys: tuple[str, ...], count: Callable[[], int]) -> None:
        with self._lock:
            self._endpoints.extend((name, count) for name in keys)
        self.update()

    def update(self, _status=None) -> None:
        """Report again if a count changed (a matched event of any watched endpoint)."""
        with self._lock:
            try:
                counts = {name: int(count()) for name, count in self._endpoints}
            except Exception:  # noqa: BLE001 - an endpoint destroyed with the node
                return
            if counts == self._sent:
                return
            self._sent = counts
            self._publisher.publish(DiagnosticStatus(
                level=DiagnosticStatus.OK, name=self._node.get_fully_qualified_name(),
                message='matched endpoints',
                values=[KeyValue(key=k, value=str(v)) for k, v in counts.items()]
                + self._facts))


class MatchedEndpoints:
    """The reports of ``matched_endpoints`` under one namespace, as a client sees them."""

    def __init__(self, node: Node, namespace: str = '', callback_group=None):
        self._lock = threading.Lock()
        self._reports: dict[str, dict[str, int]] = {}    # node -> key -> matched
        self._facts: dict[str, dict[str, str]] = {}      # node -> fact -> text
        self._subscription = node.create_subscription(
            DiagnosticStatus, names.under(namespace, names.MATCHED_ENDPOINTS), self._on_report,
            REPORTS, callback_group=callback_group)

    def _on_report(self, msg: DiagnosticStatus) -> None:
        counts, facts = {}, {}
        for kv in msg.values:
            if kv.key.startswith(fact_key('')):
                facts[kv.key[len(fact_key('')):]] = kv.value
                continue
            try:
                counts[kv.key] = int(kv.value)
            except ValueError:
                continue
        with self._lock:
            self._reports[msg.name] = counts
            self._facts[msg.name] = facts

    def fact(self, node: str, name: str) -> str:
        """The fact `name` that `node` (its fully qualified name) states in its report; ''
        while no report of it with that fact has come."""
        with self._lock:
            return self._facts.get(node, {}).get(name, '')

    def counts(self, kind: str, topic: str, as_asked: bool = False) -> dict[str, int]:
        """node -> matched endpoints of its `kind` endpoint on `topic` (resolved name; with
        `as_asked` the name the node asked for, before namespace and remapping), for the
        nodes that reported one."""
        name = key_as_asked(kind, topic) if as_asked else key(kind, topic)
        with self._lock:
            return {node: counts[name] for node, counts in self._reports.items()
                    if name in counts}

    def destroy(self, node: Node) -> None:
        node.destroy_subscription(self._subscription)
