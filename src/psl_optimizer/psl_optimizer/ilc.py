"""Iterative learning control of theta_D: the second optimiser of the dynamics modality.

After each rollout the torque the PD feedback had to add, ``u_fb(t) = Kp (q_ref - q) +
Kd (qd_ref - qd)``, is what the feed-forward lacked. Taken ``lead`` seconds ahead (the feedback
reacts late to an error the feed-forward must prevent; without the lead the update oscillates)
and projected onto the feed-forward basis, a share ``gain`` of it is added to theta_D::

    theta_D <- theta_D + gain * fit(u_fb(t + lead))

One rollout per iteration; the commanded path (theta_K) is left as it is. It stops at the first
rollout that fulfils the task instance, when the budget is spent, or after ``patience``
iterations in a row without a better reward. Batch mode only (it needs the joint trajectory,
not only the reward). Imports no ROS.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from psl_optimizer.batch_rollout import BatchRollout
from psl_optimizer.policy_search import SearchResult


@dataclasses.dataclass(frozen=True)
class ILCSettings:
    iterations: int = 30           # rollouts at most
    gain: float = 0.5              # share of the projected feedback torque added per iteration
    lead: float = 0.1              # s, how far ahead the feedback torque is taken
    patience: int = 10             # iterations in a row without a better reward before stopping

    def __post_init__(self):
        if self.iterations < 0 or self.patience < 1:
            raise ValueError('iterations must be >= 0 and patience >= 1')
        if not 0.0 < self.gain <= 1.0 or self.lead < 0.0:
            raise ValueError(f'gain must be in (0, 1] and lead >= 0, got {self.gain}, '
                             f'{self.lead}')


def feedback_torque(batch: BatchRollout, theta: np.ndarray, result) -> np.ndarray:
    """The PD part of the torque applied at each control period (T, n): the applied torque
    (after clipping) minus the feed-forward; the last period repeats the one before."""
    reference = batch.policy.reference(theta)
    applied = result.torque[1:]                       # row k+1: torque applied in step k
    feedback = applied - reference.u_ffwd[:-1]
    return np.vstack([feedback, feedback[-1:]])


def ilc_step(batch: BatchRollout, theta: np.ndarray, result, settings: ILCSettings
             ) -> np.ndarray:
    """theta with theta_D updated from one rollout's feedback torque (see the module doc)."""
    policy = batch.policy
    feedback = feedback_torque(batch, theta, result)
    shift = int(round(settings.lead / batch.task.control_period))
    ahead = np.vstack([feedback[shift:], np.repeat(feedback[-1:], min(shift, len(feedback)),
                                                   axis=0)])[:len(feedback)]
    t = np.arange(len(feedback)) * batch.task.control_period
    update = policy.feedforward.fit(t, ahead)
    return policy.with_feedforward(theta, theta[policy.dynamics] + settings.gain * update)


def ilc_search(batch: BatchRollout, tau: np.ndarray, start: np.ndarray,
               settings: ILCSettings = ILCSettings()) -> SearchResult:
    """ILC on theta_D from `start` for task instance tau; every rollout counted.

    Raises:
        ValueError: a task without feed-forward.
    """
    if not batch.policy.has_feedforward:
        raise ValueError(f'task {batch.task.name!r} has no feed-forward to learn')
    theta = np.asarray(start, dtype=float).copy()
    rewards: list[float] = []
    best_theta, best_reward, fulfilled, idle = theta, -np.inf, False, 0
    for _ in range(settings.iterations):
        result = batch.run(theta[None], tau)[0]
        reward = result.evaluation.reward
        rewards.append(reward)
        if reward > best_reward:
            best_theta, best_reward, idle = theta, reward, 0
        else:
            idle += 1
        if result.evaluation.fulfilled:
            best_theta, best_reward, fulfilled = theta, reward, True
            break
        if idle >= settings.patience:
            break
        theta = ilc_step(batch, theta, result, settings)
    return SearchResult(theta=best_theta.copy(), reward=float(best_reward), fulfilled=fulfilled,
                        rollouts=len(rewards), start_theta=np.asarray(start, dtype=float),
                        rewards=rewards)
