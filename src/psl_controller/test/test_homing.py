"""Tests of the homing motion (`psl_controller.homing`): the quintic's boundary conditions and
limits, and its feed-forward, the model's inverse dynamics, against the model's own gravity
torque at rest and in closed loop on the model (PD alone sags by g(q) / kp; with it, it does
not); the corrected hold on a model that is wrong; from outside the joint ranges, the law of
the safety check (no joint's distance to its range grows, every joint ends inside) over a
generated family of arms, and the braking's end against its closed form."""

import dataclasses

import mujoco
import numpy as np
import pytest

from psl_controller.homing import (braking_duration, braking_velocity, corrected_hold,
                                   hold_stiffness, homing_duration, homing_reference, quintic)
from psl_controller.pd_law import law_for
from psl_task.arm_model import ArmModel
from psl_task.model_error import ModelError
from psl_task.safety_check import inside_from
from psl_task.task import load_task

Q0 = np.array([0.4, -0.3])
QD0 = np.array([0.2, -0.1])


@pytest.fixture(scope='module')
def task():
    return load_task('payload_transport')


def polynomial_through(q0, qd0, q1, T):
    """The quintic's coefficients (6, n), lowest power first, solved from its six boundary
    conditions (position and velocity and zero acceleration at 0; q1 at rest at T) as a
    linear system: a second way to the module doc's closed form."""
    def rows(t):
        powers = np.arange(6)
        return (t ** powers, np.r_[0, powers[1:] * t ** (powers[1:] - 1)],
                np.r_[0, 0, powers[2:] * (powers[2:] - 1) * t ** (powers[2:] - 2)])
    A = np.vstack([*rows(0.0), *rows(T)])
    b = np.vstack([q0, qd0, np.zeros_like(q0), q1, np.zeros_like(q0), np.zeros_like(q0)])
    return np.linalg.solve(A, b)


def test_the_quintic_is_the_polynomial_of_its_boundary_conditions(task):
    """At every sample (and before its start and after its end: held) the quintic equals
    the polynomial solved from its boundary conditions, with its derivatives."""
    q1 = task.start_posture
    T = 1.3
    t = np.linspace(0.0, T, 27)
    q, qd, qdd = quintic(Q0, QD0, q1, T, np.r_[t, T + 0.5])
    c = polynomial_through(Q0, QD0, q1, T)
    powers = np.arange(6)
    np.testing.assert_allclose(q[:-1], (t[:, None] ** powers) @ c, rtol=0, atol=1e-12)
    np.testing.assert_allclose(qd[:-1], (powers[1:] * t[:, None] ** (powers[1:] - 1))
                               @ c[1:], rtol=0, atol=1e-11)
    np.testing.assert_allclose(qdd[:-1], (powers[2:] * (powers[2:] - 1)
                                          * t[:, None] ** (powers[2:] - 2)) @ c[2:],
                               rtol=0, atol=1e-10)
    np.testing.assert_array_equal(q[-1], q1)
    np.testing.assert_array_equal(qd[-1], 0.0)


# starts 0.95-1.5 rad from payload_transport's start posture (-0.9, 0.5): the velocity limit
# sets the duration; 0.2 rad (the last): the acceleration limit does
@pytest.mark.parametrize('q0', [Q0, np.array([-1.5, 2.0]), np.array([0.05, 0.1]),
                                np.array([-0.75, 0.3])])
def test_the_duration_keeps_the_limits_and_is_the_shortest(task, q0):
    """From rest: the quintic of homing_duration keeps the limits (sampled densely, ten
    points a control period), and one control period less breaks one of them, or is
    shorter than min_duration."""
    spec, dt = task.homing, task.control_period
    T = homing_duration(q0, task.start_posture, spec, dt)
    assert T / dt == pytest.approx(round(T / dt), abs=1e-9)

    def peaks(duration):
        t = np.linspace(0.0, duration, int(round(10 * duration / dt)) + 1)
        _, qd, qdd = quintic(q0, np.zeros(2), task.start_posture, duration, t)
        return np.abs(qd).max(), np.abs(qdd).max()
    velocity, acceleration = peaks(T)
    assert acceleration <= spec.max_acceleration * (1 + 1e-9)
    assert velocity <= spec.max_velocity * (1 + 1e-9)
    assert T >= spec.min_duration
    shorter_v, shorter_a = peaks(T - dt)
    assert (T - dt < spec.min_duration - 1e-12 or shorter_a > spec.max_acceleration
            or shorter_v > spec.max_velocity), (T, shorter_v, shorter_a)


