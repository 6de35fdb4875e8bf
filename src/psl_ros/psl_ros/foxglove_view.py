"""The running graph in Foxglove: ROS topics as channels of the Foxglove SDK's WebSocket server.

What foxglove_bridge does on a full ROS 2 install (the wheels bring none): every topic of the
graph is advertised as a channel whose schema is its message definition (``ros2msg``: the
concatenated ``.msg`` definitions, as a bag of `psl record` carries them, from
`psl_ros.bag_recorder.make_typestore`), and its messages are forwarded as the CDR bytes the
publisher sent (``cdr``). The Foxglove app decodes them as it decodes a recorded bag, so one
layout (`psl_ros.foxglove_layout`) serves live data and bags alike.

Nothing is subscribed in ROS while no viewer looks: a topic's ROS subscription is made when the
first viewer subscribes to its channel and destroyed when the last one leaves, so an unwatched
graph sends this node no message (and the simulator, which draws its scene only while someone
subscribes, draws none). Latched topics (every publisher transient-local: the scene, the task
instance) are subscribed transient-local, and their newest message is sent again whenever
another viewer subscribes, so a viewer that joins mid-session sees the scene at once. Other
topics are subscribed best effort, keep last: a slow viewer never holds up a publisher. The
subscriptions are served by a `HotPath` thread that takes what has arrived every 10 ms (so of a
topic published thousands of times a second at most 10 messages per take reach Python); of each
at most ``max_rate`` messages per second (wall clock) are forwarded, bursts of up to a second's
worth whole (a token bucket: the learner's progress, a few messages at once, arrives complete;
the joint states of a lockstep loop, thousands a second, are thinned).

The SDK's server speaks the Foxglove WebSocket protocol under its current subprotocol name,
``foxglove.sdk.v1`` (before: ``foxglove.websocket.v1``; the same messages), and refuses the old
name. It therefore listens on a loopback port of its own, behind `FrontDoor`
(`psl_ros.foxglove_front_door`) on the public port, which serves both names (Lichtblick and
the clients of foxglove_bridge offer only the old one).
"""
from __future__ import annotations

import dataclasses
import threading
import time

import foxglove
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from psl_ros.bag_recorder import (EXCLUDED_TOPICS, import_message_class, is_hidden,
                                  make_typestore, register_msgtype)
from psl_ros.foxglove_front_door import FrontDoor
from psl_ros.hot_path import HotPath
from psl_ros.view_parameters import ViewParameters

SERVER_NAME = 'psl'
DISCOVERY_PERIOD = 0.5      # [s] between two looks for new topics
SUBSCRIPTION_DEPTH = 10     # keep-last depth of the view's ROS subscriptions
TAKE_PAUSE = 0.01           # [s] between two takes: a fast topic's older messages are dropped
                            # by the middleware meanwhile (keep last), not taken in Python
SDK_HOST = '127.0.0.1'      # the SDK's own server: this machine only, a free port


def ros2msg_schema(typestore, msgtype: str) -> foxglove.Schema:
    """The channel schema of a ROS 2 message type: its definition with its dependencies'
    (``ros2msg``, what rosbag2 stores in an MCAP bag)."""
    definition = typestore.generate_msgdef(msgtype, ros_version=2)[0]
    return foxglove.Schema(name=msgtype, encoding='ros2msg', data=definition.encode())


@dataclasses.dataclass
class _Topic:
    """One forwarded topic: its channel, its viewers and, while it has some, its subscription."""

    name: str
    msgtype: str
    msg_class: type
    channel: foxglove.Channel
    viewers: int = 0
    subscription: object = None
    latched: bool = False
    last: bytes | None = None       # a latched topic's newest message
    tokens: float = 0.0             # messages it may forward now (the token bucket)
    filled_ns: int = 0              # wall-clock time the bucket was last filled


