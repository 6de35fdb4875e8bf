"""Tests of what a goal may ask of the arm (`psl_controller.goal_limits`), of the segment
extremes it is held to (`psl_task.joint_limits.maxima` over `SampledTrajectory.control_points`)
and of the clamp of what the controller samples (`SampledTrajectory.within`), against
references written here:

* a segment's extremes against the segment sampled densely (every 1e-5 of its length) and
  against a cubic's extremum in closed form (the root of its derivative);
* the control points against the trajectory's own samples (de Casteljau evaluation here);
* refusals: the issue's goals (10 rad, 1e308 rad, 1e6 rad/s, 1e9 N m), an interpolation that
  bulges past a limit between two points inside, too many points, too long, too late;
* psl's own goals: the demonstration of every embedded task moved until a point touches a
  joint's limit (what the safety check lets through with joint_margin 0) and the longest
  homing of each task, accepted with the default parameters.

Tolerances: ``DENSE_TOL`` (relative to the quantity's scale) bounds what sampling every 1e-5
of a segment misses of its extremum (a maximum is flat: the miss is ~1e-10 of the
curvature); the closed form and `maxima` agree to ``ROOT_TOL`` (both rounding only).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from control_msgs.action import FollowJointTrajectory
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from psl_controller.follow_joint_trajectory import goal_from_msg
from psl_controller.goal_limits import GoalLimits, limits_of
from psl_controller.homing import homing_reference
from psl_controller.parameters import (GOAL_MAX_DURATION, GOAL_MAX_POINTS,
                                       GOAL_MAX_VELOCITY, ControllerParameters)
from psl_controller.policy import policy_for
from psl_controller.robot_link import trajectory_msg
from psl_controller.trajectory_controller import GoalRefused, Tolerances
from psl_controller.trajectory_sampling import (CUBIC, LINEAR, QUINTIC, SampledTrajectory,
                                                _segment)
from psl_ros.stamps import duration_msg, time_msg
from psl_task.arm_model import ArmModel
from psl_task.joint_limits import MAX_VELOCITY, POSITION_SLACK, VELOCITY_SLACK, maxima
from psl_task.model_spec import urdf_velocity_limits
from psl_task.task import EMBEDDED_TASKS, load_task

NS = 1_000_000_000
DENSE_TOL = 1e-8
ROOT_TOL = 1e-9
JOINTS = ('a', 'b')


def limits(low=-1.0, high=1.0, velocity=10.0, effort=5.0, max_points=100,
           max_duration=10.0) -> GoalLimits:
    return GoalLimits(JOINTS, np.full(2, low), np.full(2, high), np.full(2, velocity),
                      np.full(2, -effort), np.full(2, effort), max_points, max_duration)


def trajectory(kind: str, seed: int, n_points: int = 6, scale: float = 1.0):
    """Random points (each field the kind uses), times 0.05-0.5 s apart."""
    rng = np.random.default_rng(seed)
    times = np.concatenate([[0], np.cumsum(rng.integers(NS // 20, NS // 2, n_points - 1))])
    shape = (n_points, 2)
    q = rng.uniform(-scale, scale, shape)
    qd = None if kind == LINEAR else rng.uniform(-5 * scale, 5 * scale, shape)
    qdd = rng.uniform(-50 * scale, 50 * scale, shape) if kind == QUINTIC else None
    return SampledTrajectory(times.astype(np.int64), q, qd, None, qdd)


def dense(tr: SampledTrajectory, field: str = 'positions') -> np.ndarray:
    """The field sampled every 1e-5 of each segment (T, n): the segment's own polynomial
    (`trajectory_sampling._segment`, what `sample` serves between points), vectorised."""
    times, values = tr._times_ns, [tr._values(i) for i in range(tr.n_points)]
    out = []
    for i in range(tr.n_points - 1):
        length = int(times[i + 1] - times[i])
        t = np.linspace(0, length, 100_001).astype(np.int64)[:, None]
        value = getattr(_segment(tr.interpolation, t, length, values[i], values[i + 1]), field)
        out.append(np.broadcast_to(value, (len(t), tr.n_joints)))   # a line's slope: (n,)
    return np.concatenate(out)


def bernstein(points: np.ndarray, s: float) -> np.ndarray:
    """de Casteljau evaluation of control points (k, m, n) at s: (m, n)."""
    b = points
    while len(b) > 1:
        b = (1 - s) * b[:-1] + s * b[1:]
    return b[0]


# -- segment extremes -------------------------------------------------------------------------
@pytest.mark.parametrize('kind', [LINEAR, CUBIC, QUINTIC])
def test_control_points_are_the_sampled_polynomials(kind):
    """Catches: a control point off (a cubic's v T/3, a quintic's a T^2/20) or the velocity's
    scale (d / T)."""
    tr = trajectory(kind, seed=1)
    positions, velocities = tr.control_points()
    times = tr._times_ns
    for s in (0.0, 0.13, 0.5, 0.91):
        t = times[:-1] + np.round(s * np.diff(times)).astype(np.int64)
        s_exact = (t - times[:-1]) / np.diff(times)
        for k, ti in enumerate(t):
            sample = tr.sample(int(ti))
            np.testing.assert_allclose(bernstein(positions[:, k:k + 1], s_exact[k])[0],
                                       sample.positions, rtol=0, atol=1e-9)
            np.testing.assert_allclose(bernstein(velocities[:, k:k + 1], s_exact[k])[0],
                                       sample.velocities, rtol=0, atol=1e-7)


@pytest.mark.parametrize('kind', [LINEAR, CUBIC, QUINTIC])
@pytest.mark.parametrize('seed', [2, 3])
def test_maxima_are_the_extremes_of_the_interpolation(kind, seed):
    """Catches: an extremum between points missed (only the points looked at) or a bound
    reported instead of a value the interpolation reaches."""
    tr = trajectory(kind, seed)
    positions, velocities = tr.control_points()
    for field, points in (('positions', positions), ('velocities', velocities)):
        seen = dense(tr, field)
        for sign in (1.0, -1.0):
            top, segment, s = maxima(sign * points)
            scale = np.abs(seen).max()
            np.testing.assert_allclose(top, (sign * seen).max(axis=0), rtol=0,
                                       atol=DENSE_TOL * scale)
            for j in range(2):          # and it is reached where it says
                value = sign * bernstein(points[:, segment[j]:segment[j] + 1, j:j + 1],
                                         s[j])[0, 0]
                assert value == pytest.approx(top[j], abs=ROOT_TOL * max(1.0, scale))


def test_a_cubic_bulge_against_its_closed_form():
    """Two points at 0.9 rad, leaving upward at 2 rad/s and arriving downward at 1 rad/s
    over 0.4 s: q(t) = 0.9 + 2 t + c2 t^2 + c3 t^3, maximum where q'(t) = 0 (closed form)."""
    big_t, q0, v0, v1 = 0.4, 0.9, 2.0, -1.0
    c2 = (-2 * v0 * big_t - v1 * big_t) / big_t ** 2
    c3 = (v0 * big_t + v1 * big_t) / big_t ** 3
    root = (-2 * c2 - np.sqrt(4 * c2 ** 2 - 12 * c3 * v0)) / (6 * c3)
    peak = q0 + v0 * root + c2 * root ** 2 + c3 * root ** 3
    tr = SampledTrajectory(np.array([0, int(big_t * NS)]), np.full((2, 1), q0),
                           np.array([[v0], [v1]]))
    top, _, s = maxima(tr.control_points()[0])
    assert top[0] == pytest.approx(peak, abs=ROOT_TOL)
    assert s[0] * big_t == pytest.approx(root, abs=1e-6)