def test_without_a_model_the_feed_forward_is_zero(task):
    reference = homing_reference(Q0, QD0, task.start_posture, task.homing, task.control_period)
    assert not reference.u_ffwd.any()


def _with_inverse_dynamics(task, tau):
    arm = ArmModel(task)
    return homing_reference(Q0, QD0, task.start_posture, task.homing, task.control_period,
                            lambda q, qd, qdd: arm.inverse_dynamics(tau, q, qd, qdd))


def test_the_held_feed_forward_is_the_gravity_torque_at_the_start(task):
    tau = task.tau_high               # the heaviest payload
    reference = _with_inverse_dynamics(task, tau)
    arm = ArmModel(task)
    arm.reset(tau)                    # at the start posture, at rest: mj_forward's bias force
    gravity = (arm.data.qfrc_bias - arm.data.qfrc_passive)[arm.dof_adr]
    assert np.abs(gravity).min() > 0.1, 'the test needs an arm that gravity pulls'
    np.testing.assert_allclose(reference.u_ffwd[-1], gravity, rtol=1e-9, atol=1e-12)
    # the held samples (at rest at the start posture): the same torque
    held = (reference.qd.any(axis=1) == 0) & np.all(reference.q == task.start_posture, axis=1)
    np.testing.assert_allclose(reference.u_ffwd[held], np.broadcast_to(gravity, (
        held.sum(), len(gravity))), rtol=1e-9, atol=1e-12)


def _arm(task, tau, model_error=None):
    """The task's arm with tau applied at Q0, QD0 (and a model error, the "real" robot)."""
    arm = ArmModel(task)
    arm.reset(tau)
    if model_error is not None:
        ModelError.parse(model_error).apply(arm.model, arm.joint_ids)
    arm.data.qpos[arm.qpos_adr] = Q0
    arm.data.qvel[arm.dof_adr] = QD0
    mujoco.mj_forward(arm.model, arm.data)
    return arm


def _run(task, arm, reference):
    """Run a reference on the arm under the task's PD law."""
    law = law_for(task)
    for k in range(len(reference.t)):
        arm.step(law.torque(arm.q, arm.qd, reference.q[k], reference.qd[k],
                            reference.u_ffwd[k]))


def _final_error(task, tau, reference):
    """Run the homing on the model under the task's PD law; |q - start| at the end."""
    arm = _arm(task, tau)
    _run(task, arm, reference)
    return np.abs(arm.q - task.start_posture).max()


def test_the_feed_forward_removes_the_sag_of_pd_alone(task):
    tau = task.tau_high
    without = _final_error(task, tau, homing_reference(Q0, QD0, task.start_posture,
                                                       task.homing, task.control_period))
    with_model = _final_error(task, tau, _with_inverse_dynamics(task, tau))
    assert without > task.homing.tolerance       # PD alone: outside the homing tolerance
    assert with_model < without / 10
    assert with_model < task.homing.tolerance / 10


def test_corrected_holds_cancel_the_sag_of_a_wrong_model(task):
    """On a "real" arm 30 % heavier than the model, at rest after the homing with the model's
    inverse dynamics, the arm sags by about (g_robot - g_model) / kp; each corrected hold
    (a Newton step with the model's stiffness) removes most of what is left."""
    tau, spec = task.tau_high, dataclasses.replace(task.homing, settle_time=2.0)
    model = ArmModel(task)
    feed_forward = lambda q, qd, qdd: model.inverse_dynamics(tau, q, qd, qdd)  # noqa: E731
    stiffness = hold_stiffness(task.controller.kp, feed_forward, task.start_posture)
    assert np.all(np.linalg.eigvalsh(stiffness) > 0.5 * task.controller.kp.min())
    arm = _arm(task, tau, 'mass_scale=1.3')
    reference = homing_reference(Q0, QD0, task.start_posture, spec, task.control_period,
                                 feed_forward)
    _run(task, arm, reference)
    errors, held = [np.abs(arm.q - task.start_posture).max()], reference.u_ffwd[-1]
    for _ in range(3):
        hold = corrected_hold(task.start_posture, held, stiffness, arm.q, spec.settle_time,
                              task.control_period)
        np.testing.assert_array_equal(hold.q, np.broadcast_to(task.start_posture,
                                                               hold.q.shape))
        assert not hold.qd.any()
        held = hold.u_ffwd[-1]
        _run(task, arm, hold)
        errors.append(np.abs(arm.q - task.start_posture).max())
    assert errors[0] > 3 * task.homing.tolerance     # the model's error: far outside
    assert errors[1] < errors[0] / 2
    assert errors[-1] < task.homing.tolerance


