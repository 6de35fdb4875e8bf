"""Tests of DifferentialIK against independent references: closed-form planar kinematics and
two-link inverse kinematics, forward kinematics on a separate MjData, the geometric bound
|x| - reach for targets out of reach; plus properties (joint limits hold, the null-space
pull keeps the rest posture, finite output at singular postures, determinism, joint velocity
bounds)."""

import hashlib

import mujoco
import numpy as np
import pytest

from psl_task.inverse_kinematics import (SINGULAR_DAMPING, SINGULAR_REGION, VELOCITY_MARGIN,
                                         DifferentialIK, IKError, IKResult, _Step)

DT = 1e-3                   # s, control grid
T_PATH = 800                # samples of a path (0.8 s)

TOL_FK = 1e-12              # m, MuJoCo kinematics vs closed form
TOL_CLOSED_FORM_Q = 1e-4    # rad, IK vs closed-form two-link IK
TOL_CLOSED_FORM_QD = 1e-2   # rad/s, finite-difference qd vs closed-form J^-1 xd (peaks ~3)
TOL_TRACK = 1e-4            # m, tracking of a reachable path (planar arms)
TOL_TRACK_3D = 1e-3         # m, tracking of a reachable path (7-DOF arm)
# the algorithm without the selective damping of singular directions, for the tests of exact
# tracking through a singular posture (what the damping trades for a smooth joint path)
UNDAMPED = dict(singular_region=0.0)
TOL_REACH = 1e-3            # m, error vs the distance beyond reach, once settled
TOL_LIMIT = 1e-12           # rad, q vs the margin-narrowed joint range

TWO_LINK = (0.5, 0.4)       # m
TEN_LINK = (0.1,) * 10      # m, reach 1 m


# -- models ---------------------------------------------------------------------------------------
def planar_arm(lengths, joint_range=None):
    """An arm of hinges about +z in the x-y plane, links along the body x axes, site 'tip' at
    the end; joint_range (low, high) for every joint, or None (unlimited)."""
    limits = '' if joint_range is None else f' range="{joint_range[0]} {joint_range[1]}"'
    opened, closed, pos = '', '', '0 0 0'
    for i, length in enumerate(lengths):
        opened += (f'<body name="link{i}" pos="{pos}"><joint name="j{i}"{limits}/>'
                   f'<geom fromto="0 0 0 {length} 0 0"/>')
        closed += '</body>'
        pos = f'{length} 0 0'
    return mujoco.MjModel.from_xml_string(f"""
<mujoco>
  <compiler angle="radian" autolimits="true"/>
  <option gravity="0 0 0"/>
  <default><joint type="hinge" axis="0 0 1"/><geom type="capsule" size="0.01" mass="0.1"/>
  </default>
  <worldbody>{opened}<site name="tip" pos="{pos}"/>{closed}</worldbody>
</mujoco>""")


ARM7_RANGES = {'sh_yaw': (-2.5, 2.5), 'sh_pitch': (-2.0, 2.0), 'sh_roll': (-2.5, 2.5),
               'elbow': (0.0, 2.6), 'wr_roll': (-1.5, 1.5), 'wr_pitch': (-1.2, 1.2),
               'wr_yaw': (-0.8, 0.8)}
ARM7_Q0 = np.array([0.3, -0.4, 0.2, 1.2, 0.1, 0.2, -0.1])
RAIL_REF = 0.15             # m, qpos0 of the passive rail the 7-DOF arm stands on


def seven_dof_arm(**ranges):
    """A human-like 3-D arm: shoulder yaw/pitch/roll, elbow, wrist roll/pitch/yaw, with gravity
    on. Ahead of its joints in qpos/qvel: a free-floating ball (7 qpos, 6 dofs), a mocap body
    (no qpos) and the passive slide 'rail' (ref RAIL_REF) the arm stands on, so that the arm's
    addresses neither start at 0 nor cover all dofs. ranges: joint name -> (low, high)."""
    r = {**ARM7_RANGES, **ranges}

    def joint(name, axis):
        return f'<joint name="{name}" axis="{axis}" range="{r[name][0]} {r[name][1]}"/>'
    return mujoco.MjModel.from_xml_string(f"""
<mujoco>
  <compiler angle="radian" autolimits="true"/>
  <default><joint type="hinge" damping="0.1"/><geom type="capsule" size="0.02" mass="0.5"/>
  </default>
  <worldbody>
    <body name="ball" pos="1 1 1"><freejoint/><geom type="sphere" size="0.05"/></body>
    <body name="target" mocap="true" pos="0.3 0.2 0.1">
      <geom type="sphere" size="0.02" contype="0" conaffinity="0"/></body>
    <body name="base" pos="0 0 0.5">
      <joint name="rail" type="slide" axis="1 0 0" ref="{RAIL_REF}"/>
      <geom type="box" size="0.05 0.05 0.05"/>
      <body name="upper">
        {joint('sh_yaw', '0 0 1')}{joint('sh_pitch', '0 1 0')}{joint('sh_roll', '1 0 0')}
        <geom fromto="0 0 0 0.30 0 0"/>
        <body name="fore" pos="0.30 0 0">
          {joint('elbow', '0 1 0')}
          <geom fromto="0 0 0 0.25 0 0"/>
          <body name="hand" pos="0.25 0 0">
            {joint('wr_roll', '1 0 0')}{joint('wr_pitch', '0 1 0')}{joint('wr_yaw', '0 0 1')}
            <geom fromto="0 0 0 0.08 0 0"/>
            <site name="tip" pos="0.08 0 0"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>""")


def arm_addresses(model):
    """qpos and dof addresses of the model's hinge joints, in joint order."""
    hinges = np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_HINGE)
    return model.jnt_qposadr[hinges], model.jnt_dofadr[hinges]


def solver(model, q_rest, **settings):
    qpos_adr, dof_adr = arm_addresses(model)
    return DifferentialIK(model, 'tip', qpos_adr, dof_adr, q_rest, **settings)


