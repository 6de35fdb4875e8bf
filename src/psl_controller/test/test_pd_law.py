"""Tests of the PD + feed-forward torque law: hand-computed values, clipping, the population
form against a loop, and the affine split batch mode realises in MuJoCo against the law."""

import numpy as np
import pytest

from psl_controller.pd_law import PDLaw, law_for
from psl_task.arm_model import ArmModel
from psl_task.task import load_task

TOL = 1e-12

Q = np.array([0.1, -0.2, 0.3])
QD = np.array([0.0, 0.5, -1.0])
Q_REF = np.array([0.2, 0.0, 0.0])
QD_REF = np.array([0.1, 0.5, 0.0])
U_FFWD = np.array([1.0, -1.0, 0.5])


def law(kp, kd, limit, n=3):
    return PDLaw.symmetric(np.broadcast_to(kp, (n,)), kd, limit)


def test_hand_computed_scalar_gains():
    # position errors [0.1, 0.2, -0.3], velocity errors [0.1, 0.0, 1.0]
    # u = 10 * [0.1, 0.2, -0.3] + 2 * [0.1, 0.0, 1.0] + [1.0, -1.0, 0.5] = [2.2, 1.0, -0.5]
    u = law(10.0, 2.0, 100.0).torque(Q, QD, Q_REF, QD_REF, U_FFWD)
    np.testing.assert_allclose(u, [2.2, 1.0, -0.5], rtol=0.0, atol=TOL)


def test_hand_computed_per_joint_gains():
    # u = [1*0.1 + 0*0.1 + 1, 10*0.2 + 1*0 - 1, 100*(-0.3) + 2*1 + 0.5] = [1.1, 1.0, -27.5]
    u = law([1.0, 10.0, 100.0], [0.0, 1.0, 2.0], [50.0, 50.0, 50.0]).torque(
        Q, QD, Q_REF, QD_REF, U_FFWD)
    np.testing.assert_allclose(u, [1.1, 1.0, -27.5], rtol=0.0, atol=TOL)


def test_clipping_at_torque_limits_both_signs():
    # unclipped u = 1000 * [1, -1, 0.001] = [1000, -1000, 1]
    u = law(1000.0, 0.0, [5.0, 7.0, 3.0]).torque(np.zeros(3), np.zeros(3), [1.0, -1.0, 0.001],
                                                 np.zeros(3), np.zeros(3))
    np.testing.assert_allclose(u, [5.0, -7.0, 1.0], rtol=0.0, atol=TOL)
    u = law(1.0, 1.0, 2.0).torque(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3),
                                  [-9.0, 9.0, 0.0])
    np.testing.assert_array_equal(u, [-2.0, 2.0, 0.0])


def test_asymmetric_limits():
    asymmetric = PDLaw(np.full(3, 1.0), np.zeros(3), [-1.0, -2.0, 0.0], [3.0, 2.0, 0.5])
    u = asymmetric.torque(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3),
                          [-10.0, 10.0, 0.25])
    np.testing.assert_array_equal(u, [-1.0, 2.0, 0.25])


def test_feedforward_alone_at_zero_error():
    u = law(50.0, 5.0, 10.0).torque(Q, QD, Q, QD, U_FFWD)
    np.testing.assert_allclose(u, U_FFWD, rtol=0.0, atol=TOL)


def test_a_population_of_trajectories_equals_the_law_state_by_state():
    rng = np.random.default_rng(0)
    pd = law([30.0, 20.0, 10.0], [2.0, 1.0, 0.5], [4.0, 3.0, 2.0])
    q, qd, q_ref, qd_ref, u_ffwd = rng.normal(size=(5, 4, 6, 3))       # (B, T, n) each
    batch = pd.torque(q, qd, q_ref, qd_ref, u_ffwd)
    assert batch.shape == (4, 6, 3)
    for b in range(4):
        for k in range(6):
            np.testing.assert_array_equal(
                batch[b, k], pd.torque(q[b, k], qd[b, k], q_ref[b, k], qd_ref[b, k],
                                       u_ffwd[b, k]))
            np.testing.assert_array_equal(
                pd.actuator_control(q_ref, qd_ref, u_ffwd)[b, k],
                pd.actuator_control(q_ref[b, k], qd_ref[b, k], u_ffwd[b, k]))
    assert np.any(batch == 4.0) and np.any(batch == -2.0)      # the limits were reached


def test_the_actuator_split_is_the_law():
    """Batch mode's general actuator: force = clip(ctrl + b0 + b1 q + b2 qd) with ctrl =
    actuator_control and [b0, b1, b2] = actuator_bias equals the law (up to rounding)."""
    rng = np.random.default_rng(1)
    pd = PDLaw([300.0, 200.0, 100.0], [20.0, 12.0, 5.0], [-40.0, -30.0, -20.0],
               [40.0, 30.0, 20.0])
    q, qd, q_ref, qd_ref, u_ffwd = rng.normal(scale=0.3, size=(5, 50, 3))
    bias = pd.actuator_bias()
    assert bias.shape == (3, 3)
    force = np.clip(pd.actuator_control(q_ref, qd_ref, u_ffwd) + bias[:, 0] + bias[:, 1] * q
                    + bias[:, 2] * qd, pd.torque_low, pd.torque_high)
    np.testing.assert_allclose(force, pd.torque(q, qd, q_ref, qd_ref, u_ffwd), rtol=0,
                               atol=1e-12)


def test_feedback_is_the_applied_torque_without_the_feedforward():
    pd = law(10.0, 2.0, 100.0)
    applied = pd.torque(Q, QD, Q_REF, QD_REF, U_FFWD)
    np.testing.assert_allclose(PDLaw.feedback(applied, U_FFWD),
                               10.0 * (Q_REF - Q) + 2.0 * (QD_REF - QD), rtol=0, atol=TOL)


def test_the_task_law_has_the_task_gains_and_the_model_limits():
    task = load_task('reach_over_obstacle')
    arm = ArmModel(task)
    pd = law_for(task)
    np.testing.assert_array_equal(pd.kp, task.controller.kp)
    np.testing.assert_array_equal(pd.kd, task.controller.kd)
    np.testing.assert_array_equal(pd.torque_low, arm.torque_low)
    np.testing.assert_array_equal(pd.torque_high, arm.torque_high)
    with pytest.raises(ValueError):
        pd.kp[0] = 1.0                     # the law is fixed once made


@pytest.mark.parametrize('fields', [
    {'kp': [1.0, 2.0]},
    {'kd': np.ones(4)},
    {'torque_high': [1.0, 1.0]},
    {'kp': [np.nan, 1.0, 1.0]},
    {'kd': [-1.0, 0.0, 0.0]},
    {'torque_low': [2.0, -1.0, -1.0]},          # above torque_high
    {'torque_high': [np.inf, 1.0, 1.0]},
    {'kp': [[1.0, 2.0, 3.0]]},
])
def test_bad_gains_and_limits_raise(fields):
    arguments = dict(kp=np.ones(3), kd=np.ones(3), torque_low=-np.ones(3),
                     torque_high=np.ones(3))
    arguments.update(fields)
    with pytest.raises(ValueError):
        PDLaw(**arguments)


def test_a_negative_symmetric_limit_raises():
    with pytest.raises(ValueError, match='torque_limit'):
        PDLaw.symmetric(np.ones(3), 1.0, -1.0)