def test_maxima_above_a_threshold_finds_a_value_beyond_it_or_none():
    tr = trajectory(QUINTIC, seed=4)
    positions, _ = tr.control_points()
    top, _, _ = maxima(positions)
    for floor, beyond in ((top - 0.05, True), (top + 1e-6, False)):
        found, _, _ = maxima(positions, floor)
        assert np.all((found > floor) == beyond)
        assert np.all(found <= top + ROOT_TOL)


# -- the rule ---------------------------------------------------------------------------------
def goal(points: list[dict], start_ns: int = 0, names=JOINTS) -> FollowJointTrajectory.Goal:
    """A goal of points given as dicts of fields (each a list per joint) and 't' [s]."""
    msg = JointTrajectory(joint_names=list(names))
    msg.header.stamp = time_msg(start_ns)
    for p in points:
        point = JointTrajectoryPoint(time_from_start=duration_msg(int(round(p['t'] * NS))))
        for field in ('positions', 'velocities', 'accelerations', 'effort'):
            if field in p:
                setattr(point, field, [float(v) for v in p[field]])
        msg.points.append(point)
    return FollowJointTrajectory.Goal(trajectory=msg)


def parse(msg, lim=None, newest_ns=None):
    return goal_from_msg(msg, list(JOINTS), b'k', Tolerances.none(2), lim or limits(),
                         newest_ns=newest_ns)


