"""Per-step subscriptions served by a lean wait loop instead of the rclpy executor.

The lockstep loop is bound by how fast a message gets from DDS into a Python callback. An
rclpy executor rebuilds its wait set from every entity of the node on every spin (parameter
services, QoS-event handlers, timers, guard conditions): about 120-160 us per wake-up here,
twice per control step. `HotPath` keeps a fixed wait set holding only the per-step
subscriptions (and a guard condition to stop it) and serves it from its own thread; the
node's other entities (services, parameters, latched topics) stay with the ordinary
executor. Measured on this machine: a publish/answer round trip between two processes takes
0.26 ms with this loop on both sides against 0.52 ms with executors.

The subscriptions are real subscriptions of the node (same participant, remapping and
namespace applied by rcl); they are only invisible to the executor. Callbacks run in the
hot-path thread, in the order the subscriptions were added when several are ready, so a
node that must see message A before message B (a trajectory before the state it applies
to) adds A first. Callbacks must not block.

The bag recorder uses the same loop with serialized messages (``raw``), their middleware
information (``info``: receive time, publication sequence number) and the DDS message-lost
event of each subscription (``message_lost``), adding subscriptions while it runs, taking in
batches (``pause``: a consumer that need not answer at once lets messages queue up in the
middleware and takes them with one wake-up instead of one each) and taking what is left when
it stops (``stop(drain=True)``).
"""
from __future__ import annotations

import threading
from typing import Any, Callable

from rclpy.event_handler import QoSSubscriptionEventType
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.type_support import check_is_valid_msg_type


class _Subscription:
    """One subscription of the loop: its rcl handle, what to take and whom to call."""

    __slots__ = ('handle', 'msg_type', 'callback', 'topic', 'raw', 'info', 'events')

    def __init__(self, handle, msg_type: type, callback: Callable, topic: str, raw: bool,
                 info: bool, events: list[_Event]):
        self.handle, self.msg_type, self.callback, self.topic = handle, msg_type, callback, topic
        self.raw, self.info = raw, info
        self.events = events


class _Event:
    """An event of a subscription (message lost, matched) and whom to call with its status."""

    __slots__ = ('handle', 'callback', 'what', 'index')

    def __init__(self, subscription, event_type, callback: Callable, what: str):
        with subscription:
            self.handle = _rclpy.EventHandle(subscription, event_type)
        self.callback, self.what = callback, what
        self.index = -1                              # in the current wait set


