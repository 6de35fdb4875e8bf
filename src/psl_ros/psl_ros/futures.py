"""Waiting for an rclpy future from a thread that is not spinning it.

Service calls and action goals made from a callback or a plain thread complete on the
executor's other threads; this blocks on an event instead of spinning, with a timeout that
names what did not answer. Used by the executor (sim/reset), the learner (memory services,
execute_rollout) and the CLI's client.
"""
from __future__ import annotations

import threading
from typing import Callable


def wait_for(future, timeout: float, what: str):
    """The future's result; TimeoutError naming `what` when none comes within `timeout` s."""
    event = threading.Event()
    future.add_done_callback(lambda _: event.set())
    if not event.wait(timeout):
        raise TimeoutError(f'no answer from {what} within {timeout:.0f} s')
    return future.result()


def ask(call: Callable[[], object], timeout: float, what: str, attempts: int = 3):
    """The answer to an idempotent request (``call()`` sends it and returns its future), sent
    again after `timeout` s without one, up to `attempts` times; TimeoutError after the last.
    For services that do not keep an answer they cannot send yet (rclpy's parameter
    services): a request or its answer sent while the two ends are not yet matched in DDS is
    lost ("failed to send response (timeout)" in the server's log), and only a new request
    gets through."""
    for attempt in range(attempts):
        try:
            return wait_for(call(), timeout, what)
        except TimeoutError:
            if attempt == attempts - 1:
                raise TimeoutError(f'no answer from {what} to {attempts} requests of '
                                   f'{timeout:.0f} s each') from None
