"""Iterative learning control of theta_D: the second optimiser of the dynamics modality.

After each rollout the torque the PD feedback had to add (`PDLaw.feedback`: the applied torque
minus the feed-forward, after clipping), is what the feed-forward lacked. Taken ``lead`` seconds ahead (the feedback
reacts late to an error the feed-forward must prevent; without the lead the update oscillates)
and projected onto the feed-forward basis, a share ``gain`` of it is added to theta_D::

    theta_D <- theta_D + gain * fit(u_fb(t + lead))

A task whose DMP runs over the hand position with a learned goal point (``policy.space:
end_effector``, ``learn_goal``) and has a target also gets the goal corrected by the hand's
measured miss at the end of the rollout (the same iteration in task space)::

    g <- g - goal_gain * (x_hand(T) - x_target)

and, when its DMP also moves the hand's orientation (``policy.orientation``) and its reward
scores the orientation (``orientation_error``), the goal orientation is turned by that share of
the rotation from the hand's final orientation to the target's (quaternions, world frame)::

    g_o <- exp(goal_gain * log(q_target * conj(q_hand(T)))) * g_o

Otherwise the commanded path (theta_K) is left as it is.

When it stops. The theta it returns becomes a sample of the skill, and the skill interpolates
between its samples: a sample taken at the first rollout past the success threshold is
whatever mix of feed-forward and goal offset crossed it first (the goal takes up the sag
at once, the feed-forward catches up over the iterations), so neighbouring instances give
contradicting samples, and a skill between samples that barely fulfil their instances
misses its own. So ILC goes on past the first fulfilling rollout to its fixed point, as far
as the reward shows it: while each fulfilling rollout betters the best one by more than
``min_gain`` of its magnitude, and unless the step it would take next is below
``converged`` (in the search's units, CMA-ES's normalised coordinates: then the sample is
converged already, and no rollout is spent to find that out). It returns the best fulfilling
rollout's theta. It also stops when the budget is spent, or after ``patience`` iterations in a
row without a better reward. Measured on TALOS's arm as published, point_reach_3d and
payload_transport: docs/benchmarks.md, "Generalisation on arms as published".

It needs the applied torque of each rollout: it asks the results
(`RolloutResult.has_trajectory`) and ends after the first rollout whose result carries none
(the caller's search goes on from there). Imports no ROS.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from psl_controller.pd_law import PDLaw
from psl_controller.policy import TaskPolicy
from psl_optimizer.policy_search import SearchResult
from psl_optimizer.rollouts import RolloutResult, Rollouts
from psl_task import quaternion
from psl_task.quaternion import quaternion_of


@dataclasses.dataclass(frozen=True)
class ILCSettings:
    iterations: int = 30           # rollouts at most
    gain: float = 0.5              # share of the projected feedback torque added per iteration
    goal_gain: float = 1.0         # share of the hand's final miss taken off a learned goal point
    lead: float = 0.1              # s, how far ahead the feedback torque is taken
    patience: int = 10             # iterations in a row without a better reward before stopping
    # past the first fulfilling rollout (module docstring): go on while each fulfilling rollout
    # betters the best fulfilling one before it by more than this share of its magnitude ...
    min_gain: float = 0.1
    # ... unless the next step moves no entry by more than this, in the search's units
    converged: float = 0.05

    def __post_init__(self):
        if self.iterations < 0 or self.patience < 1:
            raise ValueError('iterations must be >= 0 and patience >= 1')
        if not (self.min_gain >= 0.0 and self.converged >= 0.0):
            raise ValueError(f'min_gain and converged must be >= 0, got {self.min_gain} and '
                             f'{self.converged}')
        if not 0.0 < self.gain <= 1.0 or self.lead < 0.0 or not 0.0 <= self.goal_gain <= 1.0:
            raise ValueError(f'gain must be in (0, 1], goal_gain in [0, 1] and lead >= 0, got '
                             f'{self.gain}, {self.goal_gain}, {self.lead}')


def feedback_torque(result: RolloutResult) -> np.ndarray:
    """The PD part of the torque applied at each control period (T, n) of a measured rollout
    (`PDLaw.feedback`); the last period repeats the one before."""
    applied = result.torque[1:]                       # row k+1: torque applied in step k
    feedback = PDLaw.feedback(applied, result.reference.u_ffwd[:-1])
    return np.vstack([feedback, feedback[-1:]])


def ilc_step(policy: TaskPolicy, theta: np.ndarray, result: RolloutResult,
             settings: ILCSettings, tau: np.ndarray | None = None) -> np.ndarray:
    """theta with theta_D updated from one rollout's feedback torque on task instance tau
    (see the module doc)."""
    feedback = feedback_torque(result)
    dt = policy.task.control_period
    shift = int(round(settings.lead / dt))
    ahead = np.vstack([feedback[shift:], np.repeat(feedback[-1:], min(shift, len(feedback)),
                                                   axis=0)])[:len(feedback)]
    t = np.arange(len(feedback)) * dt
    update = policy.feedforward_for(tau).fit(t, ahead)
    theta = policy.with_feedforward(theta, theta[policy.dynamics] + settings.gain * update)
    if corrects_goal(policy):
        hand, hand_quat = policy.ik.pose(result.q[-1])
        target, rotation = policy.task.target_of(tau)
        theta[policy.goal] -= settings.goal_gain * (hand - target)
        if corrects_orientation(policy):
            turn = quaternion.log_map(quaternion.product(quaternion_of(rotation),
                                                         quaternion.conjugate(hand_quat)))
            goal = theta[policy.orientation_goal]
            theta[policy.orientation_goal] = quaternion.log_map(quaternion.product(
                quaternion.exp_map(settings.goal_gain * turn), quaternion.exp_map(goal)))
    return theta


def corrects_goal(policy: TaskPolicy) -> bool:
    """True when ILC also corrects the goal: a learned hand goal point and a target."""
    return (policy.ik is not None and policy.task.policy.learn_goal
            and policy.task.target is not None)


def corrects_orientation(policy: TaskPolicy) -> bool:
    """True when ILC also turns a learned goal orientation: `corrects_goal`, a pose DMP and a
    reward that scores the hand's orientation."""
    return (corrects_goal(policy) and policy.controls_orientation
            and policy.task.reward.weights.get('orientation_error', 0.0) > 0.0)


