"""Scheduling for the realtime loop: thread priority and pacing to a deadline.

`raise_priority` puts the calling thread under ``SCHED_FIFO`` at the given priority when the
machine allows it (root, or CAP_SYS_NICE / an rtprio limit); threads it starts afterwards
inherit it. A FIFO thread runs before every normal one as soon as it wakes, so a busy core
delays the control loop's wake-up and the controller's answer by microseconds rather than by a
scheduler slice. Every thread that gets it must block between periods (sleep, wait-set), never
spin without end. `sleep_until` paces a loop: sleep until ``margin`` s before the deadline (the
kernel's wake-up is late by tens of microseconds), then spin to it — the spin costs about
``margin / period`` of a core. On the 2-core machine of docs/benchmarks.md neither lowered the
deadline misses with a core kept busy (a FIFO loop that spins even raised them: the DDS threads
that bring the commands run at normal priority and wait for it), so the nodes use neither
unless asked. Imports no ROS.
"""
from __future__ import annotations

import os
import time


def raise_priority(priority: int) -> str:
    """SCHED_FIFO at `priority` (1..99) for the calling thread; 0 leaves it as it is.
    Returns what was done, e.g. 'SCHED_FIFO 20' or 'normal (SCHED_FIFO not permitted: ...)'.

    Raises:
        ValueError: a priority outside 0..99.
    """
    if not 0 <= priority <= 99:
        raise ValueError(f'realtime_priority must be in 0..99, got {priority}')
    if priority == 0:
        return 'normal'
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError, AttributeError) as exc:
        return f'normal (SCHED_FIFO not permitted: {exc})'
    return f'SCHED_FIFO {priority}'


def sleep_until(deadline: float, margin: float) -> None:
    """Return at `deadline` (time.perf_counter seconds): sleep until `margin` s before it,
    then spin."""
    delay = deadline - time.perf_counter() - margin
    if delay > 0:
        time.sleep(delay)
    while time.perf_counter() < deadline:
        pass