@pytest.mark.parametrize('field, value, words', [
    ('positions', 10.0, "joint 'b': position 10 at point 1 (t = 1 s) is above its limit 1 "
                        "(the model's joint range)"),
    ('positions', 1e308, "joint 'b': position 1e+308 at point 1"),
    ('positions', -1e308, 'is below its limit -1'),
    ('velocities', 1e6, "joint 'b': velocity 1e+06/s at point 0 (t = 0.5 s) is above its "
                        'limit 10/s'),
    ('effort', 1e9, "joint 'b': effort 1e+09 N m at point 0 (t = 0.5 s) is above its limit 5 "
                    "N m (the model's torque limit)")])
def test_the_issues_goals_are_refused_naming_joint_value_and_bound(field, value, words):
    """Catches: a point outside the range, a velocity or an effort beyond its bound taken."""
    points = [{'t': 0.5, 'positions': [0.1, 0.2], 'velocities': [0.0, 0.0],
               'effort': [0.0, 0.0]},
              {'t': 1.0, 'positions': [0.1, 0.2], 'velocities': [0.0, 0.0],
               'effort': [0.0, 0.0]}]
    k = 1 if field == 'positions' else 0
    points[k][field][1] = value
    with pytest.raises(GoalRefused) as refused:
        parse(goal(points))
    assert words in str(refused.value)
    assert '\n' not in str(refused.value)


@pytest.mark.parametrize('kind', [LINEAR, CUBIC, QUINTIC])
def test_an_interpolation_bulging_past_a_limit_between_points_inside_is_refused(kind):
    """Both points inside (0.9 rad), the segment between them beyond 1 rad: refused, naming
    where and how far. Catches: only the points checked."""
    fields = {LINEAR: {}, CUBIC: {'velocities': [[0.0, 4.0], [0.0, -4.0], [0.0, 0.0]]},
              QUINTIC: {'velocities': [[0.0, 4.0], [0.0, -4.0], [0.0, 0.0]],
                        'accelerations': [[0.0, 0.0]] * 3}}[kind]
    points = [{'t': 0.0, 'positions': [0.0, 0.9]}, {'t': 0.4, 'positions': [0.0, 0.9]},
              {'t': 0.8, 'positions': [0.0, 0.5]}]
    for name, rows in fields.items():
        for point, row in zip(points, rows):
            point[name] = row
    if kind == LINEAR:            # a line cannot bulge: its speed instead (1.8 rad in 0.1 s)
        points[1].update(positions=[0.0, -0.9], t=0.1)     # 18 rad/s > 10
        with pytest.raises(GoalRefused, match="joint 'b': the linear interpolation between "
                                              'points 0 and 1 reaches velocity -18/s'):
            parse(goal(points))
        return
    with pytest.raises(GoalRefused) as refused:
        parse(goal(points))
    why = str(refused.value)
    assert f"joint 'b': the {kind} interpolation between points 0 and 1 reaches position" in why
    assert 'above its limit 1' in why
    reached = float(why.split('reaches position ')[1].split()[0])
    assert reached > 1.0 + POSITION_SLACK
    # the same segment lowered until its bulge passes the limit by half the slack: taken
    bulge = float(dense(parse(goal(points), limits(high=5.0)).trajectory)[:, 1].max())
    for point in points:
        point['positions'][1] += 1.0 + POSITION_SLACK / 2 - bulge
    parse(goal(points))


