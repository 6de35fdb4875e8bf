"""Tests of `SampledTrajectory` (JTC's sampling, `joint_trajectory_controller/src/trajectory.cpp`)
against independent references:

* closed forms: a polynomial of degree 1 / 3 / 5 whose values (and derivatives) are given at the
  points is reproduced between the points by the linear / cubic / quintic interpolation (an
  interpolant of that degree through a polynomial of that degree is the polynomial);
* a second implementation of a segment: the polynomial of the segment's degree solved from its
  boundary conditions with `np.linalg.solve` (no coefficient formula shared with the module);
* exact values where the module promises them (on a point, before the first, past the end).

Tolerances (absolute, scaled by the magnitude of the quantity compared):
``TOL_ROUNDING`` bounds what rounding leaves of the closed forms; the interpolants evaluate
powers of the time within a segment (up to T^5 over coefficients divided by T^5), so their
rounding grows with the derivative taken and with short segments: the k-th derivative is
compared with ``TOL_ROUNDING * scale / T_min^k`` (T_min the shortest segment, in s).
"""

import numpy as np
import pytest

from psl_controller.trajectory_sampling import (CUBIC, LINEAR, QUINTIC, SampledTrajectory,
                                                TrajectorySample)

NS = 1_000_000_000
TOL_ROUNDING = 1e-12        # relative to a quantity's scale, per derivative / T_min (above)

# irregular point times [ns] (segments 0.3 s to 2.3 s, one odd nanosecond count)
POINT_TIMES_NS = np.array([0, 300_000_000, 1_000_000_000, 1_700_000_001, 4_000_000_000],
                          dtype=np.int64)
T_MIN = 0.3                 # s, the shortest segment of POINT_TIMES_NS
DEGREES = {LINEAR: 1, CUBIC: 3, QUINTIC: 5}
FIELDS = ('positions', 'velocities', 'accelerations', 'effort')