def hinge_bounds(model, margin=0.01):
    hinges = np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_HINGE)
    return model.jnt_range[hinges, 0] + margin, model.jnt_range[hinges, 1] - margin


# -- independent references -----------------------------------------------------------------------
def planar_fk(q, lengths):
    """Tip (3,) of a planar arm: with phi_i = q_1 + ... + q_i, x = sum l_i cos phi_i,
    y = sum l_i sin phi_i, z = 0."""
    phi = np.cumsum(q)
    return np.array([np.dot(lengths, np.cos(phi)), np.dot(lengths, np.sin(phi)), 0.0])


def planar_jacobian(q, lengths):
    """d tip / d q_i = sum_{j >= i} l_j (-sin phi_j, cos phi_j, 0)."""
    phi = np.cumsum(q)
    tail_x = np.cumsum((-np.asarray(lengths) * np.sin(phi))[::-1])[::-1]
    tail_y = np.cumsum((np.asarray(lengths) * np.cos(phi))[::-1])[::-1]
    return np.vstack([tail_x, tail_y, np.zeros(len(q))])


def two_link_ik(p, elbow, lengths=TWO_LINK):
    """Closed-form IK of the two-link planar arm at p (T, 3), elbow branch sign(q2) = elbow:
    cos q2 = (r^2 - l1^2 - l2^2) / (2 l1 l2), q1 = atan2(y, x) - atan2(l2 sin q2,
    l1 + l2 cos q2)."""
    l1, l2 = lengths
    x, y = p[:, 0], p[:, 1]
    q2 = elbow * np.arccos((x ** 2 + y ** 2 - l1 ** 2 - l2 ** 2) / (2 * l1 * l2))
    q1 = np.arctan2(y, x) - np.arctan2(l2 * np.sin(q2), l1 + l2 * np.cos(q2))
    return np.column_stack([q1, q2])


def independent_fk(model, qpos_adr, q):
    """Site 'tip' along q (T, n) on a fresh MjData (qpos0 elsewhere)."""
    data = mujoco.MjData(model)
    site = model.site('tip').id
    out = np.empty((len(q), 3))
    for k, qk in enumerate(q):
        data.qpos[qpos_adr] = qk
        mujoco.mj_kinematics(model, data)
        out[k] = data.site_xpos[site]
    return out


# -- paths: positions (T, 3) and velocities (T, 3), minimum-jerk timing ---------------------------
def timing(n=T_PATH, dt=DT):
    """s(t) = 10 u^3 - 15 u^4 + 6 u^5, u = t / D, and ds/dt."""
    duration = (n - 1) * dt
    u = np.arange(n) * dt / duration
    s = 10 * u ** 3 - 15 * u ** 4 + 6 * u ** 5
    return s, (30 * u ** 2 - 60 * u ** 3 + 30 * u ** 4) / duration


def line(a, b, n=T_PATH):
    s, sd = timing(n)
    a, b = np.asarray(a, float), np.asarray(b, float)
    return a + s[:, None] * (b - a), sd[:, None] * (b - a)


def circle(start, radius, u, w, turns=1.0, n=T_PATH):
    """A circle through start in the plane of the unit vectors u, w (centre start - r u)."""
    s, sd = timing(n)
    angle, rate = 2 * np.pi * turns * s, 2 * np.pi * turns * sd
    u, w = np.asarray(u, float), np.asarray(w, float)
    centre = np.asarray(start, float) - radius * u
    x = centre + radius * (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * w)
    xd = radius * rate[:, None] * (-np.sin(angle)[:, None] * u + np.cos(angle)[:, None] * w)
    return x, xd


def hold(x, n):
    """x (T, 3) followed by n samples at its last point."""
    return np.vstack([x, np.repeat(x[-1:], n, axis=0)])


EX, EY = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])


# -- kinematics -----------------------------------------------------------------------------------
def test_forward_and_jacobian_match_closed_form():
    model = planar_arm(TEN_LINK)
    ik = solver(model, np.zeros(10))
    rng = np.random.default_rng(0)
    for q in rng.uniform(-np.pi, np.pi, size=(20, 10)):
        np.testing.assert_allclose(ik.forward(q), planar_fk(q, TEN_LINK), rtol=0, atol=TOL_FK)
        jac = ik.jacobian(q)
        np.testing.assert_allclose(jac, planar_jacobian(q, TEN_LINK), rtol=0, atol=TOL_FK)
        assert np.all(jac[2] == 0.0)        # the planar arm's z row


def test_forward_keeps_other_qpos_at_qpos0():
    """The rail the arm stands on stays at its qpos0 (= ref): a solver that zeroed it would
    move the tip by RAIL_REF."""
    model = seven_dof_arm()
    qpos_adr, _ = arm_addresses(model)
    ik = solver(model, ARM7_Q0)
    q = ARM7_Q0 + 0.1
    np.testing.assert_allclose(ik.forward(q), independent_fk(model, qpos_adr, q[None])[0],
                               rtol=0, atol=TOL_FK)


# -- tracking -------------------------------------------------------------------------------------
TWO_LINK_PATHS = {
    'line': lambda x0: line(x0, x0 + [-0.25, 0.2, 0.0]),
    'circle': lambda x0: circle(x0, 0.12, EX, EY),
}


@pytest.mark.parametrize('elbow', [1.0, -1.0])
@pytest.mark.parametrize('path', sorted(TWO_LINK_PATHS))
def test_two_link_matches_closed_form_ik(elbow, path):
    """The elbow branch is the start posture's; q and qd follow the closed form."""
    model = planar_arm(TWO_LINK)
    start = np.array([[0.55, 0.35, 0.0]])
    q0 = two_link_ik(start, elbow)[0]
    x_ref, xd_ref = TWO_LINK_PATHS[path](start[0])
    ik = solver(model, q0)
    result = ik.solve(x_ref, q0, DT)

    expected = two_link_ik(x_ref, elbow)
    assert np.abs(result.q - expected).max() < TOL_CLOSED_FORM_Q
    assert result.max_error < TOL_TRACK
    # qd against the closed-form joint velocity J(q)^-1 xd
    expected_qd = np.array([np.linalg.solve(planar_jacobian(q, TWO_LINK)[:2], xd[:2])
                            for q, xd in zip(expected, xd_ref)])
    assert np.abs(expected_qd).max() > 1.0          # the path moves
    assert np.abs(result.qd - expected_qd).max() < TOL_CLOSED_FORM_QD