class HotPath:
    """A thread that waits on a fixed set of subscriptions and dispatches their messages."""

    def __init__(self, node: Node, name: str = 'hot_path', pause: float = 0.0):
        """A loop for `node`'s subscriptions (none yet; see `subscribe`).

        Args:
            node: The node the subscriptions belong to.
            name: The thread's name.
            pause: [s] Rest after each wake-up before waiting again (0: answer at once).

        """
        self._node = node
        self._name = name
        self._pause = pause
        self._lock = threading.Lock()
        self._subs: tuple[_Subscription, ...] = ()   # replaced, never changed, under _lock
        self._retired: list[_Subscription] = []      # unsubscribed, to destroy (under _lock)
        self._generation = 0        # counts the changes of _subs (an empty tuple is always the
                                    # same object: identity cannot tell () from () again)
        self._guard = _rclpy.GuardCondition(node.context.handle)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def subscribe(self, msg_type: type, topic: str, callback: Callable[..., None],
                  qos: QoSProfile, *, raw: bool = False, info: bool = False,
                  message_lost: Callable[[Any], None] | None = None,
                  matched: Callable[[Any], None] | None = None) -> Any:
        """Add a subscription; a running loop takes it up at once.

        Args:
            msg_type: The message class.
            topic: Topic name (resolved by rcl against the node's namespace).
            callback: Called with each message, ``callback(msg)``, or with ``info``
                ``callback(msg, info)`` (rmw message info: 'received_timestamp',
                'source_timestamp', 'publication_sequence_number', ...).
            qos: The subscription's QoS profile.
            raw: Pass the serialized message (bytes) instead of a message object.
            info: Also pass the message info.
            message_lost: Called with the rmw message-lost status (``total_count``,
                ``total_count_change``) whenever the middleware reports lost messages.
            matched: Called with the rmw matched status (``current_count``, ...) whenever
                the subscription matches or loses a publisher (`psl_ros.matching`).

        Returns:
            The rcl subscription handle (``get_publisher_count()``, ``get_topic_name()``).

        """
        check_is_valid_msg_type(msg_type)    # imports the type support
        with self._node.handle:
            handle = _rclpy.Subscription(self._node.handle, msg_type, topic,
                                         qos.get_c_qos_profile())
        events = [_Event(handle, event_type, call, what) for event_type, call, what in (
            (QoSSubscriptionEventType.RCL_SUBSCRIPTION_MESSAGE_LOST, message_lost,
             'message-lost'),
            (QoSSubscriptionEventType.RCL_SUBSCRIPTION_MATCHED, matched, 'matched'))
            if call is not None]
        with self._lock:
            self._subs = self._subs + (_Subscription(handle, msg_type, callback, topic, raw,
                                                     info, events),)
            self._generation += 1
        if self._thread is not None:
            self._guard.trigger_guard_condition()    # the loop rebuilds its wait set
        return handle

    def unsubscribe(self, handle) -> None:
        """Remove a subscription `subscribe` returned. The loop destroys it once its wait set
        no longer holds it (at once when the loop does not run)."""
        with self._lock:
            self._retired += [s for s in self._subs if s.handle is handle]
            self._subs = tuple(s for s in self._subs if s.handle is not handle)
            self._generation += 1
        if self._thread is not None and self._thread.is_alive():
            self._guard.trigger_guard_condition()    # the loop rebuilds its wait set
        else:
            self._destroy_retired()

    def _destroy_retired(self) -> None:
        with self._lock:
            retired, self._retired = self._retired, []
        for sub in retired:
            for event in sub.events:
                event.handle.destroy_when_not_in_use()
            sub.handle.destroy_when_not_in_use()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        logger = self._node.get_logger()
        subs: tuple[_Subscription, ...] = ()
        generation = -1
        while not self._stop.is_set():
            try:
                if generation != self._generation:
                    with self._lock:
                        subs, generation = self._subs, self._generation
                    events = tuple((sub, event) for sub in subs for event in sub.events)
                    wait_set = _rclpy.WaitSet(len(subs), 1, 0, 0, 0, len(events),
                                              self._node.context.handle)
                    self._destroy_retired()      # no wait set holds them any more
                wait_set.clear_entities()
                for sub in subs:
                    wait_set.add_subscription(sub.handle)
                for _, event in events:
                    event.index = wait_set.add_event(event.handle)
                wait_set.add_guard_condition(self._guard)
                wait_set.wait(-1)
            except Exception:  # noqa: BLE001 - the context was shut down: end quietly
                return
            ready = set(wait_set.get_ready_entities('subscription'))
            for sub in subs:
                if sub.handle.pointer in ready:
                    self._take_all(sub, logger)
            for sub, event in events:
                if wait_set.is_ready('event', event.index):
                    self._take_event(sub, event, logger)
            if self._pause:
                self._stop.wait(self._pause)

    @staticmethod
    def _take_all(sub: _Subscription, logger) -> None:
        """Take everything queued on `sub`, oldest first, and dispatch it."""
        while True:
            taken = sub.handle.take_message(sub.msg_type, sub.raw)
            if taken is None:
                return
            try:
                if sub.info:
                    sub.callback(taken[0], taken[1])
                else:
                    sub.callback(taken[0])
            except Exception as exc:  # noqa: BLE001 - a callback bug must not end the loop
                logger.error(f'{sub.topic} callback failed: {exc!r}')

    @staticmethod
    def _take_event(sub: _Subscription, event: _Event, logger) -> None:
        status = event.handle.take_event()
        if status is None:
            return
        try:
            event.callback(status)
        except Exception as exc:  # noqa: BLE001 - a callback bug must not end the loop
            logger.error(f'{sub.topic} {event.what} callback failed: {exc!r}')

    def stop(self, drain: bool = False) -> None:
        """End the thread and destroy the subscriptions (idempotent).

        Args:
            drain: First take and dispatch, in this thread, what the subscriptions still
                hold (and the last message-lost status): every message the middleware has
                delivered (for reliable topics: acknowledged) before the call.

        """
        self._stop.set()
        try:
            self._guard.trigger_guard_condition()
        except Exception:  # noqa: BLE001 - already destroyed with the context
            pass
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        with self._lock:
            subs, self._subs = self._subs, ()
        if drain and not (self._thread is not None and self._thread.is_alive()):
            logger = self._node.get_logger()
            for sub in subs:
                try:
                    self._take_all(sub, logger)
                    for event in sub.events:
                        self._take_event(sub, event, logger)
                except Exception:  # noqa: BLE001 - the context was shut down: nothing left
                    break
        with self._lock:
            self._retired += subs
        self._destroy_retired()