class FoxgloveView:
    """A Foxglove WebSocket server (``host``:``port``: its front door) offering the graph's
    topics to viewers, run by a node: its timer looks for new topics, its executor makes and
    removes the ROS subscriptions, a `HotPath` thread forwards their messages.

    Raises:
        RuntimeError: the server cannot listen (e.g. the port is taken).
    """

    def __init__(self, node: Node, parameters: ViewParameters):
        self.node = node
        self.typestore = make_typestore()
        self.context = foxglove.Context()
        self._lock = threading.Lock()
        self._topics: dict[str, _Topic] = {}
        self._channels: dict[int, _Topic] = {}
        self._refused: set[str] = set()          # topics that cannot be offered (said once)
        self._wanted = [node.resolve_topic_name(t) for t in parameters.topic_names] or None
        self._rate = parameters.max_rate                   # tokens per second; 0 = no limit
        self._burst = max(1.0, parameters.max_rate)        # a second's worth
        self._changed = node.create_guard_condition(self._apply)
        self._loop = HotPath(node, 'view_take', pause=TAKE_PAUSE)
        where = f'{parameters.host}:{parameters.port}'
        try:
            self.server = foxglove.start_server(name=SERVER_NAME, host=SDK_HOST, port=0,
                                                server_listener=self, context=self.context)
        except Exception as exc:    # noqa: BLE001 - the SDK raises its own error types
            raise RuntimeError(f'cannot serve Foxglove on {where}: {exc}') from None
        try:
            self.front_door = FrontDoor(parameters.host, parameters.port,
                                        f'ws://{SDK_HOST}:{self.server.port}',
                                        warn=node.get_logger().warning)
        except OSError as exc:
            self.server.stop()
            raise RuntimeError(f'cannot serve Foxglove on {where}: {exc}') from None
        self.port = self.front_door.port
        self._loop.start()
        self.discover()
        self._timer = node.create_timer(DISCOVERY_PERIOD, self.discover)

    # -- channels -----------------------------------------------------------------------------
    def discover(self) -> None:
        """Advertise every wanted topic that has publishers and is not offered yet."""
        available = dict(self.node.get_topic_names_and_types())
        candidates = self._wanted if self._wanted is not None else sorted(
            t for t in available if t not in EXCLUDED_TOPICS and not is_hidden(t))
        for topic in candidates:
            if topic in self._topics or topic in self._refused or topic not in available:
                continue
            if not self.node.count_publishers(topic):
                continue
            types = available[topic]
            if len(types) != 1:
                self._refuse(topic, f'published with several types ({", ".join(types)})')
                continue
            try:
                register_msgtype(self.typestore, types[0])
                msg_class = import_message_class(types[0])
                schema = ros2msg_schema(self.typestore, types[0])
            except (LookupError, ValueError) as exc:
                self._refuse(topic, str(exc))
                continue
            channel = foxglove.Channel(topic, message_encoding='cdr', schema=schema,
                                       context=self.context)
            entry = _Topic(topic, types[0], msg_class, channel)
            with self._lock:
                self._topics[topic] = entry
                self._channels[channel.id()] = entry

    def _refuse(self, topic: str, why: str) -> None:
        self._refused.add(topic)
        self.node.get_logger().warning(f'not offering {topic}: {why}')

    @property
    def topics(self) -> dict[str, str]:
        """Offered topic -> message type."""
        with self._lock:
            return {name: entry.msgtype for name, entry in self._topics.items()}

    @property
    def subscribed(self) -> list[str]:
        """The topics this node subscribes to in ROS now (those some viewer watches)."""
        with self._lock:
            return sorted(n for n, e in self._topics.items() if e.subscription is not None)

    # -- viewers (the server's thread) --------------------------------------------------------
    def on_subscribe(self, client, channel) -> None:
        entry = self._channels.get(channel.id)
        if entry is None:
            return
        with self._lock:
            entry.viewers += 1
            last = entry.last
        if last is not None:            # a latched topic watched already: its newest again
            entry.channel.log(last, log_time=time.time_ns())
        self._changed.trigger()

    def on_unsubscribe(self, client, channel) -> None:
        entry = self._channels.get(channel.id)
        if entry is None:
            return
        with self._lock:
            entry.viewers = max(0, entry.viewers - 1)
        self._changed.trigger()

    # -- ROS subscriptions (made and removed in the node's executor, served by the HotPath) ----
    def _apply(self) -> None:
        """Subscribe to the topics that have viewers now, unsubscribe from the others."""
        with self._lock:
            entries = list(self._topics.values())
        for entry in entries:
            if entry.viewers and entry.subscription is None:
                self._subscribe(entry)
            elif not entry.viewers and entry.subscription is not None:
                self._loop.unsubscribe(entry.subscription)
                with self._lock:
                    entry.subscription, entry.last = None, None

    def _subscribe(self, entry: _Topic) -> None:
        publishers = self.node.get_publishers_info_by_topic(entry.name)
        entry.latched = bool(publishers) and all(
            p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers)
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=SUBSCRIPTION_DEPTH,
            reliability=(ReliabilityPolicy.RELIABLE if entry.latched
                         else ReliabilityPolicy.BEST_EFFORT),
            durability=(DurabilityPolicy.TRANSIENT_LOCAL if entry.latched
                        else DurabilityPolicy.VOLATILE))
        entry.tokens, entry.filled_ns = self._burst, time.time_ns()
        entry.subscription = self._loop.subscribe(
            entry.msg_class, entry.name, lambda data, e=entry: self._forward(e, data), qos,
            raw=True)

    def _forward(self, entry: _Topic, data: bytes) -> None:
        now = time.time_ns()
        if entry.latched:
            with self._lock:
                entry.last = data
        elif self._rate:
            entry.tokens = min(self._burst,
                               entry.tokens + (now - entry.filled_ns) * 1e-9 * self._rate)
            entry.filled_ns = now
            if entry.tokens < 1.0:
                return
            entry.tokens -= 1.0
        entry.channel.log(data, log_time=now)

    def close(self) -> None:
        """Stop the servers (the viewers are disconnected) and the subscriptions."""
        self._timer.cancel()
        self.front_door.close()
        self.server.stop()
        self._loop.stop()
        for entry in list(self._topics.values()):
            entry.subscription = None
