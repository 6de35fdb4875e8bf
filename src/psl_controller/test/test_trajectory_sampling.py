"""Tests of trajectory sampling against closed-form polynomials and every edge case."""

import numpy as np
import pytest

from psl_controller.trajectory_sampling import SampledTrajectory

TOL = 1e-12  # interpolation of polynomials of degree <= 1 is exact up to rounding
NS = 1_000_000_000

# Linear-in-time closed forms: q(t) = A + B t, qd(t) = C + D t, effort(t) = E + F t (t in s).
A, B = np.array([0.1, -0.3]), np.array([0.5, 2.0])
C, D = np.array([1.0, -1.0]), np.array([0.25, 0.0])
E, F = np.array([3.0, 0.0]), np.array([-1.0, 4.0])
POINT_TIMES_NS = np.array([0, 300_000_000, 1_000_000_000, 1_700_000_001, 4_000_000_000],
                          dtype=np.int64)


def closed_form(t_ns):
    t = np.asarray(t_ns, dtype=float)[..., None] / NS
    return A + B * t, C + D * t, E + F * t


def linear_trajectory(times_ns=POINT_TIMES_NS):
    q, qd, u = closed_form(times_ns)
    return SampledTrajectory(times_ns, q, qd, u)


def test_between_points_matches_linear_closed_form():
    trajectory = linear_trajectory()
    queries = np.random.default_rng(0).integers(1, POINT_TIMES_NS[-1], size=300)
    for t_ns in queries:
        expected = closed_form(t_ns)
        for actual, reference in zip(trajectory.sample(int(t_ns)), expected):
            np.testing.assert_allclose(actual, reference, rtol=0.0, atol=TOL)


def test_between_points_is_chord_of_quadratic():
    """Midway between two points of q(t) = t^2 the sample is the chord value (q_a + q_b) / 2."""
    times_ns = np.array([0, 2 * NS, 6 * NS], dtype=np.int64)
    seconds = times_ns / NS
    trajectory = SampledTrajectory(times_ns, (seconds**2)[:, None])
    q, qd, u = trajectory.sample(4 * NS)
    np.testing.assert_allclose(q, [(4.0 + 36.0) / 2.0], rtol=0.0, atol=TOL)
    np.testing.assert_array_equal(qd, [0.0])
    np.testing.assert_array_equal(u, [0.0])


def test_exactly_on_points_returns_points_bit_for_bit():
    rng = np.random.default_rng(1)
    times_ns = np.array([5, 1_000_000_007, 2_000_000_011, 999_999_999_999], dtype=np.int64)
    positions, velocities, efforts = (rng.normal(size=(4, 3)) for _ in range(3))
    trajectory = SampledTrajectory(times_ns, positions, velocities, efforts)
    for i, t_ns in enumerate(times_ns):
        q, qd, u = trajectory.sample(int(t_ns))
        np.testing.assert_array_equal(q, positions[i])
        np.testing.assert_array_equal(qd, velocities[i])
        np.testing.assert_array_equal(u, efforts[i])
    # one nanosecond off a point is interpolated, not snapped
    q, _, _ = trajectory.sample(int(times_ns[1]) + 1)
    assert not np.array_equal(q, positions[1])


def test_before_start_holds_first_point_with_zero_velocity():
    times_ns = POINT_TIMES_NS + 2 * NS  # first point 2 s after the trajectory start
    q_points, qd_points, u_points = closed_form(times_ns)
    trajectory = SampledTrajectory(times_ns, q_points, qd_points, u_points)
    for t_ns in (-5 * NS, 0, 2 * NS - 1):
        q, qd, u = trajectory.sample(t_ns)
        np.testing.assert_array_equal(q, q_points[0])
        np.testing.assert_array_equal(qd, np.zeros(2))
        np.testing.assert_array_equal(u, u_points[0])
    _, qd, _ = trajectory.sample(2 * NS)
    np.testing.assert_array_equal(qd, qd_points[0])