# -- independent references ----------------------------------------------------------------
def polynomial(degree: int, n_joints: int, seed: int) -> np.ndarray:
    """Random coefficients (degree + 1, n_joints), lowest power first, of a polynomial in t [s]
    (scaled so that its values over [0, 4] s stay of order 1)."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, (degree + 1, n_joints)) / 4.0 ** np.arange(degree + 1)[:, None]


def evaluate(coefficients: np.ndarray, t: np.ndarray, derivative: int = 0) -> np.ndarray:
    """The `derivative`-th derivative of the polynomial (degree + 1, n) at times t (T,) [s]:
    (T, n)."""
    c = np.polynomial.polynomial.polyder(coefficients, derivative, axis=0) \
        if derivative else coefficients
    return np.polynomial.polynomial.polyval(np.asarray(t, dtype=float), c).T


def solved_segment(length: float, start: list[np.ndarray], end: list[np.ndarray]) -> np.ndarray:
    """The polynomial in s (time from the segment's start) [s] of degree 2 len(start) - 1 with
    the derivatives 0..len(start)-1 given at s = 0 (`start`, each (n,)) and s = `length`
    (`end`): coefficients (degree + 1, n), from a linear system (not JTC's closed formulas)."""
    m = len(start)
    degree = 2 * m - 1
    rows, rhs = [], []
    for s, values in ((0.0, start), (length, end)):
        for k, value in enumerate(values):
            # d^k/ds^k s^p = p! / (p - k)! s^(p - k)
            rows.append([np.prod(np.arange(p - k + 1, p + 1)) * s ** (p - k) if p >= k else 0.0
                         for p in range(degree + 1)])
            rhs.append(value)
    return np.linalg.solve(np.array(rows), np.array(rhs))


def closed_form_trajectory(kind: str, seed: int = 0, times_ns=POINT_TIMES_NS, n_joints: int = 2):
    """A trajectory whose points carry a polynomial of the interpolation's degree (the fields
    the interpolation uses) and a linear effort; returns (trajectory, position polynomial,
    effort polynomial)."""
    coefficients = polynomial(DEGREES[kind], n_joints, seed)
    effort = polynomial(1, n_joints, seed + 100) * 10.0
    t = times_ns / NS
    velocities = evaluate(coefficients, t, 1) if kind in (CUBIC, QUINTIC) else None
    accelerations = evaluate(coefficients, t, 2) if kind == QUINTIC else None
    trajectory = SampledTrajectory(times_ns, evaluate(coefficients, t), velocities,
                                   evaluate(effort, t), accelerations)
    return trajectory, coefficients, effort


def random_trajectory(kind: str, seed: int, times_ns=POINT_TIMES_NS, n_joints: int = 3):
    """Points with random values (no polynomial behind them), all four fields as the kind uses;
    returns (trajectory, dict of the arrays given)."""
    rng = np.random.default_rng(seed)
    shape = (len(times_ns), n_joints)
    given = {'positions': rng.normal(size=shape), 'effort': rng.normal(size=shape),
             'velocities': rng.normal(size=shape) if kind != LINEAR else None,
             'accelerations': rng.normal(size=shape) if kind == QUINTIC else None}
    trajectory = SampledTrajectory(times_ns, given['positions'], given['velocities'],
                                   given['effort'], given['accelerations'])
    zeros = np.zeros(shape)
    return trajectory, {**{k: zeros if v is None else v for k, v in given.items()},
                        'linear': kind == LINEAR, 'times_ns': np.asarray(times_ns)}


def assert_close(actual, expected, scale, derivative=0):
    """Within the rounding of the closed form (module docstring) for that derivative."""
    atol = TOL_ROUNDING * max(1.0, scale) / T_MIN ** derivative
    np.testing.assert_allclose(actual, expected, rtol=0.0, atol=atol)


def assert_sample_equal(sample: TrajectorySample, expected: dict, i: int | None = None):
    """Every field bit for bit (row i of the expected arrays, or the arrays themselves); of a
    positions-only trajectory (`random_trajectory`'s 'linear', with its 'times_ns') the
    velocity on point i is the slope of the segment it starts, zero on the last (JTC)."""
    for field in FIELDS:
        want = expected[field] if i is None else expected[field][i]
        if field == 'velocities' and i is not None and expected.get('linear'):
            q = np.asarray(expected['positions'])
            times_ns, i = expected['times_ns'], i % len(q)
            want = (np.zeros_like(q[i]) if i == len(q) - 1 else
                    (q[i + 1] - q[i]) / ((times_ns[i + 1] - times_ns[i]) * 1e-9))
        np.testing.assert_array_equal(getattr(sample, field), want, err_msg=field)


def queries_between_points(n: int, seed: int) -> np.ndarray:
    """Random integer query times strictly between the first and last point, none on a point."""
    t = np.random.default_rng(seed).integers(1, POINT_TIMES_NS[-1], size=n)
    return t[~np.isin(t, POINT_TIMES_NS)]


# -- the interpolation chosen by the fields ------------------------------------------------
def test_the_interpolation_follows_the_fields_given():
    times, q = np.array([0, NS]), np.zeros((2, 2))
    assert SampledTrajectory(times, q).interpolation == LINEAR
    assert SampledTrajectory(times, q, q).interpolation == CUBIC
    assert SampledTrajectory(times, q, q, accelerations=q).interpolation == QUINTIC
    assert not SampledTrajectory(times, q).has_effort
    assert SampledTrajectory(times, q, efforts=q).has_effort


# -- closed forms between points -------------------------------------------------------------
@pytest.mark.parametrize('kind', [LINEAR, CUBIC, QUINTIC])
def test_between_points_a_polynomial_of_the_interpolations_degree_is_reproduced(kind):
    """Positions (and velocities / accelerations) of a polynomial of degree 1 / 3 / 5 at the
    points: between them the sample is the polynomial, its first and second derivative (the
    linear interpolant's velocity is its slope, its acceleration zero); effort, linear in time
    at the points, is reproduced by its linear interpolation."""
    trajectory, coefficients, effort = closed_form_trajectory(kind, seed=1)
    t_ns = queries_between_points(400, seed=2)
    t = t_ns / NS
    scale = np.abs(evaluate(coefficients, np.linspace(0, 4, 50))).max()
    samples = [trajectory.sample(int(k)) for k in t_ns]
    actual = {field: np.array([getattr(s, field) for s in samples]) for field in FIELDS}
    assert_close(actual['positions'], evaluate(coefficients, t), scale, 0)
    assert_close(actual['velocities'], evaluate(coefficients, t, 1), scale, 1)
    if kind == LINEAR:
        np.testing.assert_array_equal(actual['accelerations'], 0.0)
    else:
        assert_close(actual['accelerations'], evaluate(coefficients, t, 2), scale, 2)
    assert_close(actual['effort'], evaluate(effort, t), np.abs(effort).sum() * 4, 0)


@pytest.mark.parametrize('kind', [CUBIC, QUINTIC])
def test_a_lower_interpolation_does_not_reproduce_a_higher_polynomial(kind):
    """The references above can fail: a cubic polynomial given with positions only (linear
    interpolation) or a quintic given with positions and velocities only (cubic) is not
    reproduced, by far more than the rounding tolerance."""
    coefficients = polynomial(DEGREES[kind], 2, seed=3)
    t = POINT_TIMES_NS / NS
    lower = SampledTrajectory(POINT_TIMES_NS, evaluate(coefficients, t),
                              evaluate(coefficients, t, 1) if kind == QUINTIC else None)
    t_ns = queries_between_points(50, seed=4)
    q = np.array([lower.sample(int(k)).positions for k in t_ns])
    assert np.abs(q - evaluate(coefficients, t_ns / NS)).max() > 1e-4


@pytest.mark.parametrize('kind', [LINEAR, CUBIC, QUINTIC])
def test_between_arbitrary_points_each_segment_is_the_solved_polynomial(kind):
    """Random point values (no polynomial behind them): each segment is the polynomial of the
    interpolation's degree with the ends' values solved from a linear system (a second
    implementation); effort the straight line between the ends."""
    trajectory, given = random_trajectory(kind, seed=5)
    m = (DEGREES[kind] + 1) // 2                # derivatives met at each end
    derivative_fields = ('positions', 'velocities', 'accelerations')[:m]
    for i in range(len(POINT_TIMES_NS) - 1):
        t0, t1 = int(POINT_TIMES_NS[i]), int(POINT_TIMES_NS[i + 1])
        length = (t1 - t0) / NS
        c = solved_segment(length, [given[f][i] for f in derivative_fields],
                           [given[f][i + 1] for f in derivative_fields])
        for t_ns in (t0 + 1, t0 + (t1 - t0) // 3, (t0 + t1) // 2, t1 - 1):
            s = (t_ns - t0) / NS
            sample = trajectory.sample(t_ns)
            scale = np.abs(given['positions']).max() + np.abs(given['velocities']).max() * length
            for k, field in enumerate(('positions', 'velocities', 'accelerations')):
                assert_close(getattr(sample, field), evaluate(c, [s], k)[0],
                             scale + np.abs(given['accelerations']).max() * length ** 2, k)
            line = given['effort'][i] + (given['effort'][i + 1] - given['effort'][i]) * s / length
            assert_close(sample.effort, line, np.abs(given['effort']).max())


def test_linear_between_points_of_a_quadratic_is_the_chord():
    """Midway between two points of q(t) = t^2 the sample is the chord's value (q_a + q_b) / 2,
    the velocity the chord's slope, the acceleration zero."""
    times_ns = np.array([0, 2 * NS, 6 * NS], dtype=np.int64)
    seconds = times_ns / NS
    trajectory = SampledTrajectory(times_ns, (seconds ** 2)[:, None])
    sample = trajectory.sample(4 * NS)
    atol = TOL_ROUNDING * 36.0                      # rounding on values up to 36
    np.testing.assert_allclose(sample.positions, [(4.0 + 36.0) / 2.0], rtol=0.0, atol=atol)
    np.testing.assert_allclose(sample.velocities, [(36.0 - 4.0) / 4.0], rtol=0.0, atol=atol)
    np.testing.assert_array_equal(sample.accelerations, [0.0])
    np.testing.assert_array_equal(sample.effort, [0.0])


# -- exactly on points -----------------------------------------------------------------------
@pytest.mark.parametrize('kind', [LINEAR, CUBIC, QUINTIC])
def test_exactly_on_points_the_points_values_bit_for_bit(kind):
    """On every point (first and last too) each field is the point's own, bit for bit (the
    accelerations a kind does not give are zero); one nanosecond off a point is interpolated.
    (A linear trajectory's velocity on a point: the test below.)"""
    times_ns = np.array([5, 1_000_000_007, 2_000_000_011, 999_999_999_999], dtype=np.int64)
    trajectory, given = random_trajectory(kind, seed=6, times_ns=times_ns)
    fields = [f for f in FIELDS if kind != LINEAR or f != 'velocities']
    for i, t_ns in enumerate(times_ns):
        sample = trajectory.sample(int(t_ns))
        for field in fields:
            np.testing.assert_array_equal(getattr(sample, field), given[field][i],
                                          err_msg=field)
    off = trajectory.sample(int(times_ns[1]) + 1)
    assert not np.array_equal(off.positions, given['positions'][1])


def test_linear_on_a_point_the_velocity_is_the_segments_slope():
    """JTC (trajectory.cpp, `sample`): a time t_i of a point that is not the last falls in the
    segment [t_i, t_{i+1}) and is interpolated there; with positions only (linear) the velocity
    is that segment's slope (q_{i+1} - q_i) / (t_{i+1} - t_i), the position q_i itself. On the
    last point (played out) the velocity is zero. (Caught: the point's stored velocity, zero,
    returned: the Kd term then pulls by Kd times the slope at every point.)"""
    trajectory = SampledTrajectory(np.array([0, NS, 2 * NS]), [[0.0], [1.0], [3.0]])
    np.testing.assert_array_equal(trajectory.sample(2 * NS).velocities, [0.0])  # last: holds
    np.testing.assert_array_equal(trajectory.sample(NS).positions, [1.0])       # holds
    np.testing.assert_array_equal(trajectory.sample(0).velocities, [1.0])
    np.testing.assert_array_equal(trajectory.sample(NS).velocities, [2.0])


# -- before the first point ------------------------------------------------------------------
@pytest.mark.parametrize('kind', [LINEAR, CUBIC, QUINTIC])
def test_before_the_first_point_the_first_position_at_rest_with_its_effort(kind):
    """No point before the trajectory: the first point's position, zero velocity and
    acceleration (not the first point's), its effort; at the first point its own values."""
    times_ns = POINT_TIMES_NS + 2 * NS          # the first point 2 s after the start
    trajectory, given = random_trajectory(kind, seed=7, times_ns=times_ns)
    zeros = np.zeros(3)
    for t_ns in (-5 * NS, -1, 0, 2 * NS - 1):
        assert_sample_equal(trajectory.sample(t_ns), {
            'positions': given['positions'][0], 'velocities': zeros, 'accelerations': zeros,
            'effort': given['effort'][0]})
    assert_sample_equal(trajectory.sample(2 * NS), given, 0)


@pytest.mark.parametrize('kind', [LINEAR, CUBIC, QUINTIC])
def test_starting_from_a_state_the_segment_to_the_first_point(kind):
    """`starting_from(t_b, q_b, qd_b)`: from t_b to the first point the segment of the first
    point's degree from (q_b, qd_b, acceleration 0) to the first point (solved independently;
    linear: qd_b plays no part), effort the line from zero to the first point's; at the first
    point its values bit for bit; the trajectory it was made from is unchanged."""
    times_ns = POINT_TIMES_NS + 2 * NS
    trajectory, given = random_trajectory(kind, seed=8, times_ns=times_ns)
    q_b, qd_b = np.array([0.3, -0.2, 0.5]), np.array([1.0, -0.5, 0.25])
    t_b = 500_000_000                               # 1.5 s before the first point
    before = trajectory.starting_from(t_b, q_b, qd_b)
    length = (times_ns[0] - t_b) / NS
    start = [q_b, qd_b, np.zeros(3)]
    m = (DEGREES[kind] + 1) // 2
    fields = ('positions', 'velocities', 'accelerations')
    c = solved_segment(length, start[:m], [given[f][0] for f in fields[:m]])
    scale = 5.0
    for t_ns in (t_b, t_b + 1, 1_000_000_000, 1_777_777_777, int(times_ns[0]) - 1):
        s = (t_ns - t_b) / NS
        sample = before.sample(t_ns)
        for k, field in enumerate(fields):
            assert_close(getattr(sample, field), evaluate(c, [s], k)[0], scale, k)
        assert_close(sample.effort, given['effort'][0] * s / length, scale)
    assert_sample_equal(before.sample(int(times_ns[0])), given, 0)
    # the original has no point before it
    np.testing.assert_array_equal(trajectory.sample(t_b).positions, given['positions'][0])


def test_starting_from_a_linear_trajectory_ignores_the_velocity():
    trajectory, _ = random_trajectory(LINEAR, seed=9, times_ns=POINT_TIMES_NS + NS)
    q_b = np.array([0.1, 0.2, 0.3])
    a = trajectory.starting_from(0, q_b, np.array([5.0, -5.0, 1.0])).sample(NS // 3)
    b = trajectory.starting_from(0, q_b, np.zeros(3)).sample(NS // 3)
    assert_sample_equal(a, b._asdict())


@pytest.mark.parametrize('t_b', [0, POINT_TIMES_NS[1]])
def test_starting_from_at_or_past_the_first_point_changes_nothing(t_b):
    """A point before the trajectory at or after its first point has no effect: every sample
    (before, on and between points) is bit for bit the original's."""
    trajectory, _ = random_trajectory(CUBIC, seed=10)     # first point at 0
    changed = trajectory.starting_from(int(t_b), np.full(3, 9.0), np.full(3, 9.0))
    # also replacing an earlier point before the trajectory (at -1 s)
    replaced = trajectory.starting_from(-NS, np.full(3, 7.0), np.full(3, 7.0)).starting_from(
        int(t_b), np.full(3, 9.0), np.full(3, 9.0))
    for t_ns in (-NS // 2, -1):
        assert_sample_equal(replaced.sample(t_ns), trajectory.sample(t_ns)._asdict())
    for t_ns in (-NS, 0, 1, 123_456_789, int(POINT_TIMES_NS[2]), 5 * NS):
        assert_sample_equal(changed.sample(t_ns), trajectory.sample(t_ns)._asdict())


def test_before_the_point_before_the_trajectory_the_first_point_at_rest():
    """Module docstring: "before t_b, or with no such point: the first point's position with
    zero velocity and acceleration and its effort" (not the point before the trajectory)."""
    times_ns = POINT_TIMES_NS + 2 * NS
    trajectory, given = random_trajectory(CUBIC, seed=11, times_ns=times_ns)
    before = trajectory.starting_from(NS, np.array([0.3, -0.2, 0.5]), np.ones(3))
    zeros = np.zeros(3)
    for t_ns in (-NS, 0, NS - 1):
        assert_sample_equal(before.sample(t_ns), {
            'positions': given['positions'][0], 'velocities': zeros, 'accelerations': zeros,
            'effort': given['effort'][0]})


# -- past the end ----------------------------------------------------------------------------
@pytest.mark.parametrize('kind', [LINEAR, CUBIC, QUINTIC])
def test_past_the_end_the_last_point_as_given(kind):
    """Past the last point: the last point's four fields as given, bit for bit (its velocity
    and acceleration too: JTC holds the point; an accepted trajectory ends at rest)."""
    trajectory, given = random_trajectory(kind, seed=12)
    end = int(POINT_TIMES_NS[-1])
    for t_ns in (end, end + 1, end + 10 * NS):
        assert_sample_equal(trajectory.sample(t_ns), given, -1)
    assert_sample_equal(trajectory.last_point(), given, -1)


def test_duration_and_is_finished():
    trajectory, _ = random_trajectory(LINEAR, seed=13)
    end = int(POINT_TIMES_NS[-1])
    assert trajectory.duration_ns == end
    assert trajectory.n_points == 5 and trajectory.n_joints == 3
    assert not trajectory.is_finished(0)
    assert not trajectory.is_finished(end - 1)
    assert trajectory.is_finished(end)
    assert trajectory.is_finished(end + 1)


def test_single_point_trajectory():
    """One point at 1 s: before it the position at rest with its effort, on and after it the
    point as given."""
    trajectory = SampledTrajectory(np.array([NS], dtype=np.int64), [[0.5, -0.5]],
                                   [[1.0, 2.0]], [[3.0, 4.0]])
    assert trajectory.duration_ns == NS
    for t_ns, expected_qd in ((0, [0.0, 0.0]), (NS - 1, [0.0, 0.0]), (NS, [1.0, 2.0]),
                              (3 * NS, [1.0, 2.0])):
        sample = trajectory.sample(t_ns)
        np.testing.assert_array_equal(sample.positions, [0.5, -0.5])
        np.testing.assert_array_equal(sample.velocities, expected_qd)
        np.testing.assert_array_equal(sample.effort, [3.0, 4.0])
    assert not trajectory.is_finished(NS - 1) and trajectory.is_finished(NS)


def test_samples_are_copies():
    """Changing a sample (on a point, before the first, past the end) changes nothing of the
    trajectory nor of the state given to starting_from."""
    trajectory, given = random_trajectory(CUBIC, seed=14, times_ns=POINT_TIMES_NS + NS)
    q_b = np.array([0.1, 0.2, 0.3])
    before = trajectory.starting_from(0, q_b, np.zeros(3))
    q_b[:] = 7.0
    for t_ns in (0, NS - 1, NS, 20 * NS):
        for traj in (trajectory, before):
            sample = traj.sample(t_ns)
            for field in FIELDS:
                getattr(sample, field)[:] = 42.0
    for i, t_ns in enumerate(POINT_TIMES_NS + NS):
        assert_sample_equal(trajectory.sample(int(t_ns)), given, i)
    np.testing.assert_array_equal(before.sample(0).positions, [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(trajectory.sample(0).positions, given['positions'][0])


# -- validation ------------------------------------------------------------------------------
@pytest.mark.parametrize('times_ns, positions, match', [
    (np.array([], dtype=np.int64), np.zeros((0, 2)), 'empty'),
    (np.array([[0, 5]], dtype=np.int64), np.zeros((2, 2)), 'shape'),
    (np.array([0, 5, 5], dtype=np.int64), np.zeros((3, 2)), 'increasing'),
    (np.array([0, 5, 3], dtype=np.int64), np.zeros((3, 2)), 'increasing'),
    (np.array([-1, 5], dtype=np.int64), np.zeros((2, 2)), '>= 0'),
    (np.array([0.0, 0.5]), np.zeros((2, 2)), 'integer'),
    (np.array([0, 5], dtype=np.int64), np.zeros((3, 2)), 'shape'),
    (np.array([0, 5], dtype=np.int64), np.zeros(2), 'shape'),
    (np.array([0, 5], dtype=np.int64), np.array([[0.0, np.nan], [0.0, 0.0]]), 'finite'),
])
def test_invalid_trajectories_raise(times_ns, positions, match):
    with pytest.raises(ValueError, match=match):
        SampledTrajectory(times_ns, positions)


@pytest.mark.parametrize('field', ['velocities', 'efforts', 'accelerations'])
def test_invalid_optional_fields_raise(field):
    times_ns, q = np.array([0, NS], dtype=np.int64), np.zeros((2, 2))
    extra = {'velocities': q} if field == 'accelerations' else {}
    with pytest.raises(ValueError, match=field):
        SampledTrajectory(times_ns, q, **extra, **{field: np.zeros((2, 3))})
    with pytest.raises(ValueError, match=field):
        SampledTrajectory(times_ns, q, **extra, **{field: np.full((2, 2), np.inf)})


def test_accelerations_need_velocities():
    times_ns, q = np.array([0, NS], dtype=np.int64), np.zeros((2, 2))
    with pytest.raises(ValueError, match='accelerations need velocities'):
        SampledTrajectory(times_ns, q, accelerations=q)


def test_the_query_time_is_an_integer():
    trajectory = SampledTrajectory(np.array([0, NS], dtype=np.int64), np.zeros((2, 2)))
    for bad in (0.5, 1.0, True, None):
        with pytest.raises(TypeError):
            trajectory.sample(bad)
    with pytest.raises(TypeError):
        trajectory.starting_from(0.5, np.zeros(2), np.zeros(2))
    assert trajectory.sample(np.int64(NS)).positions.shape == (2,)
