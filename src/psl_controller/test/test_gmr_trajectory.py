"""GMR trajectory encoding (eq. 2.25): fits a demonstration, theta round-trips, the `gmr`
conditioning equals the closed form, velocities are the derivative of positions."""
import numpy as np
import pytest

from psl_controller.gmr_trajectory import GMRTrajectory

DURATION, DT = 2.0, 0.002


def demonstration():
    t = np.arange(int(DURATION / DT) + 1) * DT
    s = t / DURATION
    smooth = 10 * s**3 - 15 * s**4 + 6 * s**5            # minimum jerk 0 -> 1
    y = np.column_stack([0.5 + 1.2 * smooth, -0.3 * smooth + 0.2 * np.sin(np.pi * s),
                         np.cos(2 * s)])
    return t, y


@pytest.fixture(scope='module')
def fitted():
    gmr = GMRTrajectory(n_dims=3, n_components=8, duration=DURATION)
    gmr.fit(*demonstration(), seed=0)
    return gmr


def test_the_fit_reproduces_the_demonstration(fitted):
    t, y = demonstration()
    sample = fitted.integrate(DT)
    np.testing.assert_array_equal(sample.t, t)
    assert np.sqrt(np.mean((sample.y - y) ** 2)) < 0.01      # rad, over a range of ~1.2 rad


def test_components_are_sorted_by_phase_and_theta_has_the_fixed_size(fitted):
    assert np.all(np.diff(fitted.phase_means) > 0)
    assert fitted.get_theta().shape == (2 * 8 * 3,) == (fitted.num_parameters,)


def test_theta_round_trip_and_bad_sizes(fitted):
    theta = fitted.get_theta()
    other = GMRTrajectory(3, 8, DURATION)
    other.fit(*demonstration(), seed=0)
    other.set_theta(theta + 0.1)
    other.set_theta(theta)
    np.testing.assert_array_equal(other.integrate(DT).y, fitted.integrate(DT).y)
    with pytest.raises(ValueError, match='48 entries'):
        other.set_theta(theta[:-1])
    with pytest.raises(RuntimeError, match='fit'):
        GMRTrajectory(3, 8, DURATION).integrate(DT)


def test_gmr_conditioning_equals_the_closed_form(fitted):
    """q(s) = sum_k h_k(s) (mu_k + slope_k (s - mu_s,k)), h_k from the phase Gaussians."""
    rng = np.random.default_rng(1)
    fitted_copy = GMRTrajectory(3, 8, DURATION)
    fitted_copy.fit(*demonstration(), seed=0)
    fitted_copy.set_theta(fitted.get_theta() + rng.normal(0, 0.3, fitted.num_parameters))
    sample = fitted_copy.integrate(DT)
    s = sample.t / DURATION
    d = s[:, None] - fitted_copy.phase_means
    w = fitted_copy.priors * np.exp(-0.5 * d**2 / fitted_copy.phase_vars) \
        / np.sqrt(2 * np.pi * fitted_copy.phase_vars)
    h = w / w.sum(axis=1, keepdims=True)
    expected = np.einsum('tk,tkn->tn', h, fitted_copy.means[None]
                         + fitted_copy.slopes[None] * d[:, :, None])
    np.testing.assert_allclose(sample.y, expected, atol=1e-9)


def test_velocity_is_the_derivative_of_position(fitted):
    fine = DT / 20                                 # central differences: error ~ fine**2
    sample = fitted.integrate(fine)
    numeric = np.gradient(sample.y, fine, axis=0)
    np.testing.assert_allclose(sample.yd[1:-1], numeric[1:-1],
                               atol=1e-5 * np.abs(sample.yd).max())


def test_a_component_mean_moves_the_trajectory_near_its_phase_only(fitted):
    changed = GMRTrajectory(3, 8, DURATION)
    changed.fit(*demonstration(), seed=0)
    theta = fitted.get_theta()
    theta[3 * 3 + 0] += 0.5                    # component 3, joint 0: its mean
    changed.set_theta(theta)
    delta = np.abs(changed.integrate(DT).y[:, 0] - fitted.integrate(DT).y[:, 0])
    s = np.arange(delta.size) * DT / DURATION
    peak = s[np.argmax(delta)]
    assert abs(peak - fitted.phase_means[3]) < 0.1
    assert delta.max() > 0.1 and np.all(np.abs(changed.integrate(DT).y[:, 1:]
                                                - fitted.integrate(DT).y[:, 1:]) < 1e-12)


def test_after_the_duration_the_trajectory_holds_its_end(fitted):
    sample = fitted.integrate(DT, t_end=DURATION + 0.5)
    after = sample.t > DURATION
    assert after.sum() == 250
    np.testing.assert_array_equal(sample.y[after], np.broadcast_to(sample.y[~after][-1],
                                                                   sample.y[after].shape))
    assert np.all(sample.yd[after] == 0.0)
