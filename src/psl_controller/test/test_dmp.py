"""Tests of the DMP library (eq. 2.23-2.24): canonical system, basis, DMP, fitting."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from psl_controller.basis_functions import NormalizedGaussianBasis
from psl_controller.canonical_system import CanonicalSystem
from psl_controller.dmp import DMP, demonstration_from_waypoints

TOL_EXACT = 1e-10  # closed form vs zero-order-hold discretisation (relative to signal scale)
TOL_ODE = 1e-8  # analytical phase vs adaptive ODE solver
TOL_REFERENCE = 1e-7  # exact ZOH integration vs fine RK4 reference (relative)
FIT_RMSE_FRACTION = 1e-3  # fitted reproduction RMSE per joint / joint range
GOAL_TOL = 1e-5  # |y - g| after settling

WAYPOINT_TIMES = np.array([0.0, 0.4, 1.0, 1.5, 2.0])
WAYPOINTS = np.array([[0.0, 0.5, -0.2],
                      [0.4, 0.9, 0.1],
                      [0.8, 0.3, 0.6],
                      [0.5, -0.2, 0.9],
                      [1.0, 0.0, 1.2]])  # (W, 3)


def critically_damped(t, y0, g, k_s):
    """Independent closed form of ydd = k_s (g - y) - 2 sqrt(k_s) yd, y(0) = y0, yd(0) = 0."""
    w = np.sqrt(k_s)
    t = t[:, None]
    decay = np.exp(-w * t)
    y = g + (y0 - g) * (1.0 + w * t) * decay
    yd = -(y0 - g) * w**2 * t * decay
    ydd = (y0 - g) * w**2 * (w * t - 1.0) * decay
    return y, yd, ydd


def assert_close_scaled(actual, expected, tol):
    scale = max(1.0, np.max(np.abs(expected)))
    np.testing.assert_allclose(actual, expected, rtol=0.0, atol=tol * scale)


# -- canonical system ---------------------------------------------------------------------------
@pytest.mark.parametrize('kind', ['linear', 'exponential'])
def test_canonical_phase_matches_integrated_rate(kind):
    duration = 1.7
    system = CanonicalSystem(duration, kind=kind, alpha=3.0)
    # The linear kind's rate jumps to 0 at x = 0; integrate the decaying part [0, duration].
    t_stop = duration if kind == 'linear' else 2.0 * duration
    t_eval = np.linspace(0.0, t_stop, 57)
    solution = solve_ivp(lambda _t, x: system.rate(x), (0.0, t_stop), [1.0], t_eval=t_eval,
                         rtol=1e-12, atol=1e-12)
    assert solution.success
    np.testing.assert_allclose(system.phase(t_eval), solution.y[0], rtol=0.0, atol=TOL_ODE)


def test_linear_canonical_stops_at_zero():
    system = CanonicalSystem(2.0, kind='linear')
    np.testing.assert_array_equal(system.phase(np.array([2.0, 2.5, 100.0])), 0.0)
    np.testing.assert_array_equal(system.rate(np.array([0.0])), 0.0)
    np.testing.assert_allclose(system.rate(np.array([0.3, 1.0])), -0.5)
    np.testing.assert_allclose(system.phase(np.array([0.0, 0.5, 1.0])), [1.0, 0.75, 0.5])


@pytest.mark.parametrize('kind', ['linear', 'exponential'])
def test_gate_is_one_at_start_and_zero_from_duration(kind):
    duration = 0.8
    system = CanonicalSystem(duration, kind=kind)
    assert system.gate(np.array([0.0]))[0] == 1.0
    np.testing.assert_array_equal(system.gate(np.array([duration, duration + 1e-9, 5.0])), 0.0)
    inside = system.gate(np.linspace(0.0, duration, 50, endpoint=False))
    assert np.all(inside > 0.0) and np.all(np.diff(inside) < 0.0)
    if kind == 'linear':
        t = np.linspace(0.0, 2.0, 21)
        np.testing.assert_array_equal(system.gate(t), system.phase(t))


def test_canonical_rejects_bad_options():
    with pytest.raises(ValueError, match='kind'):
        CanonicalSystem(1.0, kind='sigmoid')
    with pytest.raises(ValueError, match='duration'):
        CanonicalSystem(0.0)
    with pytest.raises(ValueError, match='alpha'):
        CanonicalSystem(1.0, kind='exponential', alpha=-1.0)


# -- basis functions ----------------------------------------------------------------------------
@pytest.mark.parametrize('n_basis', [1, 2, 7, 25])
def test_basis_rows_sum_to_one(n_basis):
    basis = NormalizedGaussianBasis(n_basis)
    x = np.random.default_rng(0).uniform(-0.5, 1.5, size=200)
    activations = basis.activations(x)
    assert activations.shape == (200, n_basis)
    assert np.all(activations >= 0.0)
    np.testing.assert_allclose(activations.sum(axis=1), 1.0, rtol=0.0, atol=1e-12)


def test_basis_centers_equally_spaced_and_peaked():
    basis = NormalizedGaussianBasis(5)
    np.testing.assert_allclose(basis.centers, [0.0, 0.25, 0.5, 0.75, 1.0])
    # V_k = 1 / (2 (width_factor * spacing)^2) with the default width_factor 0.5
    np.testing.assert_allclose(basis.widths, 1.0 / (2.0 * (0.5 * 0.25) ** 2))
    activations = basis.activations(basis.centers)
    np.testing.assert_array_equal(np.argmax(activations, axis=1), np.arange(5))


@pytest.mark.parametrize('n_basis, width_factor', [(2, 0.5), (7, 0.5), (25, 0.5), (7, 1.3)])
def test_basis_activations_are_normalised_gaussians_by_hand(n_basis, width_factor):
    """psi_k(x) = exp(-V_k (x - C_k)^2) / sum_j exp(-V_j (x - C_j)^2) (eq. 2.24), C_k equally
    spaced on [0, 1], V_k = 1 / (2 (width_factor h)^2) with h the centre spacing; computed
    directly (no shift of the exponents: none underflows on [-0.2, 1.2] here)."""
    basis = NormalizedGaussianBasis(n_basis, width_factor)
    h = 1.0 / (n_basis - 1)
    centres = h * np.arange(n_basis)                                    # (K,)
    v = 1.0 / (2.0 * (width_factor * h) ** 2)
    np.testing.assert_allclose(basis.centers, centres, rtol=0.0, atol=1e-15)
    np.testing.assert_allclose(basis.widths, np.full(n_basis, v), rtol=1e-15)
    x = np.r_[np.linspace(-0.2, 1.2, 141), centres]                    # (T,)
    psi = np.array([[np.exp(-v * (xt - c) ** 2) for c in centres] for xt in x])   # (T, K)
    expected = psi / psi.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(basis.activations(x), expected, rtol=1e-12, atol=1e-15)
    assert basis.activations(0.3).shape == (1, n_basis)                 # a scalar is T = 1


def test_a_single_basis_function_is_one_everywhere():
    basis = NormalizedGaussianBasis(1)
    np.testing.assert_array_equal(basis.centers, [0.5])
    np.testing.assert_array_equal(basis.activations(np.linspace(-1.0, 2.0, 7)), np.ones((7, 1)))


def test_basis_rejects_bad_sizes():
    with pytest.raises(ValueError, match='n_basis'):
        NormalizedGaussianBasis(0)
    with pytest.raises(ValueError, match='width_factor'):
        NormalizedGaussianBasis(3, width_factor=0.0)


# -- transformation system ----------------------------------------------------------------------
@pytest.mark.parametrize('canonical', ['linear', 'exponential'])
def test_zero_weights_equal_closed_form_critically_damped(canonical):
    y0, goal, k_s = np.array([0.3, -1.0]), np.array([1.2, 0.5]), 250.0
    dmp = DMP(2, 8, 1.0, y0, goal, k_s=k_s, canonical=canonical)
    trajectory = dmp.integrate(0.001, t_end=1.5)
    np.testing.assert_allclose(trajectory.t, np.arange(1501) * 0.001, rtol=0.0, atol=1e-15)
    y, yd, ydd = critically_damped(trajectory.t, y0, goal, k_s)
    assert_close_scaled(trajectory.y, y, TOL_EXACT)
    assert_close_scaled(trajectory.yd, yd, TOL_EXACT)
    assert_close_scaled(trajectory.ydd, ydd, TOL_EXACT)
    analytical = dmp.point_attractor_solution(trajectory.t)
    assert_close_scaled(analytical.y, y, TOL_EXACT)
    assert_close_scaled(analytical.yd, yd, TOL_EXACT)
    assert_close_scaled(analytical.ydd, ydd, TOL_EXACT)


def test_default_damping_is_critical():
    dmp = DMP(1, 3, 1.0, [0.0], [1.0], k_s=400.0)
    assert dmp.k_d == pytest.approx(40.0)


@pytest.mark.parametrize('canonical', ['linear', 'exponential'])
def test_integrate_matches_fine_reference_with_held_forcing(canonical):
    """Exact ZOH integration vs RK4 with 20 substeps, forcing held over each dt."""
    dt, duration, k_s, k_d = 0.01, 1.0, 100.0, 14.0
    dmp = DMP(2, 6, duration, [0.1, -0.4], [0.9, 0.2], k_s=k_s, k_d=k_d, canonical=canonical)
    dmp.set_theta(np.random.default_rng(1).normal(scale=200.0, size=12))
    trajectory = dmp.integrate(dt, t_end=1.3)
    goal = dmp.goal
    y, yd = dmp.y0, np.zeros(2)
    substeps = 20
    h = dt / substeps
    reference = [y.copy()]
    for t in trajectory.t[:-1]:
        f = dmp.forcing(np.array([t]))[0]
        for _ in range(substeps):
            def deriv(pos, vel):
                return vel, k_s * (goal - pos) - k_d * vel + f
            k1 = deriv(y, yd)
            k2 = deriv(y + 0.5 * h * k1[0], yd + 0.5 * h * k1[1])
            k3 = deriv(y + 0.5 * h * k2[0], yd + 0.5 * h * k2[1])
            k4 = deriv(y + h * k3[0], yd + h * k3[1])
            y = y + h / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            yd = yd + h / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        reference.append(y.copy())
    assert_close_scaled(trajectory.y, np.array(reference), TOL_REFERENCE)
    expected_ydd = (k_s * (goal - trajectory.y) - k_d * trajectory.yd
                    + dmp.forcing(trajectory.t))
    assert_close_scaled(trajectory.ydd, expected_ydd, 1e-12)


@pytest.mark.parametrize('canonical', ['linear', 'exponential'])
def test_forcing_vanishes_from_duration(canonical):
    duration = 1.2
    dmp = DMP(3, 10, duration, np.zeros(3), np.ones(3), canonical=canonical)
    dmp.set_theta(np.random.default_rng(2).normal(scale=300.0, size=30))
    assert np.all(np.abs(dmp.forcing(np.array([0.0, 0.3 * duration]))) > 0.0)
    after = np.array([duration, duration + 1e-12, duration + 0.5, 10.0])
    np.testing.assert_array_equal(dmp.forcing(after), 0.0)
    # In the integrated trajectory, ydd is the pure point attractor from the duration on.
    trajectory = dmp.integrate(0.002, t_end=duration + 0.4)
    late = trajectory.t >= duration
    attractor = dmp.k_s * (dmp.goal - trajectory.y) - dmp.k_d * trajectory.yd
    assert_close_scaled(trajectory.ydd[late], attractor[late], 1e-12)
    assert not np.allclose(trajectory.ydd[~late], attractor[~late])


def test_goal_reached_after_settling():
    duration, settle = 1.0, 1.0
    dmp = DMP(3, 10, duration, [0.0, 1.0, -0.5], [0.7, -0.3, 0.4])
    dmp.set_theta(np.random.default_rng(3).normal(scale=1000.0, size=30))
    trajectory = dmp.integrate(0.002, t_end=duration + settle)
    assert trajectory.t[-1] == pytest.approx(duration + settle)
    assert np.max(np.abs(trajectory.y[-1] - dmp.goal)) < GOAL_TOL
    assert np.max(np.abs(trajectory.yd[-1])) < GOAL_TOL
    # the forcing did perturb the motion: at the duration the DMP is still away from the goal
    middle = np.argmin(np.abs(trajectory.t - 0.5 * duration))
    free = dmp.point_attractor_solution(trajectory.t[[middle]])
    assert np.max(np.abs(trajectory.y[middle] - free.y[0])) > 1e-2


@pytest.mark.parametrize('canonical, n_basis, rmse_fraction', [
    ('linear', 20, FIT_RMSE_FRACTION),
    ('exponential', 30, 1e-2),  # centres equally spaced in phase are sparse late in time
])
def test_fit_reproduces_smooth_demonstration(canonical, n_basis, rmse_fraction):
    dt, duration = 0.002, 2.0
    t, y = demonstration_from_waypoints(WAYPOINT_TIMES, WAYPOINTS, dt)
    if canonical == 'exponential':
        t, y = demonstration_from_waypoints(WAYPOINT_TIMES[[0, 2, 4]], WAYPOINTS[[0, 2, 4]], dt)
    dmp = DMP(3, n_basis, duration, np.zeros(3), np.zeros(3), canonical=canonical)
    assert dmp.fit(t, y, dt) is dmp
    np.testing.assert_array_equal(dmp.y0, y[0])
    np.testing.assert_array_equal(dmp.goal, y[-1])
    reproduction = dmp.integrate(dt)
    assert reproduction.y.shape == y.shape
    rmse = np.sqrt(np.mean((reproduction.y - y) ** 2, axis=0))  # (3,)
    assert np.all(rmse < rmse_fraction * np.ptp(y, axis=0)), rmse / np.ptp(y, axis=0)


def test_fit_resamples_a_demonstration_on_another_grid():
    t, y = demonstration_from_waypoints(WAYPOINT_TIMES, WAYPOINTS, 0.001)
    dmp = DMP(3, 20, 2.0, np.zeros(3), np.zeros(3)).fit(t, y, dt=0.004)
    reproduction = dmp.integrate(0.004)
    rmse = np.sqrt(np.mean((reproduction.y - y[::4]) ** 2, axis=0))
    assert np.all(rmse < FIT_RMSE_FRACTION * np.ptp(y, axis=0))


def test_fit_rejects_demonstration_not_covering_duration():
    t, y = demonstration_from_waypoints(WAYPOINT_TIMES, WAYPOINTS, 0.01)
    dmp = DMP(3, 10, 3.0, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match='cover'):
        dmp.fit(t, y, 0.01)
    with pytest.raises(ValueError, match='shape'):
        dmp.fit(t, y[:, :2], 0.01)


def test_theta_round_trip_and_row_major_layout():
    dmp = DMP(2, 4, 1.0, [0.0, 0.0], [1.0, 1.0])
    assert dmp.num_parameters == 8
    np.testing.assert_array_equal(dmp.get_theta(), np.zeros(8))
    theta = np.arange(8.0) * 1.5
    dmp.set_theta(theta)
    np.testing.assert_array_equal(dmp.get_theta(), theta)
    dmp.get_theta()[:] = 99.0  # a copy, not a view
    np.testing.assert_array_equal(dmp.get_theta(), theta)
    # Row-major (n_dims, n_basis): dimension 0 all 1, dimension 1 all 2. The basis is
    # normalised, so the forcing is gate * 1 and gate * 2 (eq. 2.24).
    dmp.set_theta([1.0, 1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 2.0])
    t = np.linspace(0.0, 1.2, 13)
    gate = dmp.canonical.gate(t)
    np.testing.assert_allclose(dmp.forcing(t), np.column_stack([gate, 2.0 * gate]), atol=1e-12)


@pytest.mark.parametrize('bad', [np.zeros(7), np.zeros(9), np.array([np.nan] + [0.0] * 7),
                                 np.array([np.inf] + [0.0] * 7)])
def test_set_theta_rejects_bad_vectors(bad):
    dmp = DMP(2, 4, 1.0, [0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match='theta'):
        dmp.set_theta(bad)
    np.testing.assert_array_equal(dmp.get_theta(), np.zeros(8))


def test_constructor_and_integrate_reject_bad_arguments():
    with pytest.raises(ValueError, match='y0'):
        DMP(3, 5, 1.0, [0.0, 0.0], np.zeros(3))
    with pytest.raises(ValueError, match='goal'):
        DMP(2, 5, 1.0, [0.0, 0.0], [np.nan, 0.0])
    with pytest.raises(ValueError, match='kind'):
        DMP(2, 5, 1.0, [0.0, 0.0], [1.0, 1.0], canonical='cubic')
    with pytest.raises(ValueError, match='n_basis'):
        DMP(2, 0, 1.0, [0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match='k_s'):
        DMP(2, 5, 1.0, [0.0, 0.0], [1.0, 1.0], k_s=0.0)
    dmp = DMP(2, 5, 1.0, [0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match='dt'):
        dmp.integrate(0.0)
    with pytest.raises(ValueError, match='t_end'):
        dmp.integrate(0.01, t_end=-1.0)


def test_integrate_grid_and_discretisation_once_per_grid(monkeypatch):
    """The discretisation (matrix exponential, basis on the grid, the O(N) response loop) is
    computed once per grid: later calls on that grid, also after a theta change, only combine
    the cached responses with theta, and give what a fresh DMP computes."""
    import psl_controller.dmp as dmp_module

    discretisations = []
    real_expm = dmp_module.expm
    monkeypatch.setattr(dmp_module, 'expm',
                        lambda m: discretisations.append(m.copy()) or real_expm(m))
    rng = np.random.default_rng(4)
    dmp = DMP(3, 10, 1.0, np.zeros(3), np.ones(3))
    basis_calls = []
    real_activations = dmp.basis.activations
    monkeypatch.setattr(dmp.basis, 'activations',
                        lambda x: basis_calls.append(len(x)) or real_activations(x))
    dmp.set_theta(rng.normal(size=30))
    trajectory = dmp.integrate(0.001)  # fills the cache for this grid
    assert trajectory.t.shape == (1001,)
    assert trajectory.y.shape == trajectory.yd.shape == trajectory.ydd.shape == (1001, 3)
    assert len(discretisations) == 1 and basis_calls == [1001]
    thetas = [rng.normal(size=30) for _ in range(5)]
    for theta in thetas:
        dmp.set_theta(theta)
        again = dmp.integrate(0.001)
        fresh = DMP(3, 10, 1.0, np.zeros(3), np.ones(3))
        fresh.set_theta(theta)
        reference = fresh.integrate(0.001)
        for name in ('t', 'y', 'yd', 'ydd'):
            np.testing.assert_array_equal(getattr(again, name), getattr(reference, name))
    assert len(discretisations) == 1 + len(thetas)      # one per fresh DMP, none for `dmp`
    assert basis_calls == [1001]
    assert dmp.integrate(0.003, t_end=0.1).t.shape == (34,)  # N = round(0.1 / 0.003) = 33
    assert basis_calls == [1001, 34]                          # a new grid: discretised once


def test_demonstration_from_two_waypoints_is_smoothstep():
    """A clamped cubic spline through two points is y0 + (y1 - y0)(3 s^2 - 2 s^3)."""
    t, y = demonstration_from_waypoints([0.0, 2.0], [[0.0, 1.0], [1.0, -1.0]], 0.01)
    assert t.shape == (201,) and y.shape == (201, 2)
    s = t / 2.0
    smoothstep = 3.0 * s**2 - 2.0 * s**3
    expected = np.column_stack([smoothstep, 1.0 - 2.0 * smoothstep])
    np.testing.assert_allclose(y, expected, rtol=0.0, atol=1e-12)


def test_demonstration_passes_through_waypoints_with_zero_end_velocity():
    dt = 0.01
    t, y = demonstration_from_waypoints(WAYPOINT_TIMES, WAYPOINTS, dt)
    on_waypoints = np.rint(WAYPOINT_TIMES / dt).astype(int)
    np.testing.assert_allclose(y[on_waypoints], WAYPOINTS, rtol=0.0, atol=1e-12)
    # one-sided second-order differences (error ~ jerk dt^2 / 3); unclamped ends give ~1 rad/s
    start_velocity = (-3.0 * y[0] + 4.0 * y[1] - y[2]) / (2.0 * dt)
    end_velocity = (3.0 * y[-1] - 4.0 * y[-2] + y[-3]) / (2.0 * dt)
    assert np.max(np.abs(start_velocity)) < 1e-2 and np.max(np.abs(end_velocity)) < 1e-2
    with pytest.raises(ValueError, match='increasing'):
        demonstration_from_waypoints([0.0, 0.0, 1.0], WAYPOINTS[:3], dt)
