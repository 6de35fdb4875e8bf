"""Services that do not lose their answers.

Two ways an answer of an rclpy service got lost here (both measured with 8 querying and 2
adding clients on the skill memory, `psl bench memory-load`):
- **Under load**: the answers to all clients of a service travel on one topic that every client
  reads and keeps in a keep-last history; a client that falls behind loses its own answer among
  the others'. `psl_ros.qos.SERVICES` (deep enough for a client to fall behind longer than its
  call's timeout) on the clients and the server; its docstring has the numbers.
- **A new client**: `wait_for_service` is true as soon as the *client* has matched the server's
  endpoints, but the server may not have matched the client's response reader yet. Fast DDS
  (rmw_fastrtps, ``rmw_response.cpp``) then waits 100 ms for it and drops the answer with the
  warning "failed to send response (timeout): client will not receive response"; the client
  waits in vain. With one core busy this happened in about one run in three, the server
  matching the client 0.1-1.0 s after it had taken the request. The request itself is not lost
  (the client's request writer has matched the server's reader before it writes; a reader that
  matches the writer later gets the request by HEARTBEAT/ACKNACK: in every run every added
  sample was held and every query answered). Here the answer is kept (the request was executed
  once; only its answer is sent again) and sent as soon as the server has matched the client.

How it is sent later: rmw waits for the match with the GIL held, so a loop of attempts stalls
every other client of the node. It did: the server tried for up to 2 s and then gave the answer
up, and for the next 10 s gave every late client a single attempt. Measured with a client the
server never matches (its reader asks for TRANSIENT_LOCAL) sending one query into the load:
every other client waited 2.1-2.6 s and that answer was dropped; a client matched more than 2 s
late lost its answer, and new clients in the next 10 s could lose theirs. Now a failed answer
is parked and the service goes on serving (the same load: longest answer 0.16-1.0 s, nothing
given up). A timer (every `RETRY_PERIOD` s while answers are parked) tries a parked answer
again when a response reader the server had not seen appears in its graph (DDS discovery adds
the reader to the graph in the same callback, just before it is matched), or `FALLBACK_PERIOD`
s after its last attempt (each failed attempt blocks the node for rmw's 100 ms). An answer is
given up only after `ANSWER_PATIENCE` s, longer than any caller waits; a client that has gone
is recognised by rmw (the answer is then dropped as sent). The node's log says when a parked
answer was sent, and when one was given up.

`create_service` makes such a service; every psl node serves through it.
"""
from __future__ import annotations

import threading
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable

from rclpy.node import Node
from rclpy.service import Service

from psl_ros.guard import guard_service
from psl_ros.qos import SERVICES

RETRY_PERIOD = 0.01         # s between looks at the graph while answers are parked
FALLBACK_PERIOD = 1.0       # s after which a parked answer is tried again anyway
ANSWER_PATIENCE = 60.0      # s a parked answer is kept (callers wait 5-30 s)
_TIMEOUT_WARNING = 'failed to send response (timeout)'


def answered(send: Callable[[], None]) -> bool:
    """Runs one attempt `send` to answer a request; False when rmw gave the answer up because
    the client is not matched (its warning `_TIMEOUT_WARNING`; any other warning is shown as
    it would have been)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        send()
    timed_out = False
    for w in caught:
        if _TIMEOUT_WARNING in str(w.message):
            timed_out = True
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return not timed_out


@dataclass
class _Parked:
    response: object
    header: object
    since: float
    tried: float
    readers: frozenset = field(default_factory=frozenset)
    attempts: int = 1


def create_service(node: Node, srv_type, name: str, callback: Callable,
                   callback_group=None) -> Service:
    """``node.create_service`` with the SERVICES QoS, answers sent later to a client whose
    response reader the server has not matched yet (see the module docstring), and a callback
    that answers ``success=False`` instead of ending the node when it raises
    (`psl_ros.guard`)."""
    callback = guard_service(node.get_logger(), name, callback, srv_type.Response)
    service = node.create_service(srv_type, name, callback, qos_profile=SERVICES,
                                  callback_group=callback_group)
    send_once = service.send_response
    logger = node.get_logger()
    reply_topic = 'rr' + node.resolve_service_name(name) + 'Reply'   # rmw's DDS topic
    parked: list[_Parked] = []
    lock = threading.Lock()

    def sent(response, header) -> bool:
        return answered(lambda: send_once(response, header))

    def readers() -> frozenset:
        """The response readers of the service in the node's graph (their gids)."""
        try:
            return frozenset(bytes(i.endpoint_gid) for i in
                             node.get_subscriptions_info_by_topic(reply_topic, no_mangle=True))
        except Exception:  # noqa: BLE001 - an rmw without this name mangling: fallback only
            return frozenset()

    def retry() -> None:
        with lock:
            if not parked:
                timer.cancel()
                return
            now, seen = time.monotonic(), readers()
            for item in list(parked):
                if not (seen - item.readers or now - item.tried >= FALLBACK_PERIOD):
                    continue
                item.readers, item.attempts = seen, item.attempts + 1
                if sent(item.response, item.header):
                    parked.remove(item)
                    logger.info(f'{service.srv_name}: answered a new client after '
                                f'{time.monotonic() - item.since:.2f} s ({item.attempts} '
                                'attempts): it had not been matched yet')
                elif time.monotonic() - item.since >= ANSWER_PATIENCE:
                    parked.remove(item)
                    logger.error(f'{service.srv_name}: a client was not matched within '
                                 f'{ANSWER_PATIENCE:g} s; its answer is lost')
                item.tried = time.monotonic()
            if not parked:
                timer.cancel()

    timer = node.create_timer(RETRY_PERIOD, retry, callback_group=callback_group)
    timer.cancel()

    def send_response(response, header) -> None:
        start = time.monotonic()
        if sent(response, header):
            return
        with lock:
            parked.append(_Parked(response, header, since=start, tried=time.monotonic(),
                                  readers=readers()))
            timer.reset()

    service.send_response = send_response
    return service
