"""Graph mode: each rollout through a rollout worker's ``execute_rollout`` action.

The population is spread over the workers (sim, controller, executor and evaluator running as
processes, each worker under its own namespace), one rollout per worker at a time; lockstep
rollouts do not depend on the worker, so the results are those of one worker. The results
carry the evaluator's evaluation and the measured episode it scored (joint angles, applied
torques, the controller's reference: `trajectory_of`), so that whatever needs trajectories
(ILC of the feed-forward) runs in graph mode as in batch mode.

A rollout that fails (a homing that did not settle on a robot, a worker that died) is tried
again, up to ATTEMPTS times on each worker, before the population fails: on a robot the next
attempt starts from wherever the arm came to rest; a lockstep rollout's result does not depend
on the attempt. A rollout whose episode a goal that was not psl's preempted (the executor's
``preempted``: someone else commands the robot's controller) is no failure and no result of
the candidate: it is said in one line (`log`), counted (`preempted`, `last_preemption`) and run
again, up to PREEMPTIONS times, from wherever the other goal left the arm (homing brings it
back inside its joint ranges).
"""
from __future__ import annotations

import queue
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

from psl_controller.policy import Reference
from psl_optimizer.reward import RewardResult
from psl_optimizer.rollouts import (RolloutResult, Rollouts, Stopped, aborted_result,
                                     refused_result)
from psl_ros.client import RolloutClient
from psl_ros.timeouts import ROLLOUT_TIMEOUT
from psl_task.task import TaskDefinition, task_id

ATTEMPTS = 2        # tries of a rollout on each worker before the population fails
PREEMPTIONS = 5     # runs of one rollout that foreign goals preempted before the population
                    # fails (someone else keeps commanding the controller)


class RolloutPreempted(RuntimeError):
    """A goal that was not psl's preempted the rollout's episode (the executor's reason)."""