def test_past_end_holds_last_position_with_zero_velocity():
    trajectory = linear_trajectory()
    q_points, qd_points, u_points = closed_form(POINT_TIMES_NS)
    end = int(POINT_TIMES_NS[-1])
    q, qd, u = trajectory.sample(end)
    np.testing.assert_array_equal(qd, qd_points[-1])  # on the last point: its velocity
    for t_ns in (end + 1, end + 10 * NS):
        q, qd, u = trajectory.sample(t_ns)
        np.testing.assert_array_equal(q, q_points[-1])
        np.testing.assert_array_equal(qd, np.zeros(2))
        np.testing.assert_array_equal(u, u_points[-1])


def test_duration_and_is_finished():
    trajectory = linear_trajectory()
    end = int(POINT_TIMES_NS[-1])
    assert trajectory.duration_ns == end
    assert trajectory.n_points == 5 and trajectory.n_joints == 2
    assert not trajectory.is_finished(0)
    assert not trajectory.is_finished(end - 1)
    assert trajectory.is_finished(end)
    assert trajectory.is_finished(end + 1)


def test_single_point_trajectory():
    trajectory = SampledTrajectory(np.array([NS], dtype=np.int64), [[0.5, -0.5]],
                                   [[1.0, 2.0]], [[3.0, 4.0]])
    assert trajectory.duration_ns == NS
    for t_ns, expected_qd in ((0, [0.0, 0.0]), (NS, [1.0, 2.0]), (3 * NS, [0.0, 0.0])):
        q, qd, u = trajectory.sample(t_ns)
        np.testing.assert_array_equal(q, [0.5, -0.5])
        np.testing.assert_array_equal(qd, expected_qd)
        np.testing.assert_array_equal(u, [3.0, 4.0])
    assert not trajectory.is_finished(NS - 1) and trajectory.is_finished(NS)


def test_missing_velocities_and_efforts_are_zero():
    times_ns = np.array([0, NS], dtype=np.int64)
    trajectory = SampledTrajectory(times_ns, [[0.0], [2.0]])
    q, qd, u = trajectory.sample(NS // 4)
    np.testing.assert_allclose(q, [0.5], rtol=0.0, atol=TOL)
    np.testing.assert_array_equal(qd, [0.0])
    np.testing.assert_array_equal(u, [0.0])


def test_samples_are_copies():
    trajectory = linear_trajectory()
    q, qd, u = trajectory.sample(0)
    q[:] = 42.0
    u[:] = 42.0
    q_again, _, u_again = trajectory.sample(0)
    np.testing.assert_array_equal(q_again, A)
    np.testing.assert_array_equal(u_again, E)


@pytest.mark.parametrize('times_ns, positions, match', [
    (np.array([], dtype=np.int64), np.zeros((0, 2)), 'empty'),
    (np.array([0, 5, 5], dtype=np.int64), np.zeros((3, 2)), 'increasing'),
    (np.array([0, 5, 3], dtype=np.int64), np.zeros((3, 2)), 'increasing'),
    (np.array([-1, 5], dtype=np.int64), np.zeros((2, 2)), '>= 0'),
    (np.array([0.0, 0.5]), np.zeros((2, 2)), 'integer'),
    (np.array([0, 5], dtype=np.int64), np.zeros((3, 2)), 'shape'),
    (np.array([0, 5], dtype=np.int64), np.array([[0.0, np.nan], [0.0, 0.0]]), 'finite'),
])
def test_invalid_trajectories_raise(times_ns, positions, match):
    with pytest.raises(ValueError, match=match):
        SampledTrajectory(times_ns, positions)


def test_invalid_velocities_efforts_and_query_time_raise():
    times_ns = np.array([0, NS], dtype=np.int64)
    with pytest.raises(ValueError, match='velocities'):
        SampledTrajectory(times_ns, np.zeros((2, 2)), velocities=np.zeros((2, 3)))
    with pytest.raises(ValueError, match='efforts'):
        SampledTrajectory(times_ns, np.zeros((2, 2)), efforts=np.full((2, 2), np.inf))
    trajectory = SampledTrajectory(times_ns, np.zeros((2, 2)))
    with pytest.raises(TypeError):
        trajectory.sample(0.5)
    assert trajectory.sample(np.int64(NS))[0].shape == (2,)