def test_error_is_the_distance_to_the_reference():
    model = planar_arm(TWO_LINK)
    q0 = two_link_ik(np.array([[0.55, 0.35, 0.0]]), 1.0)[0]
    x_ref, _ = circle([0.55, 0.35, 0.0], 0.12, EX, EY)
    result = solver(model, q0).solve(x_ref, q0, DT)
    reached = np.array([planar_fk(q, TWO_LINK) for q in result.q])
    np.testing.assert_allclose(result.error, np.linalg.norm(reached - x_ref, axis=1),
                               rtol=0, atol=TOL_FK)


def test_seven_dof_tracks_a_3d_path_within_limits():
    model = seven_dof_arm()
    qpos_adr, _ = arm_addresses(model)
    ik = solver(model, ARM7_Q0)
    x0 = ik.forward(ARM7_Q0)
    tilt = np.array([0.0, 0.6, 0.8])
    ring, _ = circle(x0, 0.1, EY, tilt)
    out, _ = line(x0, x0 + [-0.1, 0.05, 0.12])
    x_ref = np.vstack([ring, out])
    result = ik.solve(x_ref, ARM7_Q0, DT)

    reached = independent_fk(model, qpos_adr, result.q)
    assert np.linalg.norm(reached - x_ref, axis=1).max() < TOL_TRACK_3D
    np.testing.assert_allclose(result.error, np.linalg.norm(reached - x_ref, axis=1),
                               rtol=0, atol=TOL_FK)
    low, high = hinge_bounds(model)
    assert np.all(result.q >= low - TOL_LIMIT) and np.all(result.q <= high + TOL_LIMIT)
    assert np.all(np.isfinite(result.qd))
    np.testing.assert_allclose(result.qd, np.gradient(result.q, DT, axis=0), rtol=0, atol=0)


def test_a_joint_limit_holds_and_the_others_take_over():
    """The path turns the shoulder yaw far beyond +-0.05 rad when it is free; with its range
    narrowed to q0 +- 0.05 rad it stays inside (minus the margin) and the arm still tracks."""
    x_ref_of = {}

    def run(**ranges):
        model = seven_dof_arm(**ranges)
        ik = solver(model, ARM7_Q0)
        x0 = ik.forward(ARM7_Q0)
        x_ref_of['path'], _ = line(x0, x0 + [-0.05, 0.15, 0.05])
        return model, ik.solve(x_ref_of['path'], ARM7_Q0, DT)

    yaw = list(ARM7_RANGES).index('sh_yaw')
    _, free = run()
    assert np.abs(free.q[:, yaw] - ARM7_Q0[yaw]).max() > 0.1      # the limit will bind
    model, limited = run(sh_yaw=(ARM7_Q0[yaw] - 0.05, ARM7_Q0[yaw] + 0.05))
    low, high = hinge_bounds(model)
    assert np.all(limited.q >= low - TOL_LIMIT) and np.all(limited.q <= high + TOL_LIMIT)
    assert np.isclose(limited.q[:, yaw], high[yaw], atol=1e-9).any()   # it did reach it
    # within a step: clipping alone, leaving the rest to the next steps, lags ~6e-4 m
    assert limited.max_error < TOL_TRACK


def test_tight_limits_on_every_joint_hold():
    """Every joint within q0 +- 0.1 rad and a path that needs more: the joints that take over
    from a locked one hit their own bounds too; none is crossed, the error says how far the
    path was missed."""
    tight = {name: (q - 0.1, q + 0.1) for name, q in zip(ARM7_RANGES, ARM7_Q0)}
    model = seven_dof_arm(**tight)
    ik = solver(model, ARM7_Q0)
    x0 = ik.forward(ARM7_Q0)
    result = ik.solve(circle(x0, 0.15, EY, [0.0, 0.6, 0.8])[0], ARM7_Q0, DT)
    low, high = hinge_bounds(model)
    assert np.all(result.q >= low - TOL_LIMIT) and np.all(result.q <= high + TOL_LIMIT)
    assert np.all(np.isfinite(result.qd))
    assert result.max_error > 0.01                      # the limits cost reach


def test_nullspace_pull_returns_to_the_rest_posture():
    """Two turns of a circle and back at the start, then a hold: the self-motion the turns
    leave behind is pulled back toward q_rest; without the pull it stays."""
    model = seven_dof_arm()
    ik = solver(model, ARM7_Q0)
    x0 = ik.forward(ARM7_Q0)
    x_ref = hold(circle(x0, 0.12, EY, [0.0, 0.6, 0.8], turns=2.0)[0], 500)
    drift = {}
    for gain in (0.0, 5.0):
        result = solver(model, ARM7_Q0, nullspace_gain=gain).solve(x_ref, ARM7_Q0, DT)
        assert result.max_error < TOL_TRACK_3D
        distance = np.linalg.norm(result.q - ARM7_Q0, axis=1)
        drift[gain] = distance.mean(), distance[-1]
    assert drift[0.0][1] > 0.05                         # there is self-motion to undo
    assert drift[5.0][1] < 0.1 * drift[0.0][1]
    assert drift[5.0][0] < drift[0.0][0]


def test_ten_joint_planar_arm_tracks_with_a_zero_z_row():
    model = planar_arm(TEN_LINK, joint_range=(-2.0, 2.0))
    q0 = np.full(10, 0.25)
    ik = solver(model, q0)
    x0 = ik.forward(q0)
    ring, _ = circle(x0, 0.15, EX, EY)
    x_ref = np.vstack([ring, line(x0, x0 + [0.1, -0.3, 0.0])[0]])
    result = ik.solve(x_ref, q0, DT)

    assert np.all(np.isfinite(result.q)) and np.all(np.isfinite(result.qd))
    reached = np.array([planar_fk(q, TEN_LINK) for q in result.q])
    assert np.linalg.norm(reached - x_ref, axis=1).max() < TOL_TRACK
    assert np.all(ik.jacobian(result.q[-1])[2] == 0.0)
    assert np.all(np.abs(result.q) <= 2.0 - 0.01 + TOL_LIMIT)


