"""Tests of the unit-quaternion orientation DMP (Ude et al. 2014) and its quaternion helpers.

References are independent of the code under test: scipy's Rotation (which orders quaternions
[x, y, z, w]) for products, log and exp maps and slerp, scipy's solve_ivp on the differential
equation written out here, closed forms of the critically damped attractor and of a
demonstration; two tests hold the orientation DMP against the position DMP (itself held against
closed forms in test_dmp.py): the same forcing on the same phase, and one axis as one angle.
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation, Slerp

from psl_task import quaternion
from psl_controller.dmp import DMP
from psl_controller.quaternion_dmp import QuaternionDMP

TOL_MAP = 1e-12  # quaternion helpers against scipy, exp(log(q)) against q
TOL_GEODESIC = 1e-12  # |rotation vector x geodesic axis| [rad] with zero weights
GOAL_TOL = 1e-3  # rad: distance to the goal after settling
TOL_ATTRACTOR = 1e-12  # rad: angle about one axis against the closed form (exact step)
TOL_REFERENCE_PER_DT = 3.0  # rad per s of dt: against RK45, continuous forcing (measured 2.1)
TOL_HELD_PER_DT = 0.5  # rad per s of dt: against RK45, forcing held per step (measured 0.32)
FIT_TOL = 1e-4  # rad: fit + integrate against the demonstration, 40 Gaussians (measured 3.1e-5)
FIT_EXACT_TOL = 1e-7  # rad: the same, a Gaussian per grid point (measured 3.7e-9)
ULPS = 16  # population against one by one: ulps of a field's largest magnitude (docs/testing.md)

RNG_SEED = 7


def to_rotation(q: np.ndarray) -> Rotation:
    """scipy Rotation of [w, x, y, z] quaternions (scipy takes [x, y, z, w])."""
    return Rotation.from_quat(np.asarray(q)[..., [1, 2, 3, 0]])


def angle_between(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Rotation angle [rad] between orientations, by scipy."""
    return (to_rotation(q_a) * to_rotation(q_b).inv()).magnitude()


