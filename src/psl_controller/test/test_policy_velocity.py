"""TALOS's left arm as published (examples/talos_arm_point_reach.yaml: a URDF whose wrist joints
allow 1.76 rad/s): the end-effector references the policy builds (the differential IK bounded
by ``ArmModel.limits.velocity``; psl_task.inverse_kinematics, "Joint velocity bounds") keep the
joint velocity bounds and pass the safety check, which refuses what the controllers psl serves
reject (psl_task.joint_limits): the default theta (the demonstration, whose plain minimum-norm
IK moves the wrist at 2.49 rad/s) and seeded perturbations of its kinematic part."""

from pathlib import Path

import numpy as np
import pytest

from psl_controller.policy import TaskPolicy
from psl_task.arm_model import ArmModel
from psl_task.inverse_kinematics import VELOCITY_MARGIN
from psl_task.safety_check import SafetyCheck
from psl_task.task import load_task

TALOS = Path(__file__).resolve().parents[3] / 'examples' / 'talos_arm_point_reach.yaml'
PERTURBED = 4               # seeded perturbations of theta_K besides the default
SPREAD = 0.05               # their standard deviation, a share of theta_K's largest entry


@pytest.fixture(scope='module')
def talos():
    task = load_task(str(TALOS))
    arm = ArmModel(task)
    return task, TaskPolicy(task), arm, SafetyCheck(arm)


def thetas_and_taus(task, policy):
    rng = np.random.default_rng(47)
    low = np.array([p.low for p in task.parameters])
    high = np.array([p.high for p in task.parameters])
    kinematics = policy.default_theta[policy.kinematics]
    for i in range(1 + PERTURBED):
        theta = policy.default_theta.copy()
        if i:
            theta[policy.kinematics] += rng.normal(0.0, SPREAD * np.abs(kinematics).max(),
                                                   kinematics.shape)
        yield theta, rng.uniform(low, high)


def test_talos_references_keep_the_velocity_bounds_and_pass_the_safety_check(talos):
    task, policy, arm, safety = talos
    bound = arm.limits.velocity
    assert bound.max() < 5.0                       # the URDF's, not the MJCF default
    for i, (theta, tau) in enumerate(thetas_and_taus(task, policy)):
        reference = policy.reference(theta, tau)
        assert np.all(np.abs(reference.qd) <= (1.0 - VELOCITY_MARGIN) * bound * (1 + 1e-12)), i
        verdict = safety.check(tau, reference.q, reference.qd, reference.u_ffwd)
        assert verdict.safe, (i, verdict.reason)
