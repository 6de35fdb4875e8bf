"""The feed-forward signal of the dynamics modality and theta = [theta_K, theta_D] in the policy."""
from pathlib import Path

import numpy as np
import pytest
import yaml

from psl_controller.basis_functions import NormalizedGaussianBasis
from psl_controller.canonical_system import CanonicalSystem
from psl_controller.feedforward import FeedForward
from psl_controller.policy import TaskPolicy, policy_for
from psl_task.task import load_task

FIT_TOLERANCE = 1e-9    # N m, a signal of the basis projects back onto itself


@pytest.fixture
def feedforward():
    return FeedForward(CanonicalSystem(1.5), NormalizedGaussianBasis(6), n_joints=2)


def test_signal_is_the_basis_weighted_by_theta_d(feedforward):
    t = np.linspace(0.0, 2.0, 101)
    theta_d = np.arange(12.0)
    u = feedforward.signal(theta_d, t)
    assert u.shape == (101, 2)
    phi = NormalizedGaussianBasis(6).activations(CanonicalSystem(1.5).phase(t))
    np.testing.assert_allclose(u, phi @ theta_d.reshape(2, 6).T)
    # constant weights give a constant signal (normalised basis), also after the motion
    np.testing.assert_allclose(feedforward.signal(np.r_[np.full(6, 3.0), np.full(6, -1.0)], t),
                               np.tile([3.0, -1.0], (101, 1)))


def test_fit_recovers_the_weights_of_a_basis_signal(feedforward):
    t = np.arange(1001) * 0.002
    theta_d = np.random.default_rng(0).normal(scale=10.0, size=12)
    np.testing.assert_allclose(feedforward.fit(t, feedforward.signal(theta_d, t), 0.0),
                               theta_d, atol=FIT_TOLERANCE)


@pytest.mark.parametrize('bad', [np.zeros(11), np.full(12, np.nan)])
def test_bad_theta_d_raises(feedforward, bad):
    with pytest.raises(ValueError):
        feedforward.signal(bad, np.zeros(3))


def test_fit_rejects_bad_torques(feedforward):
    with pytest.raises(ValueError):
        feedforward.fit(np.zeros(5), np.zeros((5, 3)))
    with pytest.raises(ValueError):
        feedforward.fit(np.zeros(2), np.array([[0.0, np.inf], [0.0, 0.0]]))


def test_policy_with_feedforward_has_theta_k_then_theta_d():
    task = load_task('payload_transport')
    policy = policy_for(task)
    n_kin = task.n_joints * task.policy.n_basis
    assert policy.has_feedforward and policy.num_parameters == 2 * n_kin
    assert policy.kinematics == slice(0, n_kin) and policy.dynamics == slice(n_kin, 2 * n_kin)
    np.testing.assert_array_equal(policy.default_theta[policy.dynamics], 0.0)
    theta = policy.with_feedforward(policy.default_theta, np.ones(n_kin))
    reference = policy.reference(theta)
    np.testing.assert_allclose(reference.u_ffwd, 1.0)
    np.testing.assert_array_equal(reference.q, policy.reference(policy.default_theta).q)
    np.testing.assert_array_equal(policy.reference(policy.default_theta).u_ffwd, 0.0)


@pytest.mark.parametrize('name', ['reach_over_obstacle', 'reach_4dof'])
def test_tasks_without_the_option_keep_their_theta(name):
    task = load_task(name)
    policy = policy_for(task)
    assert not policy.has_feedforward
    assert policy.num_parameters == task.n_joints * task.policy.n_basis
    with pytest.raises(ValueError):
        policy.with_feedforward(policy.default_theta, np.zeros(1))


def test_feedforward_option_must_be_a_boolean(tmp_path):
    task = load_task('payload_transport')
    data = yaml.safe_load(task.path.read_text())
    data['model'] = str(task.model_path)
    data['policy']['feedforward'] = 'yes'
    path = tmp_path / 'bad_ffwd.yaml'
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match='feedforward'):
        TaskPolicy(load_task(str(path)))


def test_the_signal_is_clipped_into_the_torque_limits_given():
    """A theta_D asking more than the motors give: the signal is the unclipped one clipped
    into the limits, row by row alike in the population form; inside the limits it is the
    unclipped signal bit for bit (issue 46: the safety check and the controllers refuse an
    effort past the limits, and a candidate asking it runs with the most the motors give)."""
    canonical, basis = CanonicalSystem(1.0), NormalizedGaussianBasis(5)
    low, high = np.array([-1.0, -2.0]), np.array([1.5, 2.0])
    free = FeedForward(canonical, basis, 2)
    held = FeedForward(canonical, basis, 2, low, high)
    t = np.linspace(0.0, 1.5, 151)
    rng = np.random.default_rng(3)
    thetas = rng.normal(0.0, 3.0, (4, free.num_parameters))
    for theta in thetas:
        np.testing.assert_array_equal(held.signal(theta, t), np.clip(free.signal(theta, t),
                                                                     low, high))
    np.testing.assert_array_equal(held.signal_population(thetas, t),
                                  np.clip(free.signal_population(thetas, t), low, high))
    assert np.any(free.signal(thetas[0], t) > high)          # the case is one of clipping
    inside = thetas[0] * 0.01
    assert np.array_equal(held.signal(inside, t), free.signal(inside, t))
    with pytest.raises(ValueError, match='2 entries'):
        FeedForward(canonical, basis, 2, np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match='above torque_high'):
        FeedForward(canonical, basis, 2, high, low)


def test_a_policys_feedforward_keeps_the_arms_torque_limits():
    """TALOS's arm (torque limits 3-22 N m): a theta_D of 50 N m is sent at the limits and
    passes the safety check (it was refused: 'the feed-forward of -9.1 N m ... below its torque
    limit -6.6 N m' on 206 candidates of a session)."""
    from psl_task.arm_model import ArmModel
    from psl_task.safety_check import SafetyCheck
    task = load_task(str(Path(__file__).resolve().parents[3] / 'examples'
                         / 'talos_arm_point_reach.yaml'))
    policy, arm = policy_for(task), ArmModel(task)
    theta = policy.default_theta.copy()
    theta[policy.dynamics] = 50.0 * np.sign(np.arange(len(theta[policy.dynamics])) % 2 - 0.5)
    ref = policy.reference(theta, task.tau_default)
    assert np.all(ref.u_ffwd <= arm.torque_high) and np.all(ref.u_ffwd >= arm.torque_low)
    assert np.any(ref.u_ffwd == arm.torque_high) and np.any(ref.u_ffwd == arm.torque_low)
    verdict = SafetyCheck(arm).check(task.tau_default, ref.q, ref.qd, ref.u_ffwd)
    assert verdict.safe, verdict.reason