def ilc_search(rollouts: Rollouts, tau: np.ndarray, start: np.ndarray,
               settings: ILCSettings = ILCSettings(),
               scale: np.ndarray | None = None) -> SearchResult:
    """ILC on theta_D from `start` for task instance tau; every rollout counted; `scale`
    (F,): the search's units of theta (`psl_optimizer.learning.search_normalisation`), in
    which a step is `converged` (None: no step counts as converged).

    Raises:
        ValueError: a task without feed-forward.
    """
    policy = rollouts.policy
    if not policy.has_feedforward:
        raise ValueError(f'task {rollouts.task.name!r} has no feed-forward to learn')
    theta = np.asarray(start, dtype=float).copy()
    rewards: list[float] = []
    best_theta, best_reward, fulfilled, idle = theta, -np.inf, False, 0
    for _ in range(settings.iterations):
        result = rollouts.run(theta[None], tau)[0]
        reward = result.evaluation.reward
        rewards.append(reward)
        if result.evaluation.fulfilled:
            gained = reward > best_reward + settings.min_gain * abs(best_reward)
            if not fulfilled or reward > best_reward:
                best_theta, best_reward = theta, reward
            if fulfilled and not gained:
                break                       # the fulfilling rollouts have stopped gaining
            fulfilled, idle = True, 0
        elif fulfilled:
            break                           # the step left the fulfilling ones: the best stays
        elif reward > best_reward:
            best_theta, best_reward, idle = theta, reward, 0
        else:
            idle += 1
        if idle >= settings.patience or not result.has_trajectory:
            break
        step = ilc_step(policy, theta, result, settings, tau)
        if fulfilled and scale is not None and (
                np.abs((step - theta) / scale).max() < settings.converged):
            break                           # converged: the next rollout would gain nothing
        theta = step
    return SearchResult(theta=best_theta.copy(), reward=float(best_reward), fulfilled=fulfilled,
                        rollouts=len(rewards), start_theta=np.asarray(start, dtype=float),
                        rewards=rewards)
