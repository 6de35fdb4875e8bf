"""GraphRollouts against workers written here (no graph): a rollout that fails is tried again,
ATTEMPTS times on each worker, before the population fails with the reason and the count; one
that comes through on a later try is the result, on one worker and spread over two. A rollout
a foreign goal preempted is said, counted and run again, not counted as a failed try, up to
PREEMPTIONS times."""
import threading

import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_msgs.action import ExecuteRollout
from psl_optimizer.graph_rollout import ATTEMPTS, PREEMPTIONS, GraphRollouts
from psl_task.task import load_task


class Worker:
    """A rollout worker whose first `failures` rollouts fail with `message` (a homing that
    did not settle, say), the rest succeed with the reward -(index of the call)."""

    def __init__(self, name: str, failures: int, message: str = 'homing did not settle',
                 preempted: int = 0):
        self.name, self.failures, self.message = name, failures, message
        self.preempted = preempted          # then this many rollouts preempted
        self.calls, self.lock = 0, threading.Lock()

    def rollout(self, task, tau, theta, timeout):
        with self.lock:
            self.calls += 1
            call = self.calls
        result = ExecuteRollout.Result()
        if call <= self.failures:
            result.success, result.message = False, self.message
            return result
        if call <= self.failures + self.preempted:
            result.success, result.message = False, PREEMPTED
            result.preempted = PREEMPTED
            return result
        result.success = True
        result.evaluation.reward = -float(call)
        result.evaluation.fulfilled = True
        return result

    def wait_until_ready(self, timeout):
        return None


@pytest.fixture(scope='module')
def task():
    return load_task('reach_over_obstacle')


def population(task, size: int):
    theta = policy_for(task).default_theta
    return np.tile(theta, (size, 1)), np.tile(task.tau_default, (size, 1))


def test_a_failed_rollout_is_tried_again_on_one_worker(task):
    worker = Worker('w', failures=ATTEMPTS - 1)
    results = GraphRollouts(task, [worker]).run(*population(task, 1))
    assert worker.calls == ATTEMPTS
    assert results[0].evaluation.reward == -float(ATTEMPTS)     # the try that came through


def test_a_rollout_that_fails_every_try_fails_with_its_reason(task):
    worker = Worker('w', failures=ATTEMPTS)
    with pytest.raises(RuntimeError, match=f'homing did not settle.*{ATTEMPTS} tries'):
        GraphRollouts(task, [worker]).run(*population(task, 1))
    assert worker.calls == ATTEMPTS


def test_over_two_workers_each_tries_it_before_the_population_fails(task):
    workers = [Worker('a', failures=10**6), Worker('b', failures=10**6)]
    with pytest.raises(RuntimeError, match=f'failed on every rollout worker, {ATTEMPTS} tries'):
        GraphRollouts(task, workers).run(*population(task, 2))
    assert sum(w.calls for w in workers) >= ATTEMPTS * len(workers)
    # and one that comes through on another try is the result
    workers = [Worker('a', failures=1), Worker('b', failures=1)]
    results = GraphRollouts(task, workers).run(*population(task, 2))
    assert all(r.evaluation.fulfilled for r in results)


PREEMPTED = ("the episode's goal was preempted by a goal that is not psl's (the controller: "
             "'Current goal preempted by new incoming action.')")


def test_a_preempted_rollout_is_said_counted_and_run_again(task):
    """A preemption (the executor's `preempted`) is no failed try: after ATTEMPTS - 1
    failures and ATTEMPTS preemptions the rollout still comes through; each preemption is
    one line naming it and counted (`preempted`, `last_preemption`)."""
    lines = []
    worker = Worker('w', failures=ATTEMPTS - 1, preempted=ATTEMPTS)
    rollouts = GraphRollouts(task, [worker], log=lines.append)
    results = rollouts.run(*population(task, 1))
    assert worker.calls == 2 * ATTEMPTS - 1 + 1
    assert results[0].evaluation.reward == -float(worker.calls)
    assert rollouts.preempted == ATTEMPTS and rollouts.last_preemption == PREEMPTED
    assert len(lines) == ATTEMPTS and all(PREEMPTED in line and 'runs again' in line
                                          for line in lines)
    assert rollouts.failed == 0 and rollouts.checked == 1


def test_over_two_workers_a_preempted_rollout_is_run_again(task):
    lines = []
    workers = [Worker('a', failures=0, preempted=1), Worker('b', failures=0, preempted=1)]
    rollouts = GraphRollouts(task, workers, log=lines.append)
    results = rollouts.run(*population(task, 3))
    assert all(r.evaluation.fulfilled for r in results)
    # each worker's first rollout was preempted (a worker may have served none)
    assert rollouts.preempted == sum(w.calls > 0 for w in workers) == len(lines) >= 1
    assert sum(w.calls for w in workers) == 3 + rollouts.preempted


def test_a_rollout_preempted_again_and_again_fails_the_population_with_the_reason(task):
    """Someone keeps commanding the controller: past PREEMPTIONS runs the population fails,
    naming it (a session does not run forever against another client)."""
    worker = Worker('w', failures=0, preempted=10**6)
    with pytest.raises(RuntimeError, match=f'{PREEMPTIONS + 1} times in a row: another client'):
        GraphRollouts(task, [worker], log=lambda _: None).run(*population(task, 1))
    assert worker.calls == PREEMPTIONS + 1
