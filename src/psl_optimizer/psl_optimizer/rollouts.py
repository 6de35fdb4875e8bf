"""The one rollout interface the learner sees: ``run(thetas, taus) -> results``.

Two implementations, one per way of running a rollout (DESIGN.md section 3):
- ``batch``: `psl_optimizer.batch_rollout.BatchRollouts`, a whole population in-process with
  ``mujoco.rollout``;
- ``graph``: `psl_optimizer.graph_rollout.GraphRollouts`, each rollout through a rollout
  worker's ``execute_rollout`` action (sim, controller, executor, evaluator as processes).
Nothing else in the learner knows which one it has. A result carries the evaluation and, when
the implementation measured them, the joint trajectory, the applied torque and the reference
of the rollout; whatever needs trajectories (ILC) asks the result (`has_trajectory`), not the
mode. Imports no ROS.
"""
from __future__ import annotations

import abc
import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from psl_task.task import TaskDefinition

if TYPE_CHECKING:     # the command line reads MODES without loading the physics
    from psl_controller.policy import Reference, TaskPolicy
    from psl_optimizer.reward import RewardResult

MODES = ('batch', 'graph')


class Stopped(Exception):
    """The owner of the rollouts asked them to stop (e.g. a cancelled goal)."""


@dataclasses.dataclass(frozen=True)
class RolloutResult:
    """One rollout of a population: its evaluation and, if measured, its trajectories."""

    evaluation: RewardResult
    q: np.ndarray | None = None            # (N+1, n) measured joint angles, S_0..S_N
    torque: np.ndarray | None = None       # (N+1, n) torque applied in the step before each
                                           # state (row 0: 0)
    reference: Reference | None = None     # the commanded trajectory on the same grid
    refused: str = ''                      # the safety check's reason: nothing was executed
    aborted: str = ''                      # the controller's reason: the episode was stopped
    world: dict | None = None              # {body: (N+1, 7)} poses of the bodies the task
                                           # observes (reward.observe), when measured
    qpos: np.ndarray | None = None         # (N+1, nq) the model's whole qpos, passive joints
                                           # too (batch mode: what psl render draws)

    @property
    def has_trajectory(self) -> bool:
        """True when q, torque and reference were measured (not only the evaluation)."""
        return self.q is not None and self.torque is not None and self.reference is not None

    @property
    def q_ref(self) -> np.ndarray | None:
        """The commanded joint angles (N+1, n)."""
        return None if self.reference is None else self.reference.q


def refused_result(reason: str, reward: float, violation: float) -> RolloutResult:
    """The result of a candidate the safety check refused (`psl_task.safety_check`): the
    penalty reward, not fulfilled, its violation as the one component, no trajectory."""
    from psl_optimizer.reward import RewardResult

    return RolloutResult(evaluation=RewardResult(
        reward=float(reward), fulfilled=False, components={'safety_violation': float(violation)}),
        refused=reason)


def aborted_result(reason: str, reward: float, violation: float) -> RolloutResult:
    """The result of an episode the controller aborted (its tracking error passed the task's
    ``safety.max_tracking_error``): the penalty reward, not fulfilled, the violation as the one
    component, no trajectory (what ran is no sample of the candidate)."""
    from psl_optimizer.reward import RewardResult

    return RolloutResult(evaluation=RewardResult(
        reward=float(reward), fulfilled=False, components={'tracking_abort': float(violation)}),
        aborted=reason)


class Rollouts(abc.ABC):
    """Rollouts of one task's policies on its task instances. `checked` counts the candidates
    run (each one passed the safety check or was refused by it), `refused` those refused,
    `failed` those a reward component could not score (`last_failure`: the newest reason),
    `preempted` the episodes a goal that was not psl's preempted on a robot, each run again
    (graph mode; `last_preemption`: the newest reason)."""

    def __init__(self, task: TaskDefinition):
        from psl_controller.policy import policy_for

        self.task = task
        self.policy: TaskPolicy = policy_for(task)
        self.checked = self.refused = self.failed = self.preempted = 0
        self.last_failure = self.last_preemption = ''

    def _count(self, results: list[RolloutResult]) -> list[RolloutResult]:
        self.checked += len(results)
        self.refused += sum(1 for r in results if r.refused)
        failures = [r.evaluation.failure for r in results if r.evaluation.failure]
        self.failed += len(failures)
        self.last_failure = failures[-1] if failures else self.last_failure
        return results

    @abc.abstractmethod
    def run(self, thetas: np.ndarray, taus: np.ndarray) -> list[RolloutResult]:
        """Roll out thetas (B, F) on task instances taus (B, E) or one tau (E,); one result per
        theta, in order.

        Raises:
            TaskError: a tau the task refuses; ValueError: a theta of the wrong size or not
            finite; RuntimeError / TimeoutError: the rollouts could not be run.
        """

    def evaluate(self, thetas: np.ndarray, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rewards (B,) and fulfilled flags (B,) of `run`."""
        results = self.run(thetas, taus)
        return (np.array([r.evaluation.reward for r in results]),
                np.array([r.evaluation.fulfilled for r in results]))

    def _inputs(self, thetas: np.ndarray, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """thetas (B, F) and validated taus (B, E), one tau broadcast to every theta."""
        thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
        taus = np.asarray(taus, dtype=float)
        taus = np.broadcast_to(taus, (len(thetas), taus.shape[-1])) if taus.ndim == 1 else taus
        if len(taus) != len(thetas):
            raise ValueError(f'{len(thetas)} thetas but {len(taus)} task instances')
        return thetas, np.array([self.task.validate_tau(t) for t in taus])