def test_the_hold_stiffness_is_kp_plus_the_gravity_jacobian(task):
    """Against the Jacobian of mj_forward's bias force by forward differences on a fresh
    model (an independent path: no inverse dynamics)."""
    tau = task.tau_high
    model = ArmModel(task)
    K = hold_stiffness(task.controller.kp,
                       lambda q, qd, qdd: model.inverse_dynamics(tau, q, qd, qdd),
                       task.start_posture)
    arm, h = ArmModel(task), 1e-6
    arm.reset(tau)

    def gravity(q):
        arm.data.qpos[arm.qpos_adr] = q
        arm.data.qvel[:] = 0
        mujoco.mj_forward(arm.model, arm.data)
        return arm.data.qfrc_bias[arm.dof_adr].copy()

    g0 = gravity(task.start_posture)
    n = task.n_joints
    jacobian = np.column_stack([(gravity(task.start_posture + h * np.eye(n)[j]) - g0) / h
                                for j in range(n)])
    np.testing.assert_allclose(K - np.diag(task.controller.kp), jacobian, rtol=1e-3,
                               atol=1e-3 * np.abs(jacobian).max())


def carrying_duration(q0, qd0, q1, spec, dt) -> float:
    """The shortest duration (10 control periods at a time) of a single quintic that carries
    qd0 from q0 to rest at q1 within the limits (velocity: the limit beyond |qd0|): the
    homing before the arm was braked first."""
    T = homing_duration(q0, q1, spec, dt)
    while True:
        t = np.arange(int(round(T / dt)) + 1) * dt
        _, qd, qdd = quintic(q0, qd0, q1, T, t)
        if (np.abs(qdd).max() <= spec.max_acceleration
                and np.abs(qd).max() <= spec.max_velocity + np.abs(qd0).max()):
            return T
        T += 10 * dt