# -- out of reach, singular -----------------------------------------------------------------------
@pytest.mark.parametrize('lengths,q0', [((0.5, 0.5), [0.4, 1.0]),
                                        (TEN_LINK, [0.3] + [0.15] * 9)])
def test_target_out_of_reach_reports_the_distance_beyond_reach(lengths, q0):
    """A target 2 m from the base of a 1 m arm: q finite and within the limits; the error
    is never below |x_ref| - reach (geometry) and settles at it (the arm points at it)."""
    model = planar_arm(lengths, joint_range=(-2.5, 2.5))
    q0 = np.array(q0)
    ik = solver(model, q0)
    x0 = ik.forward(q0)
    far = 2.0 * np.array([np.cos(0.9), np.sin(0.9), 0.0])
    x_ref = hold(line(x0, far)[0], 400)
    result = ik.solve(x_ref, q0, DT)

    assert np.all(np.isfinite(result.q)) and np.all(np.isfinite(result.qd))
    assert np.all(np.abs(result.q) <= 2.5 - 0.01 + TOL_LIMIT)
    beyond = np.linalg.norm(x_ref, axis=1) - sum(lengths)
    assert np.all(result.error >= beyond - 1e-9)
    assert abs(result.error[-1] - 1.0) < TOL_REACH
    assert not result.reachable(0.01)


@pytest.mark.parametrize('gain', [0.0, 5.0])
def test_back_from_out_of_reach_tracks_again(gain):
    """Out to 2 m, held there (the arm stretches straight: singular), and back: the arm
    follows the path once it is reachable again (no chatter across the stretched posture,
    no getting stuck in it); undamped, it re-enters within TOL_REACH of the exact miss."""
    model = planar_arm(TWO_LINK)
    q0 = np.array([0.3, 1.2])
    ik = solver(model, q0, nullspace_gain=gain, **UNDAMPED)
    x0 = ik.forward(q0)
    far = 2.0 * x0 / np.linalg.norm(x0)
    x_ref = np.vstack([hold(line(x0, far)[0], 300), line(far, x0)[0]])
    result = ik.solve(x_ref, q0, DT)
    beyond = np.maximum(np.linalg.norm(x_ref, axis=1) - sum(TWO_LINK), 0.0)
    assert np.all(np.isfinite(result.qd))
    # worst where the path re-enters the reach: there the exact q2 grows like a square root
    assert np.abs(result.error - beyond).max() < TOL_REACH
    assert result.error[-1] < TOL_TRACK
    # with the selective damping: the stretched direction lags (a few mm as the path
    # re-enters), and the arm tracks again at the end
    damped = solver(model, q0, nullspace_gain=gain).solve(x_ref, q0, DT)
    assert np.all(np.isfinite(damped.qd)) and damped.error[-1] < TOL_TRACK
    assert np.abs(damped.error - beyond).max() < 10 * TOL_REACH


@pytest.mark.parametrize('direction', [0.0, 0.05, 0.5])
def test_stretched_start_is_finite(direction):
    """Start exactly stretched (a singular posture) and move inward at an angle to the arm.
    Any angle: finite output. Not exactly along the arm: the arm bends and tracks, undamped
    within TOL_TRACK; with the selective damping within what it costs near the singular
    posture (the bending direction lags: about singular_damping^2 / (1 m of arm)). (Exactly
    along it, with a straight q_rest, a first-order method has no direction to bend in: the
    error reports it.)"""
    model = planar_arm((0.5, 0.5))
    q0 = np.zeros(2)
    goal = np.array([1.0 - 0.4 * np.cos(direction), 0.4 * np.sin(direction), 0.0])
    x_ref = line([1.0, 0.0, 0.0], goal)[0]
    for settings, bound in ((UNDAMPED, TOL_TRACK), ({}, 2 * SINGULAR_DAMPING ** 2)):
        result = solver(model, q0, **settings).solve(x_ref, q0, DT)
        assert np.all(np.isfinite(result.q)) and np.all(np.isfinite(result.qd))
        assert np.all(np.isfinite(result.error))
        if direction:
            assert result.max_error < bound, settings