def test_a_velocity_bulging_past_its_bound_between_points_is_refused():
    """Points at +-9.5 rad/s (bound 10) whose cubic velocity overshoots the bound by 20 %."""
    points = [{'t': 0.0, 'positions': [0.0, -0.5], 'velocities': [0.0, 9.5]},
              {'t': 0.1, 'positions': [0.0, 0.5], 'velocities': [0.0, 9.5]},
              {'t': 0.2, 'positions': [0.0, 0.5], 'velocities': [0.0, 0.0]}]
    with pytest.raises(GoalRefused, match=r"joint 'b': the cubic interpolation between points "
                                          r'\d and \d reaches velocity'):
        parse(goal(points, ), limits(high=5.0, low=-5.0))


def test_the_size_bounds_count_the_points_first_and_the_duration_and_start():
    """Catches: more than max_points taken, or a trajectory longer than max_duration, or
    starting more than max_duration after the newest state."""
    lim = limits(max_points=3, max_duration=2.0)
    rest = {'positions': [0.0, 0.0], 'velocities': [0.0, 0.0]}
    parse(goal([{'t': 0.0, **rest}, {'t': 1.0, **rest}, {'t': 2.0, **rest}]), lim)
    with pytest.raises(GoalRefused, match='the trajectory has 4 points, more than max_points 3 '
                                          r'\(a parameter of the controller\)'):
        # the 4th point is not even valid: the count is checked before anything is read
        parse(goal([{'t': 0.0, **rest}] * 4), lim)
    with pytest.raises(GoalRefused, match='the trajectory lasts 2.000000001 s, longer than '
                                          'max_duration 2 s'):
        parse(goal([{'t': 0.0, **rest}, {'t': 2.000000001, **rest}]), lim)
    newest = 100 * NS
    parse(goal([{'t': 0.0, **rest}], newest + 2 * NS), lim, newest)
    with pytest.raises(GoalRefused, match='starts 2.001 s after the newest state, later than '
                                          'max_duration 2 s'):
        parse(goal([{'t': 0.0, **rest}], newest + 2_001_000_000), lim, newest)


def test_an_unlimited_joint_takes_any_finite_position():
    lim = GoalLimits(JOINTS, np.array([-np.inf, -1.0]), np.array([np.inf, 1.0]),
                     np.full(2, np.inf), np.full(2, -5.0), np.full(2, 5.0), 100, 1e6)
    parse(goal([{'t': 0.0, 'positions': [1e300, 0.0]}, {'t': 1e3, 'positions': [-1e300, 0.0]}]),
          lim)


def test_an_interpolation_that_overflows_is_refused():
    points = [{'t': 0.0, 'positions': [0.0, 0.0], 'velocities': [0.0, 0.0],
               'accelerations': [0.0, 1e308]},
              {'t': 500.0, 'positions': [0.0, 0.0], 'velocities': [0.0, 0.0],
               'accelerations': [0.0, -1e308]}]
    with pytest.raises(GoalRefused, match='the interpolation between the points overflows'):
        parse(goal(points), limits(max_duration=1e3))


# -- the clamp --------------------------------------------------------------------------------
def test_what_is_sampled_between_points_never_leaves_the_limits():
    """A goal taken with a bulge within the slack: every sample inside [low, high], with its
    speed within the bound; a clamped position at rest. Catches: no clamp."""
    lim = limits(velocity=10.0)
    q = 1.0 - POSITION_SLACK / 4
    points = [{'t': 0.0, 'positions': [0.0, q], 'velocities': [0.0, 0.01]},
              {'t': 0.2, 'positions': [0.0, q], 'velocities': [0.0, -0.01]},
              {'t': 0.4, 'positions': [0.0, 0.5], 'velocities': [0.0, 0.0]}]
    tr = parse(goal(points), lim).trajectory
    unclamped = SampledTrajectory(tr._times_ns, tr._positions, tr._velocities)
    raw = dense(unclamped)
    assert raw.max() > 1.0, 'the test needs a bulge past the limit'
    samples = [tr.sample(int(t)) for t in np.linspace(0, 0.2 * NS, 2001).astype(np.int64)]
    q_b = np.array([s.positions[1] for s in samples])
    assert q_b.max() == 1.0
    at_limit = [s for s in samples if s.positions[1] == 1.0]
    assert at_limit and all(s.velocities[1] == 0.0 for s in at_limit)


