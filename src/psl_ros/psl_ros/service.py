"""Services that do not lose their answers.

Two ways an answer of an rclpy service got lost here (both measured with 8 querying and 2
adding clients on the skill memory, `psl bench memory-load`):
- **Under load**: the answers to all clients of a service travel on one topic that every client
  reads; with rclpy's default keep-last 10 a busy client's own answer is pushed out by the
  others'. `psl_ros.qos.SERVICES` (keep-last 1,000) on the clients and the server.
- **A new client**: `wait_for_service` is true as soon as the *client* has matched the server's
  endpoints, but the server may not have matched the client's response reader yet. Fast DDS
  (rmw_fastrtps, ``rmw_response.cpp``) then waits 100 ms for it and drops the answer with the
  warning "failed to send response (timeout): client will not receive response"; the client
  waits in vain (one run in three of the load test lost a client's first answer so). Here the
  server tries again, for up to `SEND_PATIENCE` seconds, until the client's reader is matched
  (the request was executed once; only its answer is sent again), and logs that it did.

`create_service` makes such a service; every psl node serves through it.
"""
from __future__ import annotations

import time
import warnings
from typing import Callable

from rclpy.node import Node
from rclpy.service import Service

from psl_ros.qos import SERVICES

SEND_PATIENCE = 2.0         # s a server keeps trying to answer a client it has not matched yet
GIVE_UP_WINDOW = 10.0       # s after giving an answer up in which failing answers get one try
_TIMEOUT_WARNING = 'failed to send response (timeout)'


def create_service(node: Node, srv_type, name: str, callback: Callable,
                   callback_group=None) -> Service:
    """``node.create_service`` with the SERVICES QoS and answers resent to a client whose
    response reader the server has not matched yet (see the module docstring)."""
    service = node.create_service(srv_type, name, callback, qos_profile=SERVICES,
                                  callback_group=callback_group)
    send_once = service.send_response
    logger = node.get_logger()
    # after an answer was given up, answers that fail are tried once only for a while: the
    # client is likely gone, and the server must not stall its other clients for it
    hasty_until = [0.0]

    def send_response(response, header) -> None:
        start = time.monotonic()
        patience = 0.0 if start < hasty_until[0] else SEND_PATIENCE
        attempts = 0
        while True:
            attempts += 1
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter('always')
                send_once(response, header)
            if not any(_TIMEOUT_WARNING in str(w.message) for w in caught):
                for w in caught:           # anything else is shown as it would have been
                    warnings.showwarning(w.message, w.category, w.filename, w.lineno)
                if attempts > 1:
                    logger.info(f'{service.srv_name}: answered a new client after '
                                f'{time.monotonic() - start:.2f} s ({attempts} attempts): it '
                                'had not been matched yet')
                return
            if time.monotonic() - start >= patience:
                hasty_until[0] = time.monotonic() + GIVE_UP_WINDOW
                logger.error(f'{service.srv_name}: a client was not matched within '
                             f'{patience:g} s (gone?); its answer is lost')
                return

    service.send_response = send_response
    return service
