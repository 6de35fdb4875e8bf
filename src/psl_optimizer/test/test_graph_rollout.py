"""GraphRollouts against workers written here (no graph): a rollout that fails is tried again,
ATTEMPTS times on each worker, before the population fails with the reason and the count; one
that comes through on a later try is the result, on one worker and spread over two."""
import threading

import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_msgs.action import ExecuteRollout
from psl_optimizer.graph_rollout import ATTEMPTS, GraphRollouts
from psl_task.task import load_task


class Worker:
    """A rollout worker whose first `failures` rollouts fail with `message` (a homing that
    did not settle, say), the rest succeed with the reward -(index of the call)."""

    def __init__(self, name: str, failures: int, message: str = 'homing did not settle'):
        self.name, self.failures, self.message = name, failures, message
        self.calls, self.lock = 0, threading.Lock()

    def rollout(self, task, tau, theta, timeout):
        with self.lock:
            self.calls += 1
            call = self.calls
        result = ExecuteRollout.Result()
        if call <= self.failures:
            result.success, result.message = False, self.message
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