@pytest.mark.parametrize('measured, speed', [(1.3, 2.0), (0.5, 5.0)])
def test_from_the_state_before_the_trajectory_never_further_out(measured, speed):
    """The segment from the measured state (an arm found outside at 1.3 rad, moving outward
    at 2 rad/s; or inside at 0.5 moving toward the limit at 5 rad/s, beyond the bound) to a
    first point at 0.95 rad one second later: never beyond max(1, the measured position);
    the speed within the bound."""
    lim = limits(velocity=3.0)
    points = [{'t': 1.0, 'positions': [0.0, 0.95], 'velocities': [0.0, 0.0]}]
    tr = parse(goal(points), lim).trajectory.starting_from(0, np.array([0.0, measured]),
                                                          np.array([0.0, speed]))
    samples = [tr.sample(int(t)) for t in np.linspace(0, NS, 4001).astype(np.int64)]
    q_b = np.array([s.positions[1] for s in samples])
    assert q_b.max() <= max(1.0, measured)
    assert np.abs([s.velocities[1] for s in samples]).max() <= 3.0
    unclamped = SampledTrajectory(tr._times_ns, tr._positions, tr._velocities).starting_from(
        0, np.array([0.0, measured]), np.array([0.0, speed]))
    raw = np.array([unclamped.sample(int(t)).positions[1]
                    for t in np.linspace(0, NS, 4001).astype(np.int64)])
    assert raw.max() > max(1.0, measured), 'the test needs a segment that bulges outward'


# -- psl's own goals --------------------------------------------------------------------------
TASKS = sorted(p.stem for p in EMBEDDED_TASKS.glob('*.yaml'))


def reference_goal(joints, t, q, qd, effort=None) -> FollowJointTrajectory.Goal:
    """A reference as psl's executor sends it (`robot_link.trajectory_msg`: a point every
    control period, the last velocity zero)."""
    qd = np.array(qd, dtype=float)
    qd[-1] = 0.0
    msg = JointTrajectory(joint_names=list(joints))
    msg.points = [JointTrajectoryPoint(
        positions=q[k].tolist(), velocities=qd[k].tolist(),
        effort=[] if effort is None else effort[k].tolist(),
        time_from_start=duration_msg(int(round(t[k] * NS)))) for k in range(len(t))]
    return FollowJointTrajectory.Goal(trajectory=msg)


@pytest.mark.parametrize('name', TASKS)
def test_psls_own_goals_are_taken_with_the_default_parameters(name):
    """The demonstration's reference moved until a point touches each joint's limit (the
    safety check takes it with joint_margin 0: its interpolation bulges up to 4.5e-6 rad
    past), and the longest homing (from the end of each joint's range farthest from the start
    posture, its feed-forward the model's inverse dynamics within the torque limits): accepted.
    Catches: a bound or a slack that refuses what psl sends.

    (The homing's inverse dynamics alone can exceed the torque limits where the motors cannot
    hold the arm: ball_throw's shoulder at 3 rad needs 192 N m of its 80. psl's homing must
    send its feed-forward within the limits: a controller refuses more.)"""
    task = load_task(name)
    lim = limits_of(task)          # the controller's defaults
    joints = list(lim.joint_names)
    policy = policy_for(task)
    reference = policy.reference(policy.fit_demonstration(task.demo_times,
                                                          task.demo_positions),
                                 task.tau_default)

    def accepted(msg, points: int) -> None:
        assert len(msg.trajectory.points) == points <= GOAL_MAX_POINTS
        goal_from_msg(msg, joints, b'', Tolerances.none(len(joints)), lim)
    for j in range(len(joints)):
        for bound, pick in ((lim.position_high[j], np.argmax), (lim.position_low[j], np.argmin)):
            q = reference.q.copy()
            q[:, j] += bound - q[pick(q[:, j]), j]
            q[:, j] = np.clip(q[:, j], lim.position_low[j], lim.position_high[j])  # rounding
            accepted(reference_goal(joints, reference.t, q, reference.qd, reference.u_ffwd),
                     len(reference.t))
    arm = ArmModel(task)
    far = np.where(np.abs(lim.position_low - task.start_posture)
                   > np.abs(lim.position_high - task.start_posture),
                   lim.position_low, lim.position_high)

    def inverse_dynamics(q, qd, qdd):
        return arm.inverse_dynamics(task.tau_default, q, qd, qdd)
    homing = homing_reference(far, np.zeros(len(joints)), task.start_posture, task.homing,
                              task.control_period, inverse_dynamics)
    u_ffwd = np.clip(homing.u_ffwd, lim.effort_low, lim.effort_high)
    accepted(reference_goal(joints, homing.t, homing.q, homing.qd, u_ffwd), len(homing.t))


