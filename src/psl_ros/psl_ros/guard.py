"""The last line of defence of a node's callbacks: an exception nobody expected becomes a
refused request and an error in the node's log, never a dead node.

rclpy lets an exception raised in a service or subscription callback out of ``spin()``: the
node ends, and ``psl up`` then ends the whole graph. Every callback validates its input first
and answers with a reason (a wrong size, NaN, a path outside its folder); these wrappers catch
what slipped through (a number that overflows, an OSError nobody thought of), so one request
can never take a node down. `psl_ros.service.create_service` wraps every service this way;
nodes wrap their rclpy subscriptions with `guard_subscription` (the hot path's loop catches its
callbacks' exceptions itself).
"""
from __future__ import annotations

import traceback
from typing import Callable

MESSAGE_LIMIT = 500     # characters of an exception's text put into a response


def describe(exc: BaseException) -> str:
    """``Type: text`` of an exception, at most MESSAGE_LIMIT characters."""
    text = f'{type(exc).__name__}: {exc}'
    return text if len(text) <= MESSAGE_LIMIT else text[:MESSAGE_LIMIT - 3] + '...'


def guard_service(logger, name: str, callback: Callable, response_type) -> Callable:
    """`callback(request, response)` that answers ``success=False`` with the exception as
    its message when it raises (the response type must have ``success`` and ``message``)."""
    def guarded(request, response):
        try:
            return callback(request, response)
        except Exception as exc:  # noqa: BLE001 - the point: nothing ends the node
            logger.error(f'{name}: a request failed unexpectedly, refused: {describe(exc)}\n'
                         + traceback.format_exc())
            refused = response_type()
            refused.success = False
            refused.message = f'refused: the request failed in the node ({describe(exc)})'
            return refused
    return guarded


def guard_subscription(logger, topic: str, callback: Callable) -> Callable:
    """`callback(msg)` that logs an exception it raises and drops the message."""
    def guarded(msg):
        try:
            return callback(msg)
        except Exception as exc:  # noqa: BLE001 - the point: nothing ends the node
            logger.error(f'{topic}: a message was dropped, its callback failed: '
                         f'{describe(exc)}\n' + traceback.format_exc())
    return guarded