def test_a_moving_arm_is_braked_to_rest_before_it_is_homed(task):
    """From an arm still moving fast (an oscillating robot after its episode): the reference
    starts where the arm is with its velocity, each joint's velocity falls to zero without
    reversing, the deceleration stays within max_acceleration, the arm comes to rest within
    the braking distance (closed form 0.75 qd0^2 / a, rounded up to a control period), and
    the homing then ends at the start posture at rest; the single quintic carrying qd0
    through the homing goes further (about 0.19 qd0 T: the longer the homing, the further)."""
    spec, dt = task.homing, task.control_period
    qd0 = np.array([3.0, -1.5])
    reference = homing_reference(Q0, qd0, task.start_posture, spec, dt)
    np.testing.assert_allclose(reference.q[0], Q0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(reference.qd[0], qd0, rtol=0, atol=1e-15)
    Tb = braking_duration(qd0, spec, dt)
    braking = reference.t <= Tb + 1e-12
    v = reference.qd[braking]
    assert np.all(v * np.sign(qd0) >= -1e-12)                   # no reversal
    assert np.all(np.diff(np.abs(v), axis=0) <= 1e-12)          # slowing down all along
    np.testing.assert_allclose(v[-1], 0.0, atol=1e-12)
    qdd = np.diff(reference.qd, axis=0) / dt                    # what the samples do
    assert np.abs(qdd).max() <= spec.max_acceleration * (1 + 1e-6)
    # as short as that allows: the fastest joint's deceleration reaches the limit (within
    # what sampling the peak every dt misses)
    fastest = np.argmax(np.abs(qd0))       # it sets the braking time; the others follow it
    assert np.abs(qdd[:int(round(Tb / dt)), fastest]).max() >= \
        spec.max_acceleration * (1 - 4 * dt / Tb)
    # the positions are the integral of the velocities (trapezoids, at fine sampling)
    fine = np.linspace(0.0, Tb, 20001)
    _, qd_fine, _ = quintic(Q0, qd0, reference.q[braking][-1], Tb, fine)
    travelled = np.trapezoid(qd_fine, fine, axis=0)
    stopped = reference.q[braking][-1]
    np.testing.assert_allclose(stopped - Q0, travelled, rtol=1e-7, atol=1e-12)
    # within the braking distance of a deceleration at the limit all along (qd0^2 / 2a),
    # raised by the profile's peak of 1.5 times the mean deceleration
    assert abs(stopped - Q0)[fastest] <= (1.5 * qd0[fastest]**2 / (2 * spec.max_acceleration)
                                          + abs(qd0[fastest]) * dt)
    np.testing.assert_allclose(reference.q[-1], task.start_posture, rtol=0, atol=1e-12)
    np.testing.assert_allclose(reference.qd[-1], 0.0, rtol=0, atol=1e-12)
    T = carrying_duration(Q0, qd0, task.start_posture, spec, dt)
    carried, _, _ = quintic(Q0, qd0, task.start_posture, T, np.arange(0, T + dt, dt))
    low = np.minimum(Q0, task.start_posture)
    high = np.maximum(Q0, task.start_posture)
    beyond = lambda q: np.maximum(low - q, q - high).max()         # noqa: E731
    assert beyond(reference.q) <= 0.5 * np.abs(qd0).max() * Tb + 1e-12    # the braking only
    assert beyond(carried) > beyond(reference.q)     # and it grows with the homing's length


def test_an_arm_at_rest_is_homed_by_minimum_jerk_in_the_shortest_time(task):
    """From rest the homing is the minimum-jerk path q0 + d (10 s^3 - 15 s^4 + 6 s^5),
    s = t / T, held at q1 after T; T the smallest whole number of control periods with its
    peak velocity 15 |d| / (8 T) and peak acceleration 10 |d| / (sqrt(3) T^2) within the
    limits and at least min_duration."""
    spec, dt = task.homing, task.control_period
    reference = homing_reference(Q0, np.zeros(2), task.start_posture, spec, dt)
    d = task.start_posture - Q0
    steps = max(spec.min_duration / dt, 15 * np.abs(d).max() / (8 * spec.max_velocity) / dt,
                np.sqrt(10 * np.abs(d).max() / (np.sqrt(3) * spec.max_acceleration)) / dt)
    T = dt * np.ceil(steps - 1e-9)
    assert len(reference.t) == int(round((T + spec.settle_time) / dt)) + 1
    s = np.clip(reference.t / T, 0.0, 1.0)[:, None]
    np.testing.assert_allclose(reference.q, Q0 + d * (10 * s**3 - 15 * s**4 + 6 * s**5),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(reference.qd, d * (30 * s**2 - 60 * s**3 + 30 * s**4) / T,
                               rtol=0, atol=1e-11)


# -- from outside the joint ranges ----------------------------------------------------------
LOW, HIGH = np.array([-1.0, -2.0]), np.array([1.0, 2.0])     # ranges of the tests' own


def test_a_homing_from_outside_only_comes_closer_to_the_ranges_and_ends_inside(task):
    """A generated family of arms (200: each joint inside, outside above or below by up to
    0.5 rad, at rest or moving up to 3 rad/s either way, the start posture inside): along the
    homing reference no joint's distance to its range ever grows, every joint ends inside (at
    the start posture), the reference starts where the arm is; from `inside_from` on every
    sample is inside, the one before is not, and the safety check's law passes it."""
    from psl_task.arm_model import ArmModel
    from psl_task.safety_check import SafetyCheck
    spec, dt = task.homing, task.control_period
    safety = SafetyCheck(ArmModel(task))
    low, high = safety.low, safety.high
    assert np.all(np.isfinite(low)) and np.all(low < task.start_posture) \
        and np.all(task.start_posture < high)
    rng = np.random.default_rng(46)
    outside_seen = moving_out = 0
    for _ in range(200):
        where = rng.integers(0, 3, size=2)                      # inside, above, below
        q0 = np.where(where == 1, high + rng.uniform(0, 0.5, 2),
                      np.where(where == 2, low - rng.uniform(0, 0.5, 2),
                               rng.uniform(low, high)))
        qd0 = rng.choice([0.0, 1.0], size=2) * rng.uniform(-3.0, 3.0, size=2)
        reference = homing_reference(q0, qd0, task.start_posture, spec, dt, None, low, high)
        distance = np.maximum(np.maximum(low - reference.q, reference.q - high), 0.0)
        assert np.all(np.diff(distance, axis=0) <= 0.0), (q0, qd0)
        np.testing.assert_array_equal(reference.q[0], q0)
        np.testing.assert_array_equal(reference.q[-1], task.start_posture)
        first = inside_from(reference.q, low, high)
        assert np.all((reference.q[first:] >= low) & (reference.q[first:] <= high))
        assert first == 0 or np.any((reference.q[first - 1] < low)
                                    | (reference.q[first - 1] > high))
        assert (first > 0) == bool(np.any(where > 0))
        verdict = safety.check(task.tau_default, reference.q, reference.qd,
                               reference.u_ffwd, start=q0)
        assert verdict.safe, (q0, qd0, verdict.reason)
        outside_seen += bool(np.any(where > 0))
        moving_out += bool(np.any(((where == 1) & (qd0 > 0)) | ((where == 2) & (qd0 < 0))))
    assert outside_seen > 100 and moving_out > 20             # the family covers the cases


def test_the_braking_stops_short_of_the_bound_ahead(task):
    """Braking (closed form: it stops qd0 Tb / 2 from where it starts) that would carry a
    joint past its bound starts at 2 room / Tb instead, and stops inside (by at most a
    billionth of the room); a joint outside moving away starts at rest; one with room brakes
    as it would unlimited: the same reference, bit for bit."""
    spec, dt = task.homing, task.control_period
    q0, qd0 = np.array([0.9, 0.0]), np.array([2.0, -1.0])    # joint 0: 0.1 rad to HIGH
    Tb = braking_duration(qd0, spec, dt)
    assert 0.5 * qd0[0] * Tb > HIGH[0] - q0[0]                 # unlimited, it would pass it
    cut = braking_velocity(q0, qd0, Tb, LOW, HIGH)
    assert cut[0] == pytest.approx(2 * (HIGH[0] - q0[0]) / Tb, rel=1e-8)
    assert cut[1] == qd0[1]                                    # 2 rad of room: untouched
    reference = homing_reference(q0, qd0, task.start_posture, spec, dt, None, LOW, HIGH)
    assert reference.q[:, 0].max() <= HIGH[0]
    assert reference.q[:, 0].max() >= HIGH[0] - 1e-6           # it used the room
    np.testing.assert_array_equal(reference.qd[0], cut)
    # stopped short by a billionth of the room: 2 room / Tb times Tb / 2 may round up past
    # the bound (found by search: this case by 1.1e-16 rad)
    q, bound, duration = -0.21990966359930952, 0.5, 2.582
    stop = braking_velocity(np.array([q]), np.array([5.0]), duration, np.array([-3.0]),
                            np.array([bound]))
    assert q + 0.5 * stop[0] * duration <= bound
    outside = braking_velocity(np.array([1.2, -2.3]), np.array([0.5, -0.5]), Tb, LOW, HIGH)
    np.testing.assert_array_equal(outside, 0.0)
    coming_back = braking_velocity(np.array([1.2, -2.3]), np.array([-0.5, 0.5]), Tb, LOW,
                                   HIGH)
    np.testing.assert_array_equal(coming_back, [-0.5, 0.5])
    roomy = homing_reference(Q0, QD0, task.start_posture, spec, dt, None, LOW, HIGH)
    unlimited = homing_reference(Q0, QD0, task.start_posture, spec, dt)
    for field in ('t', 'q', 'qd', 'u_ffwd'):
        np.testing.assert_array_equal(getattr(roomy, field), getattr(unlimited, field))