def test_the_defaults_are_the_parameters_and_the_velocity_the_smallest_given(tmp_path):
    """The arm's velocity bound (``ArmModel.limits``: a URDF's, else MAX_VELOCITY, within the
    task's safety.max_velocity) narrowed by the node's max_velocity, which by default narrows
    nothing. Catches: a default kept twice, a task's safety.max_velocity or a URDF's velocity
    limit ignored, or a node default that narrows the arm's bound (a URDF's 150 rad/s)."""
    parameters = ControllerParameters()
    assert (parameters.max_points, parameters.max_duration, parameters.max_velocity) == \
        (GOAL_MAX_POINTS, GOAL_MAX_DURATION, GOAL_MAX_VELOCITY)
    assert GOAL_MAX_VELOCITY == np.inf
    task = load_task('reach_over_obstacle')
    lim = limits_of(task)
    np.testing.assert_array_equal(lim.velocity, MAX_VELOCITY)
    np.testing.assert_array_equal(lim.position_high, 3.0)
    np.testing.assert_array_equal(lim.effort_high, 40.0)
    assert limits_of(task, max_velocity=2.5).velocity.tolist() == [2.5] * 3
    slow = dataclasses.replace(task, safety=dataclasses.replace(task.safety, max_velocity=1.5))
    assert GoalLimits.of(ArmModel(slow)).velocity.tolist() == [1.5] * 3
    urdf = tmp_path / 'arm.urdf'
    urdf.write_text('<robot name="r"><joint name="j1" type="revolute"><limit velocity="3.15" '
                    'effort="1"/></joint><joint name="j2" type="revolute"><limit effort="1"/>'
                    '</joint><joint name="j3" type="revolute"><limit velocity="150" '
                    'effort="1"/></joint><joint name="j4" type="revolute"><limit '
                    'velocity="inf" effort="1"/></joint></robot>')

    class Urdf:
        model_path = urdf
    assert urdf_velocity_limits(Urdf, ['j2', 'j1', 'j3', 'j4']).tolist() == \
        [np.inf, 3.15, 150.0, np.inf]
    assert VELOCITY_SLACK < 0.1


def test_bad_limits_are_refused():
    with pytest.raises(ValueError, match='velocity bounds must be > 0'):
        limits(velocity=0.0)
    with pytest.raises(ValueError, match='low <= high'):
        limits(low=2.0)
    with pytest.raises(ValueError, match='max_points must be >= 1'):
        limits(max_points=0)
    with pytest.raises(ValueError, match='max_points must be a whole number >= 2'):
        ControllerParameters(max_points=1)
    with pytest.raises(ValueError, match='max_duration must be a finite'):
        ControllerParameters(max_duration=float('inf'))


