"""Scheduling helpers of the realtime loop: the priority is what the kernel then reports, and
pacing never returns before its deadline."""
import os
import threading
import time

import pytest

from psl_ros.realtime import raise_priority, sleep_until


def in_thread(function):
    """Run function in a thread of its own (so the test process keeps its scheduling)."""
    out = {}
    thread = threading.Thread(target=lambda: out.update(value=function()))
    thread.start()
    thread.join(timeout=10)
    return out['value']


def test_priority_zero_changes_nothing():
    assert in_thread(lambda: (raise_priority(0), os.sched_getscheduler(0))) == \
        ('normal', os.sched_getscheduler(0))


def fifo_permitted() -> bool:
    """Whether a thread of this process may take SCHED_FIFO (asked of the kernel directly,
    in a thread of its own)."""
    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5))
            return True
        except PermissionError:
            return False
    return in_thread(probe)


def test_a_priority_is_applied_where_permitted_or_the_refusal_said():
    """What the machine allows decides which: SCHED_FIFO where the kernel grants it, the
    refusal said where it does not."""
    said, policy = in_thread(lambda: (raise_priority(5), os.sched_getscheduler(0)))
    if fifo_permitted():
        assert said == 'SCHED_FIFO 5' and policy == os.SCHED_FIFO, said
    else:
        assert said.startswith('normal (SCHED_FIFO not permitted') and policy != os.SCHED_FIFO


@pytest.mark.parametrize('priority', [-1, 100])
def test_priorities_outside_the_range_are_refused(priority):
    with pytest.raises(ValueError, match='0..99'):
        raise_priority(priority)


@pytest.mark.parametrize('margin', [0.0, 0.0005, 0.01])
def test_sleep_until_never_returns_early(margin):
    for delay in (0.0, 0.001, 0.003, -0.001):
        deadline = time.perf_counter() + delay
        sleep_until(deadline, margin)
        assert time.perf_counter() >= deadline
