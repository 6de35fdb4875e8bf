"""Graph mode: each rollout through a rollout worker's ``execute_rollout`` action.

The population is spread over the workers (sim, controller, executor and evaluator running as
processes, each worker under its own namespace), one rollout per worker at a time; lockstep
rollouts do not depend on the worker, so the results are those of one worker. The results
carry the evaluator's evaluation and the measured episode it scored (joint angles, applied
torques, the controller's reference: `trajectory_of`), so that whatever needs trajectories
(ILC of the feed-forward) runs in graph mode as in batch mode.
"""
from __future__ import annotations

import queue
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

from psl_controller.policy import Reference
from psl_optimizer.reward import RewardResult
from psl_optimizer.rollouts import RolloutResult, Rollouts, Stopped, refused_result
from psl_ros.client import RolloutClient
from psl_sim.task import TaskDefinition, task_id


class GraphRollouts(Rollouts):
    """Rollouts of `task` through the given workers' ``execute_rollout``.

    Args:
        task: the task (sent by name, or by its YAML's path when the name does not find it).
        workers: one `RolloutClient` per rollout worker.
        timeout: seconds to wait for one rollout.
        should_stop: asked before every rollout; True raises `Stopped` (a population of graph
            rollouts takes seconds, a cancel should not wait for all of it).
    """

    def __init__(self, task: TaskDefinition, workers: list[RolloutClient],
                 timeout: float = 120.0, should_stop: Callable[[], bool] = lambda: False):
        super().__init__(task)
        if not workers:
            raise ValueError('graph mode needs at least one rollout worker')
        self.workers, self.timeout, self.should_stop = list(workers), timeout, should_stop

    def run(self, thetas: np.ndarray, taus: np.ndarray) -> list[RolloutResult]:
        thetas, taus = self._inputs(thetas, taus)
        if len(self.workers) == 1:
            return self._count([self._one(self.workers[0], tau, theta)
                                for theta, tau in zip(thetas, taus)])
        free: queue.Queue = queue.Queue()
        for worker in self.workers:
            free.put(worker)

        def one(i: int) -> RolloutResult:
            worker = free.get()
            try:
                return self._one(worker, taus[i], thetas[i])
            finally:
                free.put(worker)
        with ThreadPoolExecutor(max_workers=len(self.workers)) as pool:
            return self._count(list(pool.map(one, range(len(thetas)))))

    def _one(self, worker: RolloutClient, tau: np.ndarray, theta: np.ndarray) -> RolloutResult:
        if self.should_stop():
            raise Stopped('stopped between two rollouts')
        result = worker.rollout(task_id(self.task), tau, theta, timeout=self.timeout)
        if not result.success:
            raise RuntimeError(f'rollout failed: {result.message}')
        ev = result.evaluation
        if result.refused:          # the executor's safety check: nothing was executed
            return refused_result(result.refused, ev.reward, ev.component_values[0])
        return RolloutResult(evaluation=RewardResult(
            reward=ev.reward, fulfilled=ev.fulfilled,
            components=dict(zip(ev.component_names, ev.component_values))),
            **trajectory_of(ev))


def trajectory_of(evaluation) -> dict:
    """q, torque and reference (`RolloutResult` fields) of a psl_msgs/RolloutEvaluation: its
    rows reshaped to (num_steps + 1, joints); {} when it carries none or they do not fit."""
    n, rows = len(evaluation.joint_names), evaluation.num_steps + 1
    fields = ('position', 'velocity', 'effort', 'reference_position', 'reference_velocity',
              'reference_effort')
    arrays = [np.asarray(getattr(evaluation, f), dtype=float) for f in fields]
    if n == 0 or any(a.size != rows * n for a in arrays):
        return {}
    q, _, torque, q_ref, qd_ref, u_ffwd = (a.reshape(rows, n) for a in arrays)
    t = np.arange(rows) * evaluation.control_period
    return {'q': q, 'torque': torque,
            'reference': Reference(t=t, q=q_ref, qd=qd_ref, u_ffwd=u_ffwd)}