def test_a_goals_points_are_released_once_read():
    """Catches: the request's points (a Python object each) kept while the goal runs and
    RESULT_KEPT s after, or kept by a rejected goal (the memory of the issue: 114 -> 217 MB
    after two goals of 100,000 points). The server of a node in this process, its goal and
    take callbacks called as rclpy calls them. Also: a server given the limits of other joints
    than its controller's."""
    import types

    import rclpy
    from rclpy.action import GoalResponse
    from rclpy.callback_groups import ReentrantCallbackGroup
    from rclpy.node import Node

    from psl_controller.follow_joint_trajectory import FollowJointTrajectoryServer
    from psl_controller.pd_law import PDLaw
    from psl_controller.trajectory_controller import TrajectoryController
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node('goal_limits_release', context=context)
    controller = TrajectoryController(list(JOINTS), PDLaw.symmetric([1.0, 1.0], [1.0, 1.0], 5))
    other = GoalLimits(('b', 'a'), *(np.full(2, v) for v in (-1.0, 1.0, 1.0, -1.0, 1.0)))
    with pytest.raises(ValueError, match=r"the limits are of joints \['b', 'a'\]"):
        FollowJointTrajectoryServer(node, controller, ReentrantCallbackGroup(), other)
    server = FollowJointTrajectoryServer(node, controller, ReentrantCallbackGroup(), limits())
    try:
        rest = {'positions': [0.0, 0.0], 'velocities': [0.0, 0.0]}
        taken = goal([{'t': 0.0, **rest}, {'t': 1.0, **rest}])
        assert server._on_goal(taken) == GoalResponse.ACCEPT
        key = bytes(range(16))
        server._take(types.SimpleNamespace(request=taken,
                                           goal_id=types.SimpleNamespace(uuid=key)))
        assert controller.active_key == key
        assert len(taken.trajectory.points) == 0
        refused = goal([{'t': 0.0, **rest}, {'t': 1.0, 'positions': [0.0, 10.0],
                                              'velocities': [0.0, 0.0]}])
        assert server._on_goal(refused) == GoalResponse.REJECT
        assert len(refused.trajectory.points) == 0
    finally:
        server.destroy()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


# -- the safety check and the controllers agree (one rule, one set of limits) -----------------
@pytest.mark.parametrize('name, count, seed, sigmas', [
    ('reach_over_obstacle', 48, 46, (0.5, 2.5)), ('payload_transport', 48, 46, (0.5, 2.5)),
    ('pose_reach_3d', 8, 3, (0.6, 1.6))])       # 8: its inverse kinematics take ~0.1 s a path
def test_the_safety_check_passes_exactly_the_candidates_a_controller_takes(name, count, seed,
                                                                           sigmas):
    """A generated family of candidates (CMA-ES draws around the default theta, `sigmas` of
    the search's units: the kinds a session meets, and far more violent ones), each sent
    as psl sends it (`robot_link.trajectory_msg`) to the controllers' goal parser with the
    default parameters: the safety check passes a candidate exactly when the controller takes
    its goal, so batch mode (which runs what the check passes) never runs one the graph's
    controller rejects, and graph mode never sends one. The family holds refusals of the kinds
    a policy's reference can still have (a range, the cubic between points); none for the
    velocity bound (an end-effector reference keeps it by construction) or the torque limits
    (the feed-forward is clipped into them). Catches: a rule or a limit in one place and not
    the other."""
    from psl_optimizer.learning import search_normalisation
    from psl_task.safety_check import SafetyCheck
    task = load_task(name)
    lim = limits_of(task)
    joints = list(lim.joint_names)
    policy = policy_for(task)
    safety = SafetyCheck(ArmModel(task))
    centre, scale = search_normalisation(task, policy.default_theta)
    rng = np.random.default_rng(seed)
    steps = np.linspace(*sigmas, count)[:, None] * rng.standard_normal((count, centre.size))
    thetas = centre + scale * steps
    taus = np.array([task.sample_tau(rng) for _ in range(count)])
    kinds = {}
    for theta, tau, reference in zip(thetas, taus, policy.references(thetas, taus)):
        verdict = safety.check(tau, reference.q, reference.qd, reference.u_ffwd)
        msg = FollowJointTrajectory.Goal(trajectory=trajectory_msg(joints, reference, 0, True))
        try:
            goal_from_msg(msg, joints, b'', Tolerances.none(len(joints)), lim)
            taken = ''
        except GoalRefused as exc:
            taken = str(exc)
        assert verdict.safe == (not taken), (verdict.reason, taken)
        kind = ('safe' if verdict.safe else 'velocity' if 'velocity of' in verdict.reason
                else 'feed-forward' if 'feed-forward' in verdict.reason
                else 'between' if 'between the points' in verdict.reason else 'range')
        kinds[kind] = kinds.get(kind, 0) + 1
    wanted = {'reach_over_obstacle': ('safe', 'range'),
              'payload_transport': ('safe', 'range'),
              'pose_reach_3d': ('safe', 'between')}[name]
    assert all(kinds.get(kind) for kind in wanted), kinds
    assert not kinds.get('velocity') and not kinds.get('feed-forward'), kinds