def _to_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class GraphRollouts(Rollouts):
    """Rollouts of `task` through the given workers' ``execute_rollout``.

    Args:
        task: the task (sent by name, or by its YAML's path when the name does not find it).
        workers: one `RolloutClient` per rollout worker.
        timeout: seconds to wait for one rollout.
        should_stop: asked before every rollout; True raises `Stopped` (a population of graph
            rollouts takes seconds, a cancel should not wait for all of it).
        log: where a line for people goes (a preempted rollout run again); stderr by default.
    """

    def __init__(self, task: TaskDefinition, workers: list[RolloutClient],
                 timeout: float = ROLLOUT_TIMEOUT, should_stop: Callable[[], bool] = lambda: False,
                 log: Callable[[str], None] = _to_stderr):
        super().__init__(task)
        if not workers:
            raise ValueError('graph mode needs at least one rollout worker')
        self.workers, self.timeout, self.should_stop = list(workers), timeout, should_stop
        self.log = log
        self._count_lock = threading.Lock()     # preemptions are counted from every worker

    def run(self, thetas: np.ndarray, taus: np.ndarray) -> list[RolloutResult]:
        thetas, taus = self._inputs(thetas, taus)
        if len(self.workers) == 1:
            return self._count([self._tried(self.workers[0], tau, theta)
                                for theta, tau in zip(thetas, taus)])
        return self._count(self._spread(thetas, taus))

    def _tried(self, worker: RolloutClient, tau: np.ndarray, theta: np.ndarray
               ) -> RolloutResult:
        """`_one`, tried again after a failure, ATTEMPTS times in all (the last error raised
        with the number of tries), and run again after a preemption (`_preempted`)."""
        failures = preemptions = 0
        while True:
            try:
                return self._one(worker, tau, theta)
            except RolloutPreempted as exc:
                preemptions += 1
                self._preempted(worker, exc, preemptions)
            except (RuntimeError, TimeoutError) as exc:
                failures += 1
                if failures == ATTEMPTS:
                    raise RuntimeError(f'{exc} ({ATTEMPTS} tries)') from None

    def _preempted(self, worker: RolloutClient, exc: RolloutPreempted, times: int) -> None:
        """Count a preemption of a rollout's episode and say it (one line); RuntimeError once
        the rollout was preempted more than PREEMPTIONS times."""
        with self._count_lock:
            self.preempted += 1
            self.last_preemption = str(exc)
        if times > PREEMPTIONS:
            raise RuntimeError(f'{worker.name}: {exc}, {times} times in a row: another client '
                               'keeps commanding the controller') from None
        self.log(f'{worker.name}: {exc}; the rollout runs again (not counted against the '
                 f'candidate; preemption {times} of at most {PREEMPTIONS})')

    def _spread(self, thetas: np.ndarray, taus: np.ndarray) -> list[RolloutResult]:
        """The population over the workers, one rollout per worker at a time. A worker whose
        rollout fails (its node died, it does not answer) fails alone: the rollout goes back
        in the queue for another worker (lockstep rollouts do not depend on the worker, so
        the result is the same), and the failed worker waits for its loop to come back (a
        restarted worker) before it takes another one. A rollout that fails on every worker,
        or with no worker left, raises with the reasons."""
        pending: queue.Queue = queue.Queue()
        for i in range(len(thetas)):
            pending.put(i)
        results: list[RolloutResult | None] = [None] * len(thetas)
        failures: dict[int, list[tuple[str, str]]] = {}   # rollout -> (worker, error) per try
        preemptions = [0] * len(thetas)                     # rollout -> times preempted
        lock = threading.Lock()
        alive = [len(self.workers)]
        abort = threading.Event()               # a cancel or an error: every worker stops

        def finished() -> bool:
            with lock:
                return abort.is_set() or all(r is not None for r in results) or \
                    any(len(f) >= ATTEMPTS * alive[0] for f in failures.values())

        def back(worker: RolloutClient) -> bool:
            """Wait until the worker's loop is up again; False after `timeout` or when the
            population is done without it."""
            deadline = time.monotonic() + self.timeout
            while not finished() and time.monotonic() < deadline:
                try:
                    worker.wait_until_ready(1.0)
                    return True
                except TimeoutError:
                    pass
            return False

        def serve(worker: RolloutClient) -> None:
            try:
                while not finished():
                    try:
                        i = pending.get(timeout=0.1)
                    except queue.Empty:
                        continue
                    try:
                        results[i] = self._one(worker, taus[i], thetas[i])
                    except RolloutPreempted as exc:      # no failure: run it again
                        with lock:
                            preemptions[i] += 1
                        self._preempted(worker, exc, preemptions[i])
                        pending.put(i)
                    except (RuntimeError, TimeoutError) as exc:
                        with lock:
                            failures.setdefault(i, []).append((worker.name, str(exc)))
                        pending.put(i)
                        if not back(worker):
                            return
            except BaseException:
                abort.set()
                raise
            finally:
                with lock:
                    alive[0] -= 1

        with ThreadPoolExecutor(max_workers=len(self.workers)) as pool:
            futures = [pool.submit(serve, worker) for worker in self.workers]
            for future in futures:
                future.result()              # Stopped (a cancel) and bugs surface here
        missing = [i for i, r in enumerate(results) if r is None]
        if missing:
            last = dict(failures.get(missing[0], []))      # each worker's last error
            reasons = '; '.join(f'{w}: {e}' for w, e in last.items()) or 'no worker left'
            raise RuntimeError(f'{len(missing)} rollouts of the population failed on every '
                               f'rollout worker, {ATTEMPTS} tries each ({reasons})')
        return results

    def _one(self, worker: RolloutClient, tau: np.ndarray, theta: np.ndarray) -> RolloutResult:
        if self.should_stop():
            raise Stopped('stopped between two rollouts')
        result = worker.rollout(task_id(self.task), tau, theta, timeout=self.timeout)
        if result.preempted:        # someone else's goal: nothing of the candidate ran
            raise RolloutPreempted(result.preempted)
        if not result.success:
            raise RuntimeError(f'rollout failed: {result.message}')
        ev = result.evaluation
        if result.refused:          # the executor's safety check: nothing was executed
            return refused_result(result.refused, ev.reward, ev.component_values[0])
        if result.aborted:          # the controller stopped the episode: the penalty
            return aborted_result(result.aborted, ev.reward, ev.component_values[0])
        return RolloutResult(evaluation=RewardResult(
            reward=ev.reward, fulfilled=ev.fulfilled,
            components=dict(zip(ev.component_names, ev.component_values)),
            failure=ev.failure), **trajectory_of(ev))


def trajectory_of(evaluation) -> dict:
    """q, torque, reference and the observed bodies' poses (`RolloutResult` fields) of a
    psl_msgs/RolloutEvaluation: its rows reshaped to (num_steps + 1, joints) and
    (num_steps + 1, 7) per body; {} when it carries no trajectory or it does not fit."""
    n, rows = len(evaluation.joint_names), evaluation.num_steps + 1
    fields = ('position', 'velocity', 'effort', 'reference_position', 'reference_velocity',
              'reference_effort')
    arrays = [np.asarray(getattr(evaluation, f), dtype=float) for f in fields]
    if n == 0 or any(a.size != rows * n for a in arrays):
        return {}
    q, _, torque, q_ref, qd_ref, u_ffwd = (a.reshape(rows, n) for a in arrays)
    t = np.arange(rows) * evaluation.control_period
    bodies = list(evaluation.observed_bodies)
    poses = np.asarray(evaluation.observed_poses, dtype=float)
    world = ({body: block for body, block in zip(bodies, poses.reshape(len(bodies), rows, 7))}
             if poses.size == len(bodies) * rows * 7 else None)
    return {'q': q, 'torque': torque, 'world': world,
            'reference': Reference(t=t, q=q_ref, qd=qd_ref, u_ffwd=u_ffwd)}
