"""Waiting for an rclpy future from a thread that is not spinning it.

Service calls and action goals made from a callback or a plain thread complete on the
executor's other threads; this blocks on an event instead of spinning, with a timeout that
names what did not answer. Used by the executor (sim/reset), the learner (memory services,
execute_rollout) and the CLI's client.
"""
from __future__ import annotations

import threading


def wait_for(future, timeout: float, what: str):
    """The future's result; TimeoutError naming `what` when none comes within `timeout` s."""
    event = threading.Event()
    future.add_done_callback(lambda _: event.set())
    if not event.wait(timeout):
        raise TimeoutError(f'no answer from {what} within {timeout:.0f} s')
    return future.result()
