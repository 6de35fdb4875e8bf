"""Tests of `TrajectoryController` (JTC's goal semantics on the effort interface, no ROS), each
rule of its module docstring against references written here: the torque against the PD law
written in this file on a reference in closed form (a straight line in time given with its
velocity at the points, which the cubic interpolation reproduces to rounding), the served
reference against the trajectory's own
points (bit for bit on them), and a closed-loop plant in closed form (a unit mass per joint,
discretised exactly under a torque held over the period).

Tolerance: ``TOL_TORQUE`` (absolute, N m): the line's interpolation is exact up to rounding
(~1e-15 rad, rad/s on values of order 1), times gains of order 100: ~1e-13 N m; 1e-10 leaves room and
is far below any torque a wrong rule would give (order 0.1 N m and more here).
"""

import threading

import numpy as np
import pytest

from psl_controller.pd_law import PDLaw
from psl_controller.trajectory_controller import (GOAL_TOLERANCE_VIOLATED, INVALID_GOAL,
                                                  OLD_HEADER_TIMESTAMP,
                                                  PATH_TOLERANCE_VIOLATED, PREEMPTED,
                                                  SUCCESSFUL, Goal, GoalRefused, Result,
                                                  Tolerances, TrajectoryController)
from psl_controller.trajectory_sampling import SampledTrajectory

NS = 1_000_000_000
MS = 1_000_000
TOL_TORQUE = 1e-10                      # N m (module docstring)

JOINTS = ['shoulder', 'elbow']
KP, KD = np.array([100.0, 50.0]), np.array([10.0, 4.0])
LIMIT = np.array([1e3, 1e3])            # N m: no clipping unless a test narrows it
START = 10 * NS                         # a goal's start on the robot's clock

# the line q(s) = A + B s, effort E + F s, s [s] from the goal's start, over DURATION
A, B = np.array([0.2, -0.4]), np.array([0.6, 0.3])
E, F = np.array([1.5, -2.0]), np.array([-1.0, 4.0])
DURATION = NS                           # points every 0.25 s


# -- references written here -----------------------------------------------------------------
def pd(q, qd, q_ref, qd_ref, u_ffwd, limit=LIMIT):
    """The law: u = clip(Kp (q_ref - q) + Kd (qd_ref - qd) + u_ffwd, -limit, limit)."""
    return np.clip(KP * (np.asarray(q_ref) - q) + KD * (np.asarray(qd_ref) - qd) + u_ffwd,
                   -limit, limit)


def hold_torque(q, qd, held):
    """Holding the position `held` at rest without feed-forward."""
    return pd(q, qd, held, np.zeros(2), np.zeros(2))


def line_reference(s_ns: int, a=A, b=B, e=E, f=F, duration_ns=DURATION):
    """The line's reference at s_ns >= 0 from its start (closed form): (q, qd, effort); past
    the end its last point, as given (moving: the controller holds a last point as it is)."""
    s = min(s_ns, duration_ns) / NS
    return a + b * s, b, e + f * s


def line_trajectory(a=A, b=B, e=E, f=F, duration_ns=DURATION, n_points=5) -> SampledTrajectory:
    """Positions, velocities (cubic interpolation: the line itself) and effort, on the line.
    (Velocities are given: a positions-only trajectory has zero velocity on its points, see
    test_trajectory_sampling's BUG test of the linear case.)"""
    times = np.linspace(0, duration_ns, n_points).astype(np.int64)
    s = times[:, None] / NS
    return SampledTrajectory(times, a + b * s, np.tile(b, (n_points, 1)), e + f * s)


def tolerances(path=(0.0, 0.0), path_velocity=(0.0, 0.0), goal=(0.0, 0.0),
               goal_velocity=(0.0, 0.0), goal_time=0.0) -> Tolerances:
    return Tolerances(np.array(path, dtype=float), np.array(path_velocity, dtype=float),
                      np.array(goal, dtype=float), np.array(goal_velocity, dtype=float),
                      goal_time)


def line_goal(key, start_ns=START, tol=None, **line) -> Goal:
    return Goal(key, line_trajectory(**line), start_ns, tol or tolerances())


def controller(limit=LIMIT) -> TrajectoryController:
    return TrajectoryController(JOINTS, PDLaw.symmetric(KP, KD, limit))


def near(rng, center, spread=0.05):
    """A measured value near `center` (q or qd), (2,)."""
    return np.asarray(center) + rng.uniform(-spread, spread, 2)


