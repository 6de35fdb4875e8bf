"""Tests of the PD + feed-forward torque law."""

import numpy as np
import pytest

from psl_controller.pd_law import pd_feedforward

TOL = 1e-12

Q = np.array([0.1, -0.2, 0.3])
QD = np.array([0.0, 0.5, -1.0])
Q_REF = np.array([0.2, 0.0, 0.0])
QD_REF = np.array([0.1, 0.5, 0.0])
U_FFWD = np.array([1.0, -1.0, 0.5])


def test_hand_computed_scalar_gains():
    # position errors [0.1, 0.2, -0.3], velocity errors [0.1, 0.0, 1.0]
    # u = 10 * [0.1, 0.2, -0.3] + 2 * [0.1, 0.0, 1.0] + [1.0, -1.0, 0.5] = [2.2, 1.0, -0.5]
    u = pd_feedforward(Q, QD, Q_REF, QD_REF, U_FFWD, kp=10.0, kd=2.0, u_limit=100.0)
    np.testing.assert_allclose(u, [2.2, 1.0, -0.5], rtol=0.0, atol=TOL)


def test_hand_computed_per_joint_gains():
    # u = [1*0.1 + 0*0.1 + 1, 10*0.2 + 1*0 - 1, 100*(-0.3) + 2*1 + 0.5] = [1.1, 1.0, -27.5]
    u = pd_feedforward(Q, QD, Q_REF, QD_REF, U_FFWD, kp=[1.0, 10.0, 100.0], kd=[0.0, 1.0, 2.0],
                       u_limit=[50.0, 50.0, 50.0])
    np.testing.assert_allclose(u, [1.1, 1.0, -27.5], rtol=0.0, atol=TOL)


def test_clipping_at_torque_limits_both_signs():
    # unclipped u = 1000 * [1, -1, 0.001] = [1000, -1000, 1]
    u = pd_feedforward(np.zeros(3), np.zeros(3), [1.0, -1.0, 0.001], np.zeros(3), np.zeros(3),
                       kp=1000.0, kd=0.0, u_limit=[5.0, 7.0, 3.0])
    np.testing.assert_allclose(u, [5.0, -7.0, 1.0], rtol=0.0, atol=TOL)
    u = pd_feedforward(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), [-9.0, 9.0, 0.0],
                       kp=1.0, kd=1.0, u_limit=2.0)
    np.testing.assert_array_equal(u, [-2.0, 2.0, 0.0])


def test_feedforward_alone_at_zero_error():
    u = pd_feedforward(Q, QD, Q, QD, U_FFWD, kp=50.0, kd=5.0, u_limit=10.0)
    np.testing.assert_allclose(u, U_FFWD, rtol=0.0, atol=TOL)


@pytest.mark.parametrize('changes', [
    {'qd': np.zeros(2)},
    {'q_ref': np.zeros(4)},
    {'u_ffwd': np.zeros((3, 1))},
    {'kp': [1.0, 2.0]},
    {'kd': np.ones(4)},
    {'u_limit': [1.0, 1.0]},
    {'q': np.array([np.nan, 0.0, 0.0])},
    {'qd_ref': np.array([0.0, np.inf, 0.0])},
    {'kp': np.nan},
    {'kd': -1.0},
    {'u_limit': -1.0},
])
def test_bad_inputs_raise(changes):
    arguments = dict(q=Q, qd=QD, q_ref=Q_REF, qd_ref=QD_REF, u_ffwd=U_FFWD,
                     kp=10.0, kd=1.0, u_limit=5.0)
    arguments.update(changes)
    with pytest.raises(ValueError):
        pd_feedforward(**arguments)
