"""The oracle of the dynamics modality: inverse dynamics from the simulator's own model.

Along the commanded trajectory (q_ref, qd_ref and the acceleration that takes qd_ref from one
control period to the next) `mujoco.mj_inverse` gives the joint torques that make the model,
with the task instance's parameters applied (e.g. the payload mass), follow it; projected onto
the feed-forward basis by least squares they give theta_D_oracle. A comparison for the learned
feed-forward only: the learner never sees it. Imports no ROS.
"""
from __future__ import annotations

import numpy as np

from psl_controller.policy import Reference, TaskPolicy, policy_for
from psl_task.arm_model import ArmModel
from psl_task.safety_check import reference_acceleration
from psl_task.task import TaskDefinition


def inverse_dynamics_torque(task: TaskDefinition, tau: np.ndarray,
                            reference: Reference) -> np.ndarray:
    """Joint torques (T, n) that realise the reference on the task instance tau.

    The acceleration at control period k is the forward difference
    ``(qd_ref[k+1] - qd_ref[k]) / dt`` (the last period repeats the one before): with one
    semi-implicit Euler physics step per period, that is the acceleration that reaches the next
    commanded velocity.

    Raises:
        TaskError: tau outside the task's ranges.
    """
    return ArmModel(task).inverse_dynamics(task.validate_tau(tau), reference.q, reference.qd,
                                           reference_acceleration(reference.qd,
                                                                  task.control_period))


def oracle_theta_d(task: TaskDefinition, tau: np.ndarray, theta: np.ndarray,
                   policy: TaskPolicy | None = None) -> np.ndarray:
    """theta_D that encodes the inverse-dynamics torque of theta's commanded trajectory.

    Raises:
        ValueError: a task without feed-forward, or a theta of the wrong size.
    """
    policy = policy or policy_for(task)
    if not policy.has_feedforward:
        raise ValueError(f'task {task.name!r} has no feed-forward (policy.feedforward)')
    reference = policy.reference(theta, tau)
    torque = inverse_dynamics_torque(task, tau, reference)
    return policy.feedforward_for(tau).fit(reference.t, torque)


def oracle_theta(task: TaskDefinition, tau: np.ndarray, theta: np.ndarray,
                 policy: TaskPolicy | None = None) -> np.ndarray:
    """theta with its theta_D replaced by the oracle's (theta_K, the commanded path, kept)."""
    policy = policy or policy_for(task)
    return policy.with_feedforward(theta, oracle_theta_d(task, tau, theta, policy))