def random_unit_quaternions(rng: np.random.Generator, count: int) -> np.ndarray:
    q = rng.normal(size=(count, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def assert_within_ulps(actual, desired):
    scale = np.max(np.abs(desired))
    np.testing.assert_allclose(actual, desired, rtol=0.0, atol=ULPS * np.spacing(scale))


# -- quaternion helpers -------------------------------------------------------------------------
def test_exp_of_log_is_the_quaternion_and_log_takes_the_shorter_way():
    q = random_unit_quaternions(np.random.default_rng(RNG_SEED), 1000)
    r = quaternion.log_map(q)
    hemisphere = np.where(q[:, :1] < 0.0, -1.0, 1.0)  # q and -q: one rotation, one log
    np.testing.assert_allclose(quaternion.exp_map(r), hemisphere * q, rtol=0.0, atol=TOL_MAP)
    np.testing.assert_array_equal(quaternion.log_map(-q), r)
    assert np.all(np.linalg.norm(r, axis=1) <= np.pi)
    np.testing.assert_allclose(r, to_rotation(q).as_rotvec(), rtol=0.0, atol=TOL_MAP)


def test_exp_map_matches_scipy_rotation():
    r = np.random.default_rng(RNG_SEED).uniform(-2.0, 2.0, size=(500, 3))
    np.testing.assert_allclose(to_rotation(quaternion.exp_map(r)).as_matrix(),
                               Rotation.from_rotvec(r).as_matrix(), rtol=0.0, atol=TOL_MAP)


@pytest.mark.parametrize('size', [1e-6, 1e-9, 1e-15, 1e-100])
def test_log_and_exp_keep_precision_near_identity(size):
    r = size * np.random.default_rng(RNG_SEED).normal(size=(20, 3))
    np.testing.assert_allclose(quaternion.log_map(quaternion.exp_map(r)), r, rtol=1e-14, atol=0)
    np.testing.assert_array_equal(quaternion.log_map(quaternion.IDENTITY), np.zeros(3))
    np.testing.assert_array_equal(quaternion.exp_map(np.zeros(3)), quaternion.IDENTITY)


def test_product_and_conjugate_match_rotation_matrices():
    rng = np.random.default_rng(RNG_SEED)
    p, q = random_unit_quaternions(rng, 200), random_unit_quaternions(rng, 200)
    np.testing.assert_allclose(to_rotation(quaternion.product(p, q)).as_matrix(),
                               to_rotation(p).as_matrix() @ to_rotation(q).as_matrix(),
                               rtol=0.0, atol=TOL_MAP)
    np.testing.assert_allclose(to_rotation(quaternion.conjugate(q)).as_matrix(),
                               np.transpose(to_rotation(q).as_matrix(), (0, 2, 1)),
                               rtol=0.0, atol=TOL_MAP)


def test_interpolate_matches_scipy_slerp_whatever_the_signs():
    rng = np.random.default_rng(RNG_SEED)
    t = np.cumsum(rng.uniform(0.1, 0.3, size=8))
    q = quaternion.exp_map(0.4 * rng.normal(size=(8, 3))) * rng.choice([-1.0, 1.0], (8, 1))
    t_new = np.linspace(t[0], t[-1], 97)
    expected = Slerp(t, to_rotation(q))(t_new)
    actual = to_rotation(quaternion.interpolate(t, q, t_new))
    assert np.max((actual * expected.inv()).magnitude()) < TOL_MAP


# -- the transformation system -------------------------------------------------------------------
def test_forcing_is_the_position_dmp_forcing_on_the_same_phase():
    theta = np.random.default_rng(RNG_SEED).normal(size=3 * 12)
    position = DMP(3, 12, 1.3, np.zeros(3), np.ones(3), canonical='exponential')
    orientation = QuaternionDMP(12, 1.3, quaternion.IDENTITY, quaternion.IDENTITY,
                                canonical='exponential')
    position.set_theta(theta)
    orientation.set_theta(theta)
    t = np.linspace(0.0, 1.6, 81)
    expected = position.forcing(t)
    np.testing.assert_allclose(orientation.forcing(t), expected, rtol=0.0,
                               atol=ULPS * np.spacing(np.max(np.abs(expected))))


def test_zero_weights_follow_the_geodesic_to_the_goal():
    q0 = quaternion.exp_map(np.array([0.3, -0.2, 0.1]))
    goal = quaternion.exp_map(np.array([-1.2, 1.5, 0.9]))
    dmp = QuaternionDMP(10, 1.0, q0, goal)
    dt, t_end = 1e-3, 0.6
    trajectory = dmp.integrate(dt, t_end)
    travelled = (to_rotation(trajectory.q) * to_rotation(q0).inv()).as_rotvec()  # (N+1, 3)
    whole = (to_rotation(goal) * to_rotation(q0).inv()).as_rotvec()
    axis, total = whole / np.linalg.norm(whole), np.linalg.norm(whole)
    assert np.max(np.linalg.norm(np.cross(travelled, axis), axis=1)) < TOL_GEODESIC
    angle = travelled @ axis
    assert np.all(np.diff(angle) >= 0.0)
    assert angle_between(trajectory.q[-1], goal) < GOAL_TOL
    # about one axis the step is exact: the critically damped attractor w = sqrt(k_s) from rest
    w, t = np.sqrt(dmp.k_s), trajectory.t
    closed_form = total * (1.0 - (1.0 + w * t) * np.exp(-w * t))
    assert np.max(np.abs(angle - closed_form)) < TOL_ATTRACTOR
    np.testing.assert_allclose(np.linalg.norm(trajectory.q, axis=1), 1.0, rtol=0, atol=1e-15)


def test_about_one_axis_it_is_the_position_dmp_of_the_angle():
    """Forcing only about the start-goal axis (z) keeps the motion on that axis; the angle is
    then DMP's exact integration of eq. 2.23 (itself held against closed forms in test_dmp)."""
    weights = np.zeros((3, 10))
    weights[2] = 300.0 * np.random.default_rng(RNG_SEED).normal(size=10)
    q0 = quaternion.exp_map(np.array([0.0, 0.0, -0.4]))
    goal = quaternion.exp_map(np.array([0.0, 0.0, 1.1]))
    orientation = QuaternionDMP(10, 0.7, q0, goal)
    orientation.set_theta(weights.reshape(-1))
    angle_dmp = DMP(1, 10, 0.7, [-0.4], [1.1])
    angle_dmp.set_theta(weights[2])
    rotation, angle = orientation.integrate(0.005, 1.0), angle_dmp.integrate(0.005, 1.0)
    rotvec = to_rotation(rotation.q).as_rotvec()
    np.testing.assert_allclose(rotvec[:, :2], 0.0, rtol=0.0, atol=TOL_ATTRACTOR)
    np.testing.assert_allclose(rotvec[:, 2], angle.y[:, 0], rtol=0.0, atol=TOL_ATTRACTOR)
    np.testing.assert_allclose(rotation.omega[:, 2], angle.yd[:, 0], rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(rotation.omega_dot[:, 2], angle.ydd[:, 0], rtol=0.0, atol=1e-10)


def test_a_zero_length_integration_is_the_start():
    dmp = QuaternionDMP(4, 1.0, quaternion.exp_map(np.array([0.1, 0.0, 0.0])),
                        quaternion.IDENTITY)
    trajectory = dmp.integrate(0.01, t_end=0.0)
    np.testing.assert_array_equal(trajectory.t, [0.0])
    np.testing.assert_array_equal(trajectory.q, dmp.q0[None])
    np.testing.assert_array_equal(trajectory.omega, np.zeros((1, 3)))


def equation_16_17(dmp: QuaternionDMP, forcing):
    """Right-hand side of eq. 16-17 on the state [q (4), omega (3)], written out independently
    of the module: ``[0, omega] * q`` as a 4x4 matrix, the rotation error by scipy, q
    normalised; ``forcing(t)`` gives f (3,)."""
    goal, tau = to_rotation(dmp.goal), dmp.time_scale

    def rhs(t, state):
        q = state[:4] / np.linalg.norm(state[:4])
        omega = state[4:]
        ox, oy, oz = omega
        left = np.array([[0.0, -ox, -oy, -oz], [ox, 0.0, -oz, oy],
                         [oy, oz, 0.0, -ox], [oz, -oy, ox, 0.0]])  # [0, omega] * q
        error = (goal * to_rotation(q).inv()).as_rotvec()
        omega_dot = (dmp.k_s * error - dmp.k_d * tau * omega + forcing(t)) / tau**2
        return np.concatenate([0.5 * left @ q, omega_dot])

    return rhs


def continuous_forcing(dmp: QuaternionDMP, weights: np.ndarray):
    """f(t) of eq. 2.24 for the linear canonical system, written out: phase and gate
    ``max(0, 1 - t / duration)``, Gaussians of width 0.5 centre spacings."""
    centres = np.linspace(0.0, 1.0, dmp.n_basis)
    width = 1.0 / (2.0 * (0.5 / (dmp.n_basis - 1)) ** 2)

    def forcing(t):
        x = max(0.0, 1.0 - t / dmp.duration)
        psi = np.exp(-width * (x - centres) ** 2)
        return x * (weights @ psi) / psi.sum()

    return forcing


def reference_continuous(dmp: QuaternionDMP, weights: np.ndarray, t_eval: np.ndarray):
    """Eq. 16-17 by RK45 (rtol 1e-10) with the forcing continuous in time: q (T, 4) at t_eval
    (integrated apart before and after the gate's kink at the duration)."""
    rhs = equation_16_17(dmp, continuous_forcing(dmp, weights))
    state = np.concatenate([dmp.q0, np.zeros(3)])
    pieces = []
    for start, stop in ((0.0, dmp.duration), (dmp.duration, t_eval[-1])):
        solution = solve_ivp(rhs, (start, stop), state, method='RK45', rtol=1e-10,
                             atol=1e-12, dense_output=True)
        assert solution.success
        inside = t_eval[(t_eval >= start) & ((t_eval < stop) | (stop == t_eval[-1]))]
        pieces.append(solution.sol(inside)[:4].T)
        state = solution.y[:, -1]
    q = np.vstack(pieces)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def reference_held(dmp: QuaternionDMP, weights: np.ndarray, t_eval: np.ndarray):
    """Eq. 16-17 by RK45 (rtol 1e-10) step by step over the grid t_eval, with the forcing held
    over each step at its value at the step's start, as the module holds it: q (T, 4)."""
    forcing = continuous_forcing(dmp, weights)
    state = np.concatenate([dmp.q0, np.zeros(3)])
    q = [state[:4]]
    for start, stop in zip(t_eval[:-1], t_eval[1:]):
        held = forcing(start)
        solution = solve_ivp(equation_16_17(dmp, lambda _t: held), (start, stop), state,
                             method='RK45', rtol=1e-10, atol=1e-12)
        assert solution.success
        state = solution.y[:, -1]
        state[:4] /= np.linalg.norm(state[:4])
        q.append(state[:4])
    return np.array(q)


@pytest.mark.parametrize('reference, tolerance_per_dt', [
    (reference_continuous, TOL_REFERENCE_PER_DT), (reference_held, TOL_HELD_PER_DT)])
def test_integration_converges_to_the_fine_reference_at_first_order(reference,
                                                                     tolerance_per_dt):
    rng = np.random.default_rng(RNG_SEED)
    dmp = QuaternionDMP(8, 0.5, quaternion.exp_map(np.array([0.2, 0.1, -0.4])),
                        quaternion.exp_map(np.array([1.0, -0.6, 0.8])), time_scale=1.2)
    weights = 150.0 * rng.normal(size=(3, 8))
    dmp.set_theta(weights.reshape(-1))
    t_end = 0.8  # past the duration: the gate's kink and the settling
    errors = []
    for dt in (4e-3, 2e-3):
        trajectory = dmp.integrate(dt, t_end)
        errors.append(np.max(angle_between(trajectory.q, reference(dmp, weights,
                                                                   trajectory.t))))
        assert errors[-1] < tolerance_per_dt * dt
    assert errors[1] < 0.6 * errors[0]  # halving dt halves the error (or better)


def test_time_scale_gives_the_same_path_slower():
    theta = 80.0 * np.random.default_rng(RNG_SEED).normal(size=3 * 6)
    q0, goal = quaternion.exp_map(np.array([0.1, 0.2, 0.3])), quaternion.IDENTITY
    fast = QuaternionDMP(6, 0.5, q0, goal)
    slow = QuaternionDMP(6, 1.5, q0, goal, time_scale=3.0)
    fast.set_theta(theta)
    slow.set_theta(theta)
    one, three = fast.integrate(0.002, 0.8), slow.integrate(0.006, 2.4)
    np.testing.assert_allclose(three.q, one.q, rtol=0.0, atol=1e-13)
    np.testing.assert_allclose(3.0 * three.omega, one.omega, rtol=0.0, atol=1e-11)


# -- fitting --------------------------------------------------------------------------------------
DEMO_DURATION = 1.5
DEMO_AXIS = np.array([1.0, 2.0, -1.0]) / np.sqrt(6.0)
DEMO_START = quaternion.exp_map(np.array([0.3, -0.5, 0.2]))


def demonstration(t: np.ndarray) -> np.ndarray:
    """Minimum-jerk turn of 2 rad about a fixed axis, with a wobble of up to 0.2 rad whose
    velocity and acceleration vanish at both ends: q (T, 4), [w, x, y, z], by scipy."""
    s = np.clip(t / DEMO_DURATION, 0.0, 1.0)
    angle = 2.0 * (10.0 * s**3 - 15.0 * s**4 + 6.0 * s**5)
    bump = 64.0 * s**3 * (1.0 - s) ** 3
    wobble = 0.2 * bump[:, None] * np.column_stack(
        [np.cos(2 * np.pi * s), np.sin(2 * np.pi * s), 0.5 * np.ones_like(s)])
    rotation = (Rotation.from_rotvec(angle[:, None] * DEMO_AXIS) * Rotation.from_rotvec(wobble)
                * to_rotation(DEMO_START))
    xyzw = rotation.as_quat()
    return xyzw[:, [3, 0, 1, 2]]


@pytest.mark.parametrize('learn_goal', [False, True])
def test_fit_reproduces_a_smooth_demonstration(learn_goal):
    t_demo = np.linspace(0.0, DEMO_DURATION, 1501)
    q_demo = demonstration(t_demo)
    q_demo[1::2] *= -1.0  # either sign of a quaternion is the same orientation
    default_goal = quaternion.IDENTITY
    dmp = QuaternionDMP(40, DEMO_DURATION, quaternion.IDENTITY, default_goal,
                        learn_goal=learn_goal)
    dt = 2e-3
    dmp.fit(t_demo, q_demo, dt)
    trajectory = dmp.integrate(dt)
    assert np.max(angle_between(trajectory.q, demonstration(trajectory.t))) < FIT_TOL
    end = demonstration(np.array([DEMO_DURATION]))[0]
    assert angle_between(dmp.goal, end) < TOL_MAP
    assert angle_between(dmp.q0, DEMO_START) < TOL_MAP
    if learn_goal:  # the goal is in theta, relative to the unchanged default goal
        np.testing.assert_array_equal(dmp.default_goal, default_goal)
        offset = dmp.get_theta()[dmp.num_weights:]
        np.testing.assert_allclose(offset, to_rotation(end).as_rotvec(), rtol=0, atol=TOL_MAP)


@pytest.mark.parametrize('time_scale', [1.0, 1.7])
def test_fit_inverts_the_integration_step(time_scale):
    """With a Gaussian per grid point the basis represents the forcing targets, and a forcing
    equal to them reproduces the resampled demonstration: only rounding and the ridge remain."""
    t_demo = np.linspace(0.0, DEMO_DURATION, 1501)
    dt = 0.02
    n_points = int(round(DEMO_DURATION / dt)) + 1
    dmp = QuaternionDMP(n_points, DEMO_DURATION, quaternion.IDENTITY, quaternion.IDENTITY,
                        time_scale=time_scale)
    trajectory = dmp.fit(t_demo, demonstration(t_demo), dt).integrate(dt)
    assert np.max(angle_between(trajectory.q, demonstration(trajectory.t))) < FIT_EXACT_TOL


# -- population and learned goal -----------------------------------------------------------------
def test_population_equals_one_by_one():
    rng = np.random.default_rng(RNG_SEED)
    dmp = QuaternionDMP(10, 0.8, quaternion.exp_map(np.array([0.5, 0.0, -0.3])),
                        quaternion.exp_map(np.array([-0.4, 1.1, 0.2])), learn_goal=True)
    thetas = np.hstack([100.0 * rng.normal(size=(5, dmp.num_weights)),
                        0.5 * rng.normal(size=(5, 3))])
    population = dmp.integrate_population(0.004, thetas, t_end=1.0)
    assert population.q.shape == (5, 251, 4) and population.omega.shape == (5, 251, 3)
    for p, theta in enumerate(thetas):
        dmp.set_theta(theta)
        single = dmp.integrate(0.004, t_end=1.0)
        np.testing.assert_array_equal(population.t, single.t)
        for field in ('q', 'omega', 'omega_dot'):
            assert_within_ulps(getattr(population, field)[p], getattr(single, field))


def test_learned_goal_turns_the_end_by_its_rotation_vector():
    q0 = quaternion.exp_map(np.array([0.2, 0.4, -0.1]))
    default_goal = quaternion.exp_map(np.array([0.9, -0.3, 0.5]))
    dmp = QuaternionDMP(10, 0.5, q0, default_goal, learn_goal=True)
    shift = np.array([0.3, -0.5, 0.25])
    theta = np.concatenate([np.zeros(dmp.num_weights), shift])
    dmp.set_theta(theta)
    np.testing.assert_array_equal(dmp.get_theta(), theta)
    expected = Rotation.from_rotvec(shift) * to_rotation(default_goal)
    assert (to_rotation(dmp.goal) * expected.inv()).magnitude() < TOL_MAP
    end = dmp.integrate(1e-3, t_end=1.2).q[-1]
    assert (to_rotation(end) * expected.inv()).magnitude() < GOAL_TOL
    assert angle_between(end, default_goal) > np.linalg.norm(shift) - GOAL_TOL


# -- bad input -----------------------------------------------------------------------------------
@pytest.mark.parametrize('q0, message', [
    ([1.0, 1.0, 0.0, 0.0], 'q0 must be a unit quaternion'),
    ([np.nan, 0.0, 0.0, 1.0], 'q0 must be finite'),
    ([1.0, 0.0, 0.0], r'q0 must be a quaternion \[w, x, y, z\] of shape \(4,\)'),
])
def test_bad_start_orientation_is_refused(q0, message):
    with pytest.raises(ValueError, match=message):
        QuaternionDMP(5, 1.0, q0, quaternion.IDENTITY)


def test_bad_goal_theta_and_demonstration_are_refused():
    with pytest.raises(ValueError, match='goal must be a unit quaternion'):
        QuaternionDMP(5, 1.0, quaternion.IDENTITY, [0.5, 0.5, 0.5, 0.0])
    dmp = QuaternionDMP(5, 1.0, quaternion.IDENTITY, quaternion.IDENTITY, learn_goal=True)
    with pytest.raises(ValueError, match=r'theta must have 18 = 3 axes \* n_basis \+ 3'):
        dmp.set_theta(np.zeros(15))
    with pytest.raises(ValueError, match='theta must be finite'):
        dmp.set_theta(np.full(18, np.nan))
    with pytest.raises(ValueError, match=r'thetas must be \(P, 18\)'):
        dmp.integrate_population(0.01, np.zeros((2, 15)))
    t = np.linspace(0.0, 1.0, 11)
    q = np.tile(quaternion.IDENTITY, (11, 1))
    q[4] *= 1.01
    with pytest.raises(ValueError, match=r'unit quaternions .* \|q\[4\]\| = 1.01'):
        dmp.fit(t, q, 0.01)
    q[4] = np.nan
    with pytest.raises(ValueError, match='demonstration must be finite'):
        dmp.fit(t, q, 0.01)
    with pytest.raises(ValueError, match=r'q shape \(T, 4\)'):
        dmp.fit(t, q[:, :3], 0.01)
    with pytest.raises(ValueError, match='must cover'):
        dmp.fit(t[:6], np.tile(quaternion.IDENTITY, (6, 1)), 0.01)


# -- goal change (issue 26) -----------------------------------------------------------------------
def turning_dmp():
    from psl_controller.quaternion_dmp import QuaternionDMP
    dmp = QuaternionDMP(n_basis=5, duration=1.0, q0=quaternion.exp_map([0.1, 0.2, -0.1]),
                        goal=quaternion.exp_map([-0.3, 0.4, 0.6]))
    dmp.set_theta(np.random.default_rng(3).normal(0.0, 20.0, dmp.num_parameters))
    return dmp


def test_a_goal_change_to_the_same_goal_changes_nothing():
    dmp = turning_dmp()
    plain = dmp.integrate(0.002, 1.5)
    same = dmp.integrate_goal_change(0.002, 0.4, dmp.goal, 1.5)
    np.testing.assert_array_equal(same.q, plain.q)
    np.testing.assert_array_equal(same.omega, plain.omega)


def test_a_goal_change_turns_smoothly_to_the_new_goal():
    """Up to the grid point after the switch bit for bit the plain path; then omega
    continuous (no step larger than the plain path's largest plus the filter's), and the new
    goal reached."""
    dmp = turning_dmp()
    new_goal = quaternion.exp_map([0.5, -0.2, 0.9])
    plain = dmp.integrate(0.002, 2.0)
    changed = dmp.integrate_goal_change(0.002, 0.4, new_goal, 2.0, alpha_goal=10.0)
    k = 200
    np.testing.assert_array_equal(changed.q[:k + 2], plain.q[:k + 2])
    jumps = np.abs(np.diff(changed.omega, axis=0)).max()
    change = np.linalg.norm(quaternion.log_map(quaternion.product(
        new_goal, quaternion.conjugate(dmp.goal))))
    # the filter moves the goal by at most alpha |change| dt a step, which changes omega_dot
    # by k_s times that: omega's step grows by at most k_s alpha |change| dt^2 (a goal that
    # jumped would add k_s |change| dt, fifty times more)
    filter_step = 2 * 400.0 * 10.0 * change * 0.002**2
    assert jumps <= np.abs(np.diff(plain.omega, axis=0)).max() + filter_step
    assert np.linalg.norm(quaternion.log_map(quaternion.product(
        new_goal, quaternion.conjugate(changed.q[-1])))) < 1e-3


def test_bad_goal_changes_are_refused():
    dmp = turning_dmp()
    for goal, t_switch, alpha, words in (([1.0, 0.0, 0.0], 0.2, 10.0, 'new_goal'),
                                         ([2.0, 0.0, 0.0, 0.0], 0.2, 10.0, 'unit'),
                                         ([1.0, 0.0, 0.0, 0.0], 5.0, 10.0, 't_switch'),
                                         ([1.0, 0.0, 0.0, 0.0], 0.2, 0.0, 'alpha_goal')):
        with pytest.raises(ValueError, match=words):
            dmp.integrate_goal_change(0.002, t_switch, goal, 1.5, alpha_goal=alpha)