@pytest.mark.parametrize('elbow', [1.0, -1.0])
def test_stretched_start_bends_toward_a_bent_rest_posture(elbow):
    """Exactly along the arm from exactly straight, but a bent q_rest: at the singular posture
    bending is null-space motion, so the pull bends the arm into q_rest's elbow branch (at
    first ahead of the closed form, which bends like the square root of the distance moved)."""
    model = planar_arm((0.5, 0.5))
    ik = solver(model, np.array([0.0, 0.5 * elbow]))
    x_ref = line([1.0, 0.0, 0.0], [0.6, 0.0, 0.0])[0]
    result = ik.solve(x_ref, np.zeros(2), DT)
    assert result.max_error < TOL_TRACK
    assert np.all(np.sign(result.q[1:, 1]) == elbow)
    np.testing.assert_allclose(result.q[T_PATH // 4:],
                               two_link_ik(x_ref, elbow, (0.5, 0.5))[T_PATH // 4:],
                               rtol=0, atol=TOL_CLOSED_FORM_Q)


def test_stretched_seven_dof_start_is_finite():
    model = seven_dof_arm(elbow=(-2.6, 2.6))
    q0 = np.zeros(7)
    ik = solver(model, q0, **UNDAMPED)
    x0 = ik.forward(q0)
    path = line(x0, x0 + [-0.2, 0.05, 0.1])[0]
    result = ik.solve(path, q0, DT)
    assert np.all(np.isfinite(result.q)) and np.all(np.isfinite(result.qd))
    assert result.max_error < TOL_TRACK_3D
    damped = solver(model, q0).solve(path, q0, DT)     # lags while it bends out of it
    assert np.all(np.isfinite(damped.q)) and damped.error[-1] < TOL_TRACK_3D
    assert damped.max_error < 2 * SINGULAR_DAMPING ** 2


@pytest.mark.parametrize('elbow', [0.15, 0.3])
def test_near_a_singular_posture_the_joint_path_is_smooth(elbow):
    """The 7-DOF arm (redundant for the hand's position) with its elbow `elbow` rad from
    straight: the smallest singular value of J is 0.02-0.05 m/rad. Without the selective
    damping each sample's step overshoots in that direction and the next takes it back: the
    joints zig-zag from sample to sample (RMS joint acceleration above 1,000 rad/s^2 along
    a 1 s minimum-jerk line of 8 cm). With it the path is smooth (below 100 rad/s^2) and
    tracks as closely as the undamped one."""
    model = seven_dof_arm(elbow=(-2.6, 2.6))
    q0 = np.array([0.0, 0.3, 0.0, elbow, 0.0, 0.0, 0.0])
    undamped = solver(model, q0, **UNDAMPED)
    x0 = undamped.forward(q0)
    assert np.linalg.svd(undamped.jacobian(q0), compute_uv=False).min() < SINGULAR_REGION
    path = line(x0, x0 + [0.03, 0.05, -0.04])[0]

    def rms_acceleration(result):
        return float(np.sqrt(np.mean((np.diff(result.q, n=2, axis=0) / DT**2) ** 2)))
    rough = undamped.solve(path, q0, DT)
    smooth = solver(model, q0).solve(path, q0, DT)
    assert rms_acceleration(rough) > 1000.0
    assert rms_acceleration(smooth) < 100.0
    assert smooth.max_error <= rough.max_error + TOL_TRACK_3D


# -- input ----------------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def two_link():
    return solver(planar_arm(TWO_LINK), np.array([0.3, 1.2]))


def _nan_at_7(x):
    x = x.copy()
    x[7, 1] = np.nan
    return x


@pytest.mark.parametrize('change,message', [
    (lambda a: {**a, 'x_ref': _nan_at_7(a['x_ref'])}, r'x_ref must be finite.*index 7'),
    (lambda a: {**a, 'x_ref': np.full((10, 3), np.inf)}, r'x_ref must be finite'),
    (lambda a: {**a, 'x_ref': a['x_ref'][:, :2]}, r'x_ref must have shape \(T, 3\)'),
    (lambda a: {**a, 'x_ref': a['x_ref'][0]}, r'x_ref must have shape \(T, 3\)'),
    (lambda a: {**a, 'x_ref': np.empty((0, 3))}, r'T >= 1'),
    (lambda a: {**a, 'q0': np.zeros(3)}, r'q0 must have shape \(2,\)'),
    (lambda a: {**a, 'q0': np.array([0.0, np.nan])}, r'q0 must be finite'),
    (lambda a: {**a, 'dt': 0.0}, r'dt must be finite and > 0'),
    (lambda a: {**a, 'dt': np.nan}, r'dt must be finite and > 0'),
])
def test_bad_input_is_refused(two_link, change, message):
    good = {'x_ref': np.tile(two_link.forward(np.array([0.3, 1.2])), (10, 1)),
            'q0': np.array([0.3, 1.2]), 'dt': DT}
    two_link.solve(**good)
    with pytest.raises(IKError, match=message):
        two_link.solve(**change(good))


@pytest.mark.parametrize('settings,message', [
    ({'site': 'hand'}, r"no site 'hand'"),
    ({'site': 5}, r'site id 5 out of range'),
    ({'qpos_adr': np.array([0]), 'dof_adr': np.array([0])}, r'not a hinge or slide'),
    ({'dof_adr': np.array([7, 8, 9, 10, 11, 12, 6])}, r'not a hinge or slide'),
    ({'qpos_adr': np.array([8, 8, 9, 10, 11, 12, 13])}, r'names a joint twice'),
    ({'qpos_adr': np.array([8.0, 9, 10, 11, 12, 13, 14])}, r'integer arrays'),
    ({'q_rest': np.zeros(6)}, r'q_rest must have shape \(7,\)'),
    ({'damping': 0.0}, r'damping must be finite and > 0'),
    ({'tolerance': np.nan}, r'tolerance must be finite and >= 0'),
    ({'nullspace_gain': -1.0}, r'nullspace_gain must be finite and >= 0'),
    ({'iterations': 0}, r'iterations must be an integer >= 1'),
    ({'limit_margin': 1.5}, r"no range for joints \['elbow', 'wr_pitch', 'wr_yaw'\]"),
])
def test_bad_settings_are_refused(settings, message):
    model = seven_dof_arm()
    qpos_adr, dof_adr = arm_addresses(model)
    arguments = {'model': model, 'site': 'tip', 'qpos_adr': qpos_adr, 'dof_adr': dof_adr,
                 'q_rest': ARM7_Q0, **settings}
    with pytest.raises(IKError, match=message):
        DifferentialIK(**arguments)


# -- determinism, result --------------------------------------------------------------------------
def test_solves_are_bit_identical():
    model = seven_dof_arm()
    ik = solver(model, ARM7_Q0)
    x0 = ik.forward(ARM7_Q0)
    x_ref, _ = circle(x0, 0.1, EY, [0.0, 0.6, 0.8])
    first = ik.solve(x_ref, ARM7_Q0, DT)
    ik.solve(x_ref[::-1] + 0.05, ARM7_Q0, DT)            # a different solve in between
    again = ik.solve(x_ref, ARM7_Q0, DT)
    fresh = solver(model, ARM7_Q0).solve(x_ref, ARM7_Q0, DT)
    for other in (again, fresh):
        assert np.array_equal(first.q, other.q)
        assert np.array_equal(first.qd, other.qd)
        assert np.array_equal(first.error, other.error)


def random_jacobians(rng, m, count, sigma_low, sigma_high):
    """count (m, 7) Jacobians U diag(sigma) V^T whose singular values are drawn log-uniformly
    in [sigma_low, sigma_high] [m/rad]."""
    for _ in range(count):
        u, _ = np.linalg.qr(rng.normal(size=(m, m)))
        v, _ = np.linalg.qr(rng.normal(size=(7, m)))
        sigma = np.exp(rng.uniform(np.log(sigma_low), np.log(sigma_high), m))
        yield (u * sigma) @ v.T


@pytest.mark.parametrize('m', [3, 6])
def test_the_shortcut_past_the_eigen_decomposition_never_skips_a_singular_direction(m):
    """`_Step._clear_of_region` (no eigen-decomposition where J J^T's smallest eigenvalue is
    certainly above region^2) against numpy's eigenvalues: never True below region^2, True
    for every J whose smallest singular value is 1.001 times the region or more."""
    step = _Step(m, SINGULAR_REGION, SINGULAR_DAMPING)
    rng = np.random.default_rng(11)
    below = 0
    for jac in random_jacobians(rng, m, 3000, 0.2 * SINGULAR_REGION, 20 * SINGULAR_REGION):
        a = jac @ jac.T
        smallest = np.linalg.eigvalsh(a).min()
        if step._clear_of_region(a):
            assert smallest >= SINGULAR_REGION ** 2
        elif smallest >= (1.001 * SINGULAR_REGION) ** 2:
            pytest.fail(f'smallest eigenvalue {smallest} is clear of the region, not found so')
        below += smallest < SINGULAR_REGION ** 2
    assert below > 300


@pytest.mark.parametrize('orientation', [False, True])
def test_the_shortcut_gives_the_very_steps_of_the_eigen_decomposition(monkeypatch, orientation):
    """A path through and near the singular region solved with the shortcut and without it
    (every step decided by the eigen-decomposition): bit for bit the same joint path; in
    position (3-D error) and pose (6-D)."""
    model = seven_dof_arm(elbow=(-2.6, 2.6))
    q0 = np.array([0.0, 0.3, 0.0, 0.15, 0.0, 0.0, 0.0])        # elbow nearly straight
    ik = solver(model, q0)
    x0, quat0 = ik.pose(q0)
    path = line(x0, x0 + [-0.1, 0.05, -0.1])[0]                 # bending it
    quat_ref = np.tile(quat0, (len(path), 1)) if orientation else None   # the hand held
    shortcut = ik.solve(path, q0, DT, orientation_ref=quat_ref)
    calls = []
    decided = _Step._clear_of_region
    monkeypatch.setattr(_Step, '_clear_of_region',
                        lambda self, a: calls.append(decided(self, a)) or False)
    every = ik.solve(path, q0, DT, orientation_ref=quat_ref)
    assert any(calls) and not all(calls)      # the path has steps on both sides
    np.testing.assert_array_equal(shortcut.q, every.q)
    np.testing.assert_array_equal(shortcut.error, every.error)


def test_result_is_read_only_and_summarises_the_error():
    result = IKResult(q=np.zeros((3, 2)), qd=np.zeros((3, 2)), error=np.array([0.0, 2e-3, 1e-4]))
    assert result.max_error == 2e-3
    assert result.reachable(2e-3) and not result.reachable(1e-3)
    with pytest.raises(ValueError):
        result.q[0, 0] = 1.0


def test_a_single_sample():
    model = planar_arm(TWO_LINK)
    q0 = np.array([0.3, 1.2])
    ik = solver(model, q0)
    result = ik.solve(ik.forward(q0)[None], q0, DT)
    assert result.q.shape == (1, 2) and np.array_equal(result.qd, np.zeros((1, 2)))
    assert result.max_error < TOL_FK


# -- knots and orientation (issue 26) -------------------------------------------------------------
TOL_KNOTS = 1e-3            # rad, knots + spline vs every sample: the null-space pull integrated
                            # over 8 ms instead of 1 ms steps (measured 2.5e-4 on point_reach_3d)
TOL_ANGLE_DRIFT = 1e-2      # rad, the orientation a position-only solve leaves (> this)


def independent_pose(model, qpos_adr, q):
    """Site 'tip' position (T, 3) and orientation (T, 4) along q (T, n) on a fresh MjData."""
    data = mujoco.MjData(model)
    site = model.site('tip').id
    x, quat = np.empty((len(q), 3)), np.empty((len(q), 4))
    for k, qk in enumerate(q):
        data.qpos[qpos_adr] = qk
        mujoco.mj_kinematics(model, data)
        x[k] = data.site_xpos[site]
        mujoco.mju_mat2Quat(quat[k], data.site_xmat[site])
    return x, quat


def angle_between(quat, quat_ref):
    """The rotation angle (T,) [rad] from quat to quat_ref: 2 acos |<q, q_ref>|."""
    return 2.0 * np.arccos(np.minimum(1.0, np.abs(np.sum(quat * quat_ref, axis=1))))


def seven_dof_pose_path():
    """A reachable pose path of the 7-DOF arm: the forward kinematics of a minimum-jerk joint
    path (so every pose has an exact solution)."""
    model = seven_dof_arm()
    qpos_adr, _ = arm_addresses(model)
    s, _ = timing()
    goal = np.array([0.9, 0.4, -0.6, 1.2, 0.8, -0.5, 0.3])
    return model, independent_pose(model, qpos_adr, ARM7_Q0 + s[:, None] * (goal - ARM7_Q0))


def test_knots_track_like_every_sample():
    """Solved every KNOT_STEP (8 samples at 1 ms) and interpolated by a cubic spline: every
    sample within twice the tolerance (independent forward kinematics), the joints within
    TOL_KNOTS of the solve of every sample, the limits kept; the knots are the postures of
    the knots solved alone (bit for bit, the last one apart: its step is shorter)."""
    model = seven_dof_arm()
    qpos_adr, _ = arm_addresses(model)
    ik, every = solver(model, ARM7_Q0), solver(model, ARM7_Q0, knot_step=0.0)
    x0 = ik.forward(ARM7_Q0)
    ring, _ = circle(x0, 0.1, EY, np.array([0.0, 0.6, 0.8]))
    x_ref = np.vstack([ring, line(x0, x0 + [-0.1, 0.05, 0.12])[0]])
    result, reference = ik.solve(x_ref, ARM7_Q0, DT), every.solve(x_ref, ARM7_Q0, DT)
    reached = independent_fk(model, qpos_adr, result.q)
    assert np.linalg.norm(reached - x_ref, axis=1).max() <= 2 * ik.tolerance + TOL_FK
    np.testing.assert_allclose(result.error, np.linalg.norm(reached - x_ref, axis=1),
                               rtol=0, atol=TOL_FK)
    assert 0 < np.abs(result.q - reference.q).max() < TOL_KNOTS
    low, high = hinge_bounds(model)
    assert np.all(result.q >= low - TOL_LIMIT) and np.all(result.q <= high + TOL_LIMIT)
    np.testing.assert_array_equal(result.qd, np.gradient(result.q, DT, axis=0))
    stride = round(ik.knot_step / DT)
    knots = np.r_[np.arange(0, len(x_ref) - 1, stride), len(x_ref) - 1]
    alone = every.solve(x_ref[knots], ARM7_Q0, stride * DT)
    np.testing.assert_array_equal(result.q[knots[:-1]], alone.q[:-1])


def test_where_a_knot_misses_its_samples_are_solved_one_by_one():
    """Out of reach and back (the two-link arm, 2 m out): beyond the reach no knot meets the
    tolerance, so those samples are solved one by one from the last knot that did; the errors
    are those of the solve of every sample (the distance beyond reach) within TOL_REACH, and
    the arm tracks again once back."""
    model = planar_arm(TWO_LINK)
    q0 = np.array([0.3, 1.2])
    ik, every = solver(model, q0), solver(model, q0, knot_step=0.0)
    x0 = ik.forward(q0)
    far = 2.0 * x0 / np.linalg.norm(x0)
    x_ref = np.vstack([hold(line(x0, far)[0], 300), line(far, x0)[0]])
    result, reference = ik.solve(x_ref, q0, DT), every.solve(x_ref, q0, DT)
    assert np.abs(result.error - reference.error).max() < TOL_REACH
    assert result.error[-1] < TOL_TRACK
    assert not np.array_equal(result.q, reference.q)      # the knots did take part


@pytest.mark.parametrize('knot_step', [0.0, 0.008])
def test_a_pose_path_is_tracked_with_the_orientation_term(knot_step):
    """With an orientation reference the hand follows position and orientation (forward
    kinematics and angles on a separate MjData), within the tolerance on the stacked error
    (twice between knots); without it the position only, and the orientation drifts."""
    model, (x_ref, quat_ref) = seven_dof_pose_path()
    qpos_adr, _ = arm_addresses(model)
    ik = solver(model, ARM7_Q0, knot_step=knot_step)
    posed = ik.solve(x_ref, ARM7_Q0, DT, orientation_ref=quat_ref)
    plain = ik.solve(x_ref, ARM7_Q0, DT)
    x, quat = independent_pose(model, qpos_adr, posed.q)
    angle = angle_between(quat, quat_ref)
    np.testing.assert_allclose(posed.rotation_error, angle, rtol=0, atol=1e-7)   # acos near 1
    stacked = np.sqrt(np.sum((x - x_ref) ** 2, axis=1) + (ik.orientation_weight * angle) ** 2)
    assert stacked.max() <= (2 if knot_step else 1) * ik.tolerance + 1e-7 * ik.orientation_weight
    assert plain.rotation_error is None
    drift = angle_between(independent_pose(model, qpos_adr, plain.q)[1], quat_ref)
    assert drift.max() > TOL_ANGLE_DRIFT


@pytest.mark.parametrize('change, message', [
    (lambda q: q[:-1], r'orientation_ref must have shape \(800, 4\)'),
    (lambda q: 2 * q, r'unit quaternions .* sample 0 has norm 2'),
    (lambda q: np.where(np.arange(800)[:, None] == 5, np.nan, q), r'orientation_ref must be '
     r'finite; 1 samples are not, the first at index 5'),
])
def test_bad_orientation_references_are_refused(change, message):
    model, (x_ref, quat_ref) = seven_dof_pose_path()
    ik = solver(model, ARM7_Q0)
    with pytest.raises(IKError, match=message):
        ik.solve(x_ref, ARM7_Q0, DT, orientation_ref=change(quat_ref))


@pytest.mark.parametrize('settings,message', [
    ({'knot_step': -0.01}, r'knot_step must be finite and >= 0'),
    ({'orientation_weight': 0.0}, r'orientation_weight must be finite and > 0'),
])
def test_bad_knot_and_orientation_settings_are_refused(settings, message):
    model = seven_dof_arm()
    with pytest.raises(IKError, match=message):
        solver(model, ARM7_Q0, **settings)


# -- joint velocity bounds ------------------------------------------------------------------------
# (the module docstring, "Joint velocity bounds"): a path faster than the bounds allow is followed
# with every chord (q_{k+1} - q_k) / dt within (1 - margin) of the bound, the hand lagging and
# catching up, the ranges kept; a path within the bounds is the path without them, bit for bit;
# with every bound infinite the solve is the one recorded before the bounds existed. TALOS's
# references under its URDF's bounds: src/psl_controller/test/test_policy_velocity.py.
TOL_CAUGHT_UP = 1e-4        # m, the hand's error once the path has come to rest
# SHA-256 of q.tobytes() of `fast_path` solved on the 7-DOF arm without velocity bounds, by
# the solver before they existed (commit 1468014)
RECORDED_Q_SHA256 = '1efa8a2ebc009f4b64fdd03ae609a75cd680cdc93e3812106ae670f56280e2a9'


def fast_path(**ranges):
    """The 7-DOF arm (with ``ranges``) and a 0.2 s circle of 0.1 m and a line out and back
    (hand up to ~4 m/s, joints up to 13 rad/s), then 0.3 s at rest."""
    model = seven_dof_arm(**ranges)
    ik = solver(model, ARM7_Q0)
    x0 = ik.forward(ARM7_Q0)
    ring, _ = circle(x0, 0.1, EY, np.array([0.0, 0.6, 0.8]), n=200)
    out, _ = line(x0, x0 + [-0.1, 0.05, 0.12], n=150)
    back, _ = line(out[-1], x0, n=150)
    return model, hold(np.vstack([ring, out, back]), 300)


def chord_speed(q):
    return np.abs(np.diff(q, axis=0)) / DT


# three joints in ranges of 0.25-0.4 rad around the start: the bounds and the ranges at once
TIGHT_RANGES = dict(sh_roll=(0.05, 0.35), elbow=(1.0, 1.4), wr_pitch=(0.05, 0.3))


@pytest.mark.parametrize('ranges', [{}, TIGHT_RANGES])
def test_the_bounds_hold_and_the_hand_catches_up(ranges):
    model, x_ref = fast_path(**ranges)
    free = solver(model, ARM7_Q0).solve(x_ref, ARM7_Q0, DT)
    bound = np.array([3.0, 3.0, 3.0, 4.0, 2.0, 2.0, 1.5])          # rad/s
    assert np.any(chord_speed(free.q) > 2.0 * bound)               # the path asks more
    result = solver(model, ARM7_Q0, max_velocity=bound).solve(x_ref, ARM7_Q0, DT)
    kept = (1.0 - VELOCITY_MARGIN) * bound
    assert np.all(chord_speed(result.q) <= kept * (1.0 + 1e-12))
    assert np.all(np.abs(result.qd) <= kept * (1.0 + 1e-12))
    low, high = hinge_bounds(model)
    assert np.all(result.q >= low - TOL_LIMIT) and np.all(result.q <= high + TOL_LIMIT)
    assert result.error[500] > 0.01                                # it lagged
    if not ranges:
        assert result.error[-1] < TOL_CAUGHT_UP                    # and caught up


def test_a_path_speeding_up_past_the_bounds_between_knots_keeps_them():
    """A hand path whose speed grows from rest (x0 + d (t / T)^3): the knots are taken while
    it is slow, and it passes the bound between two of them (the knots' own bound and the
    spline's check hold it there)."""
    model = seven_dof_arm()
    ik = solver(model, ARM7_Q0)
    x0 = ik.forward(ARM7_Q0)
    u = np.arange(400) / 399.0
    x_ref = hold(x0 + np.outer(u ** 3, [-0.1, 0.05, 0.12]), 200)
    bound = np.full(7, 2.0)                                         # rad/s
    assert chord_speed(ik.solve(x_ref, ARM7_Q0, DT).q).max() > 1.4 * bound[0]
    result = solver(model, ARM7_Q0, max_velocity=bound).solve(x_ref, ARM7_Q0, DT)
    kept = (1.0 - VELOCITY_MARGIN) * bound
    assert np.all(chord_speed(result.q) <= kept * (1.0 + 1e-12))
    assert result.error[-1] < TOL_CAUGHT_UP


def test_a_path_ending_in_motion_is_sent_within_the_bounds():
    """The hand still lagging at the end (a ramp cut before it slows down): the reference is
    sent ending at rest (its last velocity 0), and the cubic of every segment a controller
    interpolates, the last one included, keeps the bounds (`psl_task.joint_limits`)."""
    from psl_task.joint_limits import JointLimits, control_points, interpolation_excess
    model = seven_dof_arm()
    ik = solver(model, ARM7_Q0)
    x0 = ik.forward(ARM7_Q0)
    u = np.arange(400) / 399.0
    x_ref = x0 + np.outer(u ** 3, [-0.1, 0.05, 0.12])               # fastest at its end
    bound = np.full(7, 2.0)                                         # rad/s
    result = solver(model, ARM7_Q0, max_velocity=bound).solve(x_ref, ARM7_Q0, DT)
    assert result.error[-1] > 0.01                                  # still lagging
    sent = np.array(result.qd)
    sent[-1] = 0.0
    n = len(bound)
    limits = JointLimits(tuple(map(str, range(n))), np.full(n, -np.inf), np.full(n, np.inf),
                         bound, np.full(n, -1.0), np.full(n, 1.0))
    assert interpolation_excess(limits, *control_points(np.full(len(sent) - 1, DT), result.q,
                                                        sent)) is None


def test_a_path_within_the_bounds_is_the_path_without_them():
    model, x_ref = fast_path()
    free = solver(model, ARM7_Q0).solve(x_ref, ARM7_Q0, DT)
    roomy = 1.5 * np.abs(free.qd).max(axis=0) / (1.0 - VELOCITY_MARGIN) + 1e-3
    bounded = solver(model, ARM7_Q0, max_velocity=roomy).solve(x_ref, ARM7_Q0, DT)
    assert np.array_equal(bounded.q, free.q) and np.array_equal(bounded.qd, free.qd)


@pytest.mark.parametrize('unbounded', [None, np.inf, [np.inf] * 7])
def test_infinite_bounds_give_the_recorded_path(unbounded):
    model, x_ref = fast_path()
    q = solver(model, ARM7_Q0, max_velocity=unbounded).solve(x_ref, ARM7_Q0, DT).q
    assert hashlib.sha256(q.tobytes()).hexdigest() == RECORDED_Q_SHA256


@pytest.mark.parametrize('settings,message', [
    (dict(max_velocity=[1.0] * 3), 'max_velocity must be one number or 7'),
    (dict(max_velocity=0.0), 'max_velocity must be > 0'),
    (dict(max_velocity=[1.0] * 6 + [np.nan]), 'max_velocity must be > 0'),
    (dict(velocity_margin=1.0), 'velocity_margin must lie in'),
    (dict(velocity_margin=-0.1), 'velocity_margin must lie in'),
])
def test_bad_bounds_are_refused(settings, message):
    with pytest.raises(IKError, match=message):
        solver(seven_dof_arm(), ARM7_Q0, **settings)