def assert_torque(actual, expected):
    np.testing.assert_allclose(actual, expected, rtol=0.0, atol=TOL_TORQUE)


def codes(results):
    return [(r.key, r.error_code) for r in results]


# -- the law on the sampled reference --------------------------------------------------------
@pytest.mark.parametrize('limit', [LIMIT, np.array([4.0, 3.0])])
def test_the_torque_is_the_pd_law_on_the_sampled_reference(limit):
    """At random state times over the goal and past its end (the success hold serves the
    last point as given: the line's end, its velocity and effort), the torque is the law
    written here on the line's closed form, feed-forward = the effort at the state's own time;
    with narrow limits some torques clip (and do so here too)."""
    rng = np.random.default_rng(0)
    c = controller(limit)
    assert c.submit(line_goal('a')) == []
    times = np.sort(rng.integers(START + 1, START + DURATION + NS // 2, 200))
    clipped = 0
    for t in np.concatenate([[START], times]):
        q_ref, qd_ref, u_ref = line_reference(int(t) - START)
        q, qd = near(rng, q_ref, 0.2), near(rng, qd_ref, 1.0)
        torque, _ = c.update(int(t), q, qd)
        expected = pd(q, qd, q_ref, qd_ref, u_ref, limit)
        assert_torque(torque, expected)
        clipped += np.any(np.abs(expected) == limit)
    narrow = not np.array_equal(limit, LIMIT)
    assert clipped > 10 if narrow else clipped == 0


def test_a_goal_stamped_zero_starts_at_the_next_update():
    """Stamp 0: the goal's time starts at the first update after it came (not at the clock's
    zero, which would be far past its end)."""
    c = controller()
    c.update(5 * NS, A, np.zeros(2))
    c.submit(line_goal('a', start_ns=0))
    for t, s in ((7 * NS, 0), (7 * NS + 250 * MS, 250 * MS), (7 * NS + 600 * MS, 600 * MS)):
        q, qd = A + 0.01, np.full(2, 0.1)
        torque, results = c.update(t, q, qd)
        assert results == []
        assert (c.last.key, c.last.time_from_start_ns) == ('a', s)
        assert_torque(torque, pd(q, qd, *line_reference(s)))
    _, results = c.update(8 * NS, *line_reference(DURATION)[:2])
    assert codes(results) == [('a', SUCCESSFUL)]


def test_with_nothing_run_the_first_measured_position_is_held():
    c = controller()
    q1, qd1 = np.array([0.3, -0.1]), np.array([0.2, 0.5])
    torque, results = c.update(NS, q1, qd1)
    assert results == [] and c.last.key is None
    assert_torque(torque, hold_torque(q1, qd1, q1))
    q2, qd2 = np.array([0.1, 0.0]), np.array([-0.3, 0.0])
    torque, _ = c.update(NS + 2 * MS, q2, qd2)
    assert_torque(torque, hold_torque(q2, qd2, q1))         # still q1, not the newest


# -- preemption and future starts ------------------------------------------------------------
def test_a_new_goal_preempts_the_active_one():
    c = controller()
    assert c.submit(line_goal('a')) == []
    c.update(START, A, B)
    ended = c.submit(line_goal('b', start_ns=START + 100 * MS, a=A + 1.0))
    assert ended == [Result('a', INVALID_GOAL, PREEMPTED)]
    assert c.active_key == 'b'
    # 'a' never ends again: only 'b' succeeds at its end
    seen = []
    for t in range(START + 10 * MS, START + 1500 * MS, 10 * MS):
        seen += c.update(t, *line_reference(t - START - 100 * MS, a=A + 1.0)[:2])[1]
    assert codes(seen) == [('b', SUCCESSFUL)]


def test_a_future_goal_is_taken_at_once_and_what_ran_goes_on_until_its_start():
    """'a' runs with a path tolerance; 'b', stamped later, preempts it at once, but until b's
    stamp a's reference (and a's effort) is served, with neither a's tolerance (a has ended)
    nor b's checked; the feedback shows b with a negative time from its start. From its stamp
    on, b's reference."""
    c = controller()
    c.submit(line_goal('a', tol=tolerances(path=(0.01, 0.01))))
    for t in (START, START + 100 * MS):
        c.update(t, *line_reference(t - START)[:2])
    start_b = START + 600 * MS
    b = dict(a=-A, b=2 * B, e=E + 3.0, f=-F)
    ended = c.submit(line_goal('b', start_ns=start_b, tol=tolerances(path=(0.01, 0.01)), **b))
    assert codes(ended) == [('a', INVALID_GOAL)]
    for t in (START + 300 * MS, START + 450 * MS, start_b - 1):
        q, qd = line_reference(t - START)[0] + 0.5, np.full(2, 0.5)   # far outside 0.01
        torque, results = c.update(t, q, qd)
        assert results == []
        assert_torque(torque, pd(q, qd, *line_reference(t - START)))
        assert (c.last.key, c.last.time_from_start_ns) == ('b', t - start_b)
    for t in (start_b, start_b + 100 * MS):
        q, qd = line_reference(t - start_b, **b)[0] + 0.001, np.zeros(2)
        torque, results = c.update(t, q, qd)
        assert results == []
        assert_torque(torque, pd(q, qd, *line_reference(t - start_b, **b)))
        assert (c.last.key, c.last.time_from_start_ns) == ('b', t - start_b)


def test_a_future_goal_after_a_success_holds_the_last_point_with_its_effort():
    c = controller()
    c.submit(line_goal('a'))
    c.update(START, A, B)
    _, results = c.update(START + DURATION, *line_reference(DURATION)[:2])
    assert codes(results) == [('a', SUCCESSFUL)]
    start_b = START + 3 * NS
    c.submit(line_goal('b', start_ns=start_b, a=A + 1.0))
    q_end, qd_end, u_end = line_reference(DURATION)
    assert np.all(u_end != 0.0)
    for t in (START + 2 * NS, start_b - MS):
        q, qd = q_end - 0.02, np.array([0.1, -0.1])
        torque, _ = c.update(t, q, qd)
        assert_torque(torque, pd(q, qd, q_end, qd_end, u_end))


def test_a_future_goal_with_nothing_run_holds_the_first_state_until_its_start():
    c = controller()
    start_b = START + NS
    c.submit(line_goal('b', start_ns=start_b))
    q1, qd1 = np.array([0.5, 0.5]), np.array([0.1, 0.0])
    torque, _ = c.update(START, q1, qd1)
    assert_torque(torque, hold_torque(q1, qd1, q1))
    assert (c.last.key, c.last.time_from_start_ns) == ('b', START - start_b)
    q2, qd2 = np.array([0.4, 0.6]), np.array([0.0, -0.2])
    torque, _ = c.update(START + 500 * MS, q2, qd2)
    assert_torque(torque, hold_torque(q2, qd2, q1))
    torque, _ = c.update(start_b, q2, qd2)
    assert_torque(torque, pd(q2, qd2, *line_reference(0)))


def test_two_future_goals_what_ran_goes_on_until_the_later_start():
    """'b' (stamped S_b) is preempted by 'c' (stamped S_c > S_b) before S_b: a's reference
    goes on through S_b until S_c."""
    c = controller()
    c.submit(line_goal('a', tol=tolerances()))
    c.update(START, A, B)
    start_b, start_c = START + 200 * MS, START + 400 * MS
    c.submit(line_goal('b', start_ns=start_b, a=A + 1.0))
    assert codes(c.submit(line_goal('c', start_ns=start_c, a=A - 1.0))) == [('b', INVALID_GOAL)]
    for t in (START + 100 * MS, start_b, start_b + 100 * MS, start_c - 1):
        q, qd = A, np.zeros(2)
        torque, _ = c.update(t, q, qd)
        assert_torque(torque, pd(q, qd, *line_reference(t - START)))
    q, qd = A, np.zeros(2)
    torque, _ = c.update(start_c, q, qd)
    assert_torque(torque, pd(q, qd, *line_reference(0, a=A - 1.0)))


# -- late goals and seamless replacements ----------------------------------------------------
def test_a_late_goal_ends_with_old_header_timestamp_and_what_runs_goes_on():
    c = controller()
    c.submit(line_goal('a'))
    for t in (START, START + 500 * MS):
        c.update(t, *line_reference(t - START)[:2])
    ended = c.submit(line_goal('b', start_ns=START + 200 * MS, a=A + 1.0))
    assert codes(ended) == [('b', OLD_HEADER_TIMESTAMP)]
    assert c.active_key == 'a'
    t = START + 600 * MS
    q, qd = A, B
    torque, results = c.update(t, q, qd)
    assert results == [] and c.last.key == 'a'
    assert_torque(torque, pd(q, qd, *line_reference(t - START)))
    _, results = c.update(START + DURATION, *line_reference(DURATION)[:2])
    assert codes(results) == [('a', SUCCESSFUL)]


def test_a_late_goal_while_holding_leaves_the_hold():
    c = controller()
    q1 = np.array([0.3, 0.3])
    c.update(START, q1, np.zeros(2))
    assert codes(c.submit(line_goal('b', start_ns=START - 1))) == [('b', OLD_HEADER_TIMESTAMP)]
    q2, qd2 = np.array([0.2, 0.1]), np.array([0.1, 0.1])
    torque, _ = c.update(START + MS, q2, qd2)
    assert_torque(torque, hold_torque(q2, qd2, q1))


def test_a_goal_stamped_at_the_newest_state_is_not_late():
    """The states have not *passed* a stamp equal to the newest state's time: it is taken
    (preempting), and served from the next update on."""
    c = controller()
    c.submit(line_goal('a'))
    c.update(START, A, B)
    t_newest = START + 100 * MS
    c.update(t_newest, A, B)
    assert codes(c.submit(line_goal('b', start_ns=t_newest, a=A + 1.0))) == [('a', INVALID_GOAL)]
    q, qd = A, B
    torque, _ = c.update(t_newest + 50 * MS, q, qd)
    assert_torque(torque, pd(q, qd, *line_reference(50 * MS, a=A + 1.0)))


STEP = 10 * MS                          # the cubic trajectory's points


def cubic_points(seed=0, n=101):
    """A smooth trajectory at points every STEP: positions, velocities (the last zero),
    effort; (n, 2) each."""
    t = np.arange(n) * STEP / NS
    w = np.array([2.0, 3.0])
    q = 0.3 * np.sin(w * t[:, None] + seed)
    qd = 0.3 * w * np.cos(w * t[:, None] + seed)
    qd[-1] = 0.0
    u = np.column_stack([np.cos(t), t])
    return np.arange(n, dtype=np.int64) * STEP, q, qd, u


def running_cubic(c, served_steps: int):
    """Submit the cubic goal 'a' at START and update on its points 0..served_steps (the
    states on the reference); returns its arrays."""
    times, q, qd, u = cubic_points()
    c.submit(Goal('a', SampledTrajectory(times, q, qd, u), START, tolerances()))
    for k in range(served_steps + 1):
        c.update(START + k * STEP, q[k], qd[k])
    return times, q, qd, u


def test_a_seamless_replacement_is_taken():
    """A goal of the same start whose reference equals the running one at the last state
    served (a goal change from a later point on) replaces it, though its start has passed:
    the old goal ends preempted, the new one is served from the next update (its own points
    after the change, bit for bit)."""
    c = controller()
    times, q, qd, u = running_cubic(c, served_steps=20)
    q2, qd2 = q.copy(), qd.copy()
    q2[30:] += 0.1 * np.linspace(0, 1, len(q) - 30)[:, None]
    qd2[30:-1] += 0.1
    ended = c.submit(Goal('a2', SampledTrajectory(times, q2, qd2, u), START, tolerances()))
    assert ended == [Result('a', INVALID_GOAL, PREEMPTED)]
    assert c.active_key == 'a2'
    for k in (21, 35, 60):
        c.update(START + k * STEP, q2[k], qd2[k])
        assert (c.last.key, c.last.time_from_start_ns) == ('a2', k * STEP)
        np.testing.assert_array_equal(c.last.desired.positions, q2[k])
        np.testing.assert_array_equal(c.last.desired.velocities, qd2[k])
        np.testing.assert_array_equal(c.last.desired.effort, u[k])
    assert not np.array_equal(q2[35], q[35])


@pytest.mark.parametrize('change', ['position', 'velocity', 'effort', 'start'])
def test_a_replacement_that_would_jump_is_refused(change):
    """A late goal that differs from the running reference at the last state served (in any
    field, even only the feed-forward), or that has another start: OLD_HEADER_TIMESTAMP, and
    the running goal goes on (its own reference, its key)."""
    c = controller()
    times, q, qd, u = running_cubic(c, served_steps=20)
    q2, qd2, u2, start = q.copy(), qd.copy(), u.copy(), START
    if change == 'position':
        q2[20:] += 1e-9
    elif change == 'velocity':
        qd2[20:-1] += 1e-9
    elif change == 'effort':
        u2[20:] += 1e-9
    else:
        start = START + 1
    ended = c.submit(Goal('a2', SampledTrajectory(times, q2, qd2, u2), start, tolerances()))
    assert codes(ended) == [('a2', OLD_HEADER_TIMESTAMP)]
    assert c.active_key == 'a'
    c.update(START + 21 * STEP, q[21], qd[21])
    assert c.last.key == 'a'
    np.testing.assert_array_equal(c.last.desired.positions, q[21])


def test_a_replacement_of_a_hold_is_refused():
    """After a success the controller holds (no goal runs): a late goal of the old start
    that matches the held point is not a replacement."""
    c = controller()
    times, q, qd, u = running_cubic(c, served_steps=100)
    assert c.active_key is None                                 # succeeded at its last point
    ended = c.submit(Goal('a2', SampledTrajectory(times, q, qd, u), START, tolerances()))
    assert codes(ended) == [('a2', OLD_HEADER_TIMESTAMP)]


# -- path tolerance --------------------------------------------------------------------------
FLAT = dict(a=np.array([0.5, 0.5]), b=np.zeros(2))  # positions exactly 0.5 all along


def test_a_path_tolerance_violation_aborts_and_holds_the_measured_position():
    """Joint 0 has no path tolerance (0: not enforced); joint 1 has 0.125 rad. An error of
    exactly 0.125 is within; beyond it the goal aborts naming the joint, and from that state
    on the measured position is held without feed-forward."""
    c = controller()
    c.submit(line_goal('a', tol=tolerances(path=(0.0, 0.125)), **FLAT))
    c.update(START, np.array([0.5, 0.5]), np.zeros(2))
    _, results = c.update(START + 100 * MS, np.array([5.0, 0.375]), np.zeros(2))
    assert results == []                            # joint 0 unchecked, joint 1 at the bound
    q, qd = np.array([0.5, 0.374]), np.array([0.3, -0.2])
    torque, results = c.update(START + 150 * MS, q, qd)
    assert codes(results) == [('a', PATH_TOLERANCE_VIOLATED)]
    assert "'elbow'" in results[0].error_string
    assert c.active_key is None and c.last.key is None
    assert_torque(torque, hold_torque(q, qd, q))
    q2, qd2 = np.array([0.2, 0.9]), np.array([0.0, 0.4])
    torque, results = c.update(START + 200 * MS, q2, qd2)
    assert results == []
    assert_torque(torque, hold_torque(q2, qd2, q))


def test_a_path_velocity_tolerance_violation_aborts():
    c = controller()
    c.submit(line_goal('a', tol=tolerances(path_velocity=(0.25, 0.0)), **FLAT))
    _, results = c.update(START, np.array([0.5, 0.5]), np.array([0.25, 9.0]))
    assert results == []                            # at the bound, and joint 1 unchecked
    q, qd = np.array([0.5, 0.5]), np.array([-0.26, 0.0])
    torque, results = c.update(START + MS, q, qd)
    assert codes(results) == [('a', PATH_TOLERANCE_VIOLATED)]
    assert "'shoulder'" in results[0].error_string
    assert_torque(torque, hold_torque(q, qd, q))


def test_past_the_last_point_the_path_tolerance_is_not_checked():
    """After the last point only the goal tolerance counts (here none: success), however far
    the arm is from the reference."""
    c = controller()
    c.submit(line_goal('a', tol=tolerances(path=(0.01, 0.01)), **FLAT))
    c.update(START, np.array([0.5, 0.5]), np.zeros(2))
    _, results = c.update(START + DURATION, np.array([3.0, 3.0]), np.zeros(2))
    assert codes(results) == [('a', SUCCESSFUL)]


@pytest.mark.parametrize('error, code', [(0.5, PATH_TOLERANCE_VIOLATED), (0.005, SUCCESSFUL)])
def test_a_first_sample_past_the_end_checks_the_path_tolerance(error, code):
    """JTC checks the path tolerance on a trajectory's first sample even past its end (the
    states skipped the whole trajectory): outside it aborts, inside it succeeds."""
    c = controller()
    c.submit(line_goal('a', tol=tolerances(path=(0.01, 0.01)), **FLAT))
    _, results = c.update(START + 2 * DURATION, np.array([0.5, 0.5 + error]), np.zeros(2))
    assert codes(results) == [('a', code)]


# -- goal tolerance ----------------------------------------------------------------------------
def test_the_goal_tolerance_is_waited_for_goal_time_then_aborts():
    """Past the end outside the goal tolerance: no result while the lateness is at most
    goal_time (0.5 s, exactly 0.5 s included), then GOAL_TOLERANCE_VIOLATED and the measured
    position is held. Inside the goal tolerance before the end is no success."""
    c = controller()
    c.submit(line_goal('a', tol=tolerances(goal=(0.05, 0.05), goal_time=0.5), **FLAT))
    end = START + DURATION
    for t in (START, end - 1):
        _, results = c.update(t, np.array([0.5, 0.5]), np.zeros(2))
        assert results == []
    off = np.array([0.5, 0.4])                      # 0.1 from the last point
    for t in (end, end + 250 * MS, end + 500 * MS):
        _, results = c.update(t, off, np.zeros(2))
        assert results == [] and c.active_key == 'a'
    q, qd = np.array([0.5, 0.41]), np.array([0.0, 0.1])
    torque, results = c.update(end + 500 * MS + 1, q, qd)
    assert codes(results) == [('a', GOAL_TOLERANCE_VIOLATED)]
    assert "'elbow'" in results[0].error_string
    assert_torque(torque, hold_torque(q, qd, q))
    q2, qd2 = np.array([0.3, 0.3]), np.zeros(2)
    torque, _ = c.update(end + NS, q2, qd2)
    assert_torque(torque, hold_torque(q2, qd2, q))


def test_with_goal_time_zero_the_goal_tolerance_is_waited_for_without_limit():
    c = controller()
    c.submit(line_goal('a', tol=tolerances(goal=(0.05, 0.05), goal_velocity=(0.1, 0.1)),
                       **FLAT))
    end = START + DURATION
    for t, q, qd in ((end, [0.5, 0.4], [0.0, 0.0]), (end + 100 * NS, [0.5, 0.4], [0.0, 0.0]),
                     (end + 101 * NS, [0.5, 0.5], [0.0, 0.2])):   # position in, velocity out
        _, results = c.update(t, np.array(q), np.array(qd))
        assert results == [] and c.active_key == 'a'
    _, results = c.update(end + 102 * NS, np.array([0.46, 0.54]), np.array([0.09, -0.09]))
    assert codes(results) == [('a', SUCCESSFUL)]


def test_a_success_holds_the_last_point_with_its_effort():
    """Inside the goal tolerance at the end: SUCCESSFUL once; from then on the last point
    (position, velocity, its feed-forward) is served, whatever the states do."""
    c = controller()
    times, q, qd, u = cubic_points()
    assert np.all(u[-1] != 0.0) and not qd[-1].any()
    c.submit(Goal('a', SampledTrajectory(times, q, qd, u), START,
                  tolerances(goal=(0.01, 0.01))))
    c.update(START, q[0], qd[0])
    _, results = c.update(START + int(times[-1]), q[-1] + 0.005, np.zeros(2))
    assert results == [Result('a', SUCCESSFUL, 'Goal successfully reached!')]
    for t in (START + 5 * NS, START + 50 * NS):
        q_now, qd_now = q[-1] - 0.2, np.array([0.5, -0.5])
        torque, results = c.update(t, q_now, qd_now)
        assert results == [] and c.last.key is None
        assert_torque(torque, pd(q_now, qd_now, q[-1], qd[-1], u[-1]))


# -- cancel and stop -------------------------------------------------------------------------
def test_cancel_ends_the_goal_and_holds_the_measured_position():
    c = controller()
    c.submit(line_goal('a'))
    q_last = np.array([0.25, -0.3])
    c.update(START, A, B)
    c.update(START + 100 * MS, q_last, B)
    assert c.cancel('someone else') == []
    assert c.active_key == 'a'
    assert c.cancel('a') == [Result('a', SUCCESSFUL,
                                    'canceled: the controller holds the position', True)]
    assert c.active_key is None and c.cancel('a') == []
    for t in (START + 110 * MS, START + 5 * NS):
        q, qd = np.array([0.1, 0.1]), np.array([0.2, 0.0])
        torque, results = c.update(t, q, qd)
        assert results == []
        assert_torque(torque, hold_torque(q, qd, q_last))


def test_cancel_before_any_state_holds_the_next_state():
    c = controller()
    c.submit(line_goal('a'))
    assert [r.canceled for r in c.cancel('a')] == [True]
    q1, qd1 = np.array([0.7, 0.1]), np.array([0.0, 0.3])
    torque, _ = c.update(START, q1, qd1)
    assert_torque(torque, hold_torque(q1, qd1, q1))
    torque, _ = c.update(START + MS, A, B)
    assert_torque(torque, hold_torque(A, B, q1))


def test_stop_aborts_the_goal_and_holds_the_next_state_where_it_is():
    c = controller()
    c.submit(line_goal('a'))
    c.update(START, A, B)
    assert c.stop('joint states stopped') == [Result('a', INVALID_GOAL, 'joint states stopped')]
    q1, qd1 = np.array([0.9, -0.9]), np.array([0.1, 0.1])
    torque, results = c.update(START + NS, q1, qd1)
    assert results == [] and c.last.key is None
    assert_torque(torque, hold_torque(q1, qd1, q1))
    torque, _ = c.update(START + NS + MS, A, B)
    assert_torque(torque, hold_torque(A, B, q1))


def test_stop_without_a_goal_still_holds_the_next_state():
    """After a success the last point is held; a stop replaces that hold by the next state."""
    c = controller()
    c.submit(line_goal('a'))
    c.update(START, A, B)
    c.update(START + DURATION, *line_reference(DURATION)[:2])
    assert c.stop('lost') == []
    q1 = np.array([0.0, 0.0])
    torque, _ = c.update(START + 2 * DURATION, q1, np.zeros(2))
    assert_torque(torque, np.zeros(2))


# -- closed loop ---------------------------------------------------------------------------------
def double_integrator_step(q, qd, u, dt):
    """A unit mass per joint, the torque held over dt (exact)."""
    return q + qd * dt + 0.5 * u * dt ** 2, qd + u * dt


def run_closed_loop(c, t0, t1, dt_ns, q, qd):
    """Update and step the plant from t0 to t1 (exclusive); the tracking errors (T, 2) and
    the results."""
    errors, results = [], []
    for t in range(t0, t1, dt_ns):
        torque, ended = c.update(t, q, qd)
        results += ended
        errors.append(c.last.error[0])
        q, qd = double_integrator_step(q, qd, torque, dt_ns / NS)
    return np.array(errors), results, q, qd


def parabola_goal(key, with_effort: bool):
    """q = s^2 / 2 per joint (qdd = 1) for 1 s, points every 2 ms with positions, velocities
    and the effort a unit mass needs (1 N m), or no effort."""
    times = np.arange(501, dtype=np.int64) * 2 * MS
    s = times[:, None] / NS * np.ones(2)
    qd = s.copy()
    qd[-1] = 0.0
    return Goal(key, SampledTrajectory(times, 0.5 * s ** 2, qd,
                                       np.ones_like(s) if with_effort else None),
                START, tolerances(path=(0.01, 0.01)))


def test_in_closed_loop_the_effort_is_the_feed_forward():
    """On a unit mass, tracking q = s^2 / 2 from its start: with the effort the mass needs
    (1 N m) as feed-forward the PD law has nothing to correct (the plant's exact step is the
    reference's next point); without it the arm lags towards qdd / kp (0.01 rad on the
    shoulder, 0.02 rad on the elbow), which trips the elbow's 0.01 rad path tolerance."""
    c = controller()
    c.submit(parabola_goal('a', with_effort=True))
    errors, results, _, _ = run_closed_loop(c, START, START + NS - 2 * MS, 2 * MS,
                                            np.zeros(2), np.zeros(2))
    assert results == []
    assert np.abs(errors).max() < 1e-12
    c = controller()
    c.submit(parabola_goal('a', with_effort=False))
    _, results, _, _ = run_closed_loop(c, START, START + NS - 2 * MS, 2 * MS,
                                       np.zeros(2), np.zeros(2))
    assert codes(results) == [('a', PATH_TOLERANCE_VIOLATED)]
    assert "'elbow'" in results[0].error_string


# -- tolerances ------------------------------------------------------------------------------
DEFAULTS = Tolerances(np.array([0.1, 0.2]), np.array([0.3, 0.4]), np.array([0.05, 0.06]),
                      np.array([0.07, 0.08]), goal_time=2.0)


def test_resolved_without_a_goals_tolerances_is_the_defaults():
    resolved = DEFAULTS.resolved(JOINTS, {}, {}, 0.0)
    for name in ('path_position', 'path_velocity', 'goal_position', 'goal_velocity'):
        np.testing.assert_array_equal(getattr(resolved, name), getattr(DEFAULTS, name))
    assert resolved.goal_time == 2.0


def test_resolved_positive_replaces_zero_keeps_minus_one_erases():
    resolved = DEFAULTS.resolved(JOINTS, {'elbow': (0.5, 0.0)},
                                 {'shoulder': (-1.0, 0.9), 'elbow': (0.0, -1.0 + 1e-8)}, -1.0)
    np.testing.assert_array_equal(resolved.path_position, [0.1, 0.5])
    np.testing.assert_array_equal(resolved.path_velocity, [0.3, 0.4])
    np.testing.assert_array_equal(resolved.goal_position, [0.0, 0.06])
    np.testing.assert_array_equal(resolved.goal_velocity, [0.9, 0.0])   # -1 within float eps
    assert resolved.goal_time == 0.0
    assert DEFAULTS.resolved(JOINTS, {}, {}, 3.5).goal_time == 3.5
    # the defaults themselves are unchanged
    np.testing.assert_array_equal(DEFAULTS.path_position, [0.1, 0.2])
    np.testing.assert_array_equal(DEFAULTS.goal_position, [0.05, 0.06])
    np.testing.assert_array_equal(DEFAULTS.goal_velocity, [0.07, 0.08])


@pytest.mark.parametrize('path, goal, goal_time, match', [
    ({'elbow': (-0.5, 0.0)}, {}, 0.0, 'elbow position'),
    ({}, {'shoulder': (0.0, -1.01)}, 0.0, 'shoulder velocity'),
    ({}, {}, -2.0, 'goal_time'),
    ({'wrist': (0.1, 0.1)}, {}, 0.0, "'wrist'"),
    ({}, {'wrist': (0.1, 0.1)}, 0.0, "'wrist'"),
    ({'elbow': (np.nan, 0.0)}, {}, 0.0, 'finite'),
    ({}, {'elbow': (0.1, np.nan)}, 0.0, 'finite'),
    ({}, {}, np.nan, 'finite'),
])
def test_resolved_refuses_illegal_tolerances(path, goal, goal_time, match):
    with pytest.raises(GoalRefused, match=match):
        DEFAULTS.resolved(JOINTS, path, goal, goal_time)


# -- the snapshot ----------------------------------------------------------------------------
def test_the_snapshot_shows_the_goal_and_its_time_from_start():
    """Waiting for its start: the goal's key and a negative time from its start (the desired
    state what is served, a hold here); running: the key and t - start; after success: no
    key. The error is desired - measured."""
    c = controller()
    c.submit(line_goal('a'))
    q, qd = np.array([0.1, 0.2]), np.array([0.3, 0.4])
    c.update(START - 300 * MS, q, qd)
    last = c.last
    assert (last.t_ns, last.key, last.time_from_start_ns) == (START - 300 * MS, 'a', -300 * MS)
    np.testing.assert_array_equal(last.desired.positions, q)        # the first state held
    c.update(START + 400 * MS, q, qd)
    last = c.last
    assert (last.key, last.time_from_start_ns) == ('a', 400 * MS)
    np.testing.assert_array_equal(last.q, q)
    np.testing.assert_array_equal(last.qd, qd)
    np.testing.assert_array_equal(last.error[0], last.desired.positions - q)
    np.testing.assert_array_equal(last.error[1], last.desired.velocities - qd)
    c.update(START + DURATION, q, qd)
    assert c.last.key is None


# -- construction ----------------------------------------------------------------------------
def test_mismatched_joints_are_refused():
    with pytest.raises(ValueError, match='joints'):
        TrajectoryController(['a', 'b', 'c'], PDLaw.symmetric(KP, KD, LIMIT))
    trajectory = SampledTrajectory(np.array([0, NS]), np.zeros((2, 3)))
    with pytest.raises(GoalRefused, match='3 joints'):
        controller().submit(Goal('a', trajectory, START, Tolerances.none(3)))


def test_goals_from_another_thread_while_updating():
    """Thread safety: goals submitted and canceled from another thread while the loop
    updates; every goal ends exactly once (preempted, canceled or succeeded)."""
    c = controller()
    ended: list[Result] = []
    lock = threading.Lock()
    stop = threading.Event()

    def loop():
        t = START
        while not stop.is_set():
            _, results = c.update(t, A, B)
            with lock:
                ended.extend(results)
            t += MS

    thread = threading.Thread(target=loop)
    thread.start()
    keys = [f'g{i}' for i in range(200)]
    try:
        for i, key in enumerate(keys):
            results = c.submit(line_goal(key, start_ns=0, duration_ns=5 * MS, n_points=2))
            if i % 3 == 0:
                results += c.cancel(key)
            with lock:
                ended.extend(results)
    finally:
        stop.set()
        thread.join(timeout=30)
    assert not thread.is_alive(), 'the sampling thread did not end'
    active = [c.active_key] if c.active_key is not None else []
    assert sorted([r.key for r in ended] + active) == sorted(keys)
