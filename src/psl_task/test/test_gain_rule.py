"""The gain rule (psl_task/gain_rule.py) against the closed form of a one-link pendulum: the
inertia is the link's about its axis plus the armature, and the closed loop run through psl's
own PD law in MuJoCo has the natural frequency and damping ratio asked (within 5 %). Then its
bounds: a small torque limit lowers the bandwidth so that the stated errors fit the limit, a
coarse control period keeps the sampled loop stable where the unbounded gains diverge, and the
gains scale with the inertia."""
import mujoco
import numpy as np
import pytest
from scipy.optimize import curve_fit

from psl_controller.pd_law import PDLaw
from psl_task.gain_rule import (DEFAULT_DAMPING_RATIO, MAX_DAMPING_PERIOD, MAX_OMEGA_PERIOD,
                                MAX_POSITION_ERROR, MAX_STIFFNESS_PERIOD, MAX_VELOCITY_ERROR,
                                joint_inertia, model_gains)

MASS, LENGTH = 1.5, 0.4                 # kg, m: the link's mass at LENGTH from the axis
INERTIA_C = (0.01, 0.02, 0.03)          # kg m^2, about its centre of mass
ARMATURE = 0.05                         # kg m^2
TIMESTEP = 0.002                        # s: one physics step per control period
STEP = 0.1                              # rad, the step of the reference
TOL = 0.05                              # relative


def pendulum(scale: float = 1.0, timestep: float = TIMESTEP) -> mujoco.MjModel:
    """One hinge about z in a horizontal plane, no gravity, no damping: linear."""
    ixx, iyy, izz = (scale * v for v in INERTIA_C)
    return mujoco.MjModel.from_xml_string(f"""
<mujoco>
  <option timestep="{timestep}" gravity="0 0 0" integrator="Euler"/>
  <worldbody>
    <body name="link">
      <joint name="hinge" type="hinge" axis="0 0 1" armature="{scale * ARMATURE}"/>
      <inertial pos="{LENGTH} 0 0" mass="{scale * MASS}" diaginertia="{ixx} {iyy} {izz}"/>
    </body>
  </worldbody>
  <actuator><motor joint="hinge" ctrllimited="false"/></actuator>
</mujoco>""")


def closed_form_inertia(scale: float = 1.0) -> float:
    """About the hinge axis: Izz + m l^2 (parallel axes), plus the armature."""
    return scale * (INERTIA_C[2] + MASS * LENGTH ** 2 + ARMATURE)


def step_response(model: mujoco.MjModel, kp: float, kd: float, seconds: float,
                  limit: float = 1e12) -> tuple[np.ndarray, np.ndarray]:
    """t, e(t) = q_ref - q from rest at 0 toward STEP, psl's PD law answering every state."""
    law = PDLaw.symmetric([kp], [kd], limit)
    data = mujoco.MjData(model)
    n = int(round(seconds / model.opt.timestep))
    error = np.empty(n)
    for k in range(n):
        error[k] = STEP - data.qpos[0]
        data.ctrl[:] = law.torque(data.qpos[:1], data.qvel[:1], [STEP], [0.0], [0.0])
        mujoco.mj_step(model, data)
    return np.arange(n) * model.opt.timestep, error


def peaks(t: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Times and values of |e|'s local maxima, each refined by the parabola through it and its
    neighbours."""
    a = np.abs(e)
    k = np.flatnonzero((a[1:-1] > a[:-2]) & (a[1:-1] >= a[2:])) + 1
    y0, y1, y2 = a[k - 1], a[k], a[k + 1]
    shift = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    return t[k] + shift * (t[1] - t[0]), y1 - 0.25 * (y0 - y2) * shift


def test_the_inertia_is_the_links_about_the_axis_plus_the_armature():
    model = pendulum()
    assert model.dof_armature[0] == ARMATURE
    for q in (0.0, 1.0, -2.5):       # the same at every angle (the axis is the symmetry)
        assert joint_inertia(model, np.array([0]), np.array([q]))[0] == \
            pytest.approx(closed_form_inertia(), rel=1e-12)


@pytest.mark.parametrize('bandwidth_hz', [2.0, 4.0])
def test_a_lightly_damped_step_response_has_the_asked_frequency_and_damping(bandwidth_hz):
    """zeta 0.3: the log decrement of successive peaks of |e| (half periods apart) and their
    spacing give zeta and the damped frequency, hence the natural frequency."""
    model = pendulum()
    gains = model_gains(model, np.array([0]), np.array([0.0]), np.array([1000.0]), TIMESTEP,
                        bandwidth_hz=bandwidth_hz, damping_ratio=0.3)
    m = closed_form_inertia()
    omega = 2 * np.pi * bandwidth_hz
    np.testing.assert_allclose([gains.kp[0], gains.kd[0]], [m * omega ** 2, 2 * 0.3 * omega * m],
                               rtol=1e-12)
    assert gains.reason == ('',) and gains.bandwidth_hz[0] == pytest.approx(bandwidth_hz)
    t, e = step_response(model, gains.kp[0], gains.kd[0], seconds=4.0 / bandwidth_hz)
    times, values = peaks(t, e)
    times, values = times[1:6], values[1:6]      # t = 0 is the start, not a peak
    delta = np.mean(np.log(values[:-1] / values[1:]))      # per half period
    zeta = delta / np.sqrt(np.pi ** 2 + delta ** 2)
    damped = np.pi / np.mean(np.diff(times))
    natural = damped / np.sqrt(1 - zeta ** 2)
    assert zeta == pytest.approx(0.3, rel=TOL)
    assert natural / (2 * np.pi) == pytest.approx(bandwidth_hz, rel=TOL)


def test_the_default_damping_fits_the_closed_form_step_response():
    """zeta 0.7 (two visible peaks at most): a least-squares fit of the underdamped closed form
    e(t) = e0 exp(-zeta w t) (cos wd t + zeta / sqrt(1 - zeta^2) sin wd t)."""
    model = pendulum()
    gains = model_gains(model, np.array([0]), np.array([0.0]), np.array([1000.0]), TIMESTEP)
    assert gains.damping_ratio[0] == pytest.approx(DEFAULT_DAMPING_RATIO, rel=1e-12)
    t, e = step_response(model, gains.kp[0], gains.kd[0], seconds=1.0)

    def closed_form(t, omega, zeta):
        wd = omega * np.sqrt(1 - zeta ** 2)
        return STEP * np.exp(-zeta * omega * t) * (
            np.cos(wd * t) + zeta / np.sqrt(1 - zeta ** 2) * np.sin(wd * t))

    (omega, zeta), _ = curve_fit(closed_form, t, e, p0=(10.0, 0.5), bounds=([1, 0.05],
                                                                              [100, 0.95]))
    assert zeta == pytest.approx(DEFAULT_DAMPING_RATIO, rel=TOL)
    assert omega / (2 * np.pi) == pytest.approx(gains.bandwidth_hz[0], rel=TOL)
    assert np.max(np.abs(e - closed_form(t, omega, zeta))) < 0.01 * STEP


@pytest.mark.parametrize('limit', [0.5, 2.0, 8.0, 30.0])
def test_a_small_torque_limit_lowers_the_bandwidth_to_what_fits(limit):
    """At the bound kp e_max + kd v_max is the limit exactly; the damping ratio is kept; the
    loop at the stated errors stays inside the limit. 30 N m does not bind at 3 Hz."""
    model = pendulum()
    m = closed_form_inertia()
    gains = model_gains(model, np.array([0]), np.array([0.0]), np.array([limit]), TIMESTEP)
    kp, kd = gains.kp[0], gains.kd[0]
    assert kd / (2 * np.sqrt(kp * m)) == pytest.approx(DEFAULT_DAMPING_RATIO, rel=1e-12)
    asked = m * (2 * np.pi * 3.0) ** 2 * MAX_POSITION_ERROR + \
        2 * DEFAULT_DAMPING_RATIO * 2 * np.pi * 3.0 * m * MAX_VELOCITY_ERROR
    if asked <= limit:
        assert gains.reason == ('',) and gains.bandwidth_hz[0] == pytest.approx(3.0)
        return
    assert kp * MAX_POSITION_ERROR + kd * MAX_VELOCITY_ERROR == pytest.approx(limit, rel=1e-9)
    assert gains.bandwidth_hz[0] < 3.0
    assert gains.reason[0].startswith(f'torque limit {limit:.3g} N m')
    assert f'{gains.bandwidth_hz[0]:.3g} Hz fits' in gains.reason[0]


def test_a_coarse_control_period_keeps_the_sampled_loop_stable():
    """20 Hz at a 10 ms period: omega T = 1.26, unstable as asked ((omega T)^2 + 2 kd T / m
    = 5.1 > 4); the rule lowers it to omega T = 0.1 and the loop settles."""
    period = 0.01
    model = pendulum(timestep=period)
    m = closed_form_inertia()
    asked = 2 * np.pi * 20.0
    # 20 periods: a pole at -1.77 grows the error 9e4 times (stopped before MuJoCo's own
    # divergence warning, which would write MUJOCO_LOG.TXT into the working folder)
    _, unbounded = step_response(model, m * asked ** 2, 2 * 0.7 * asked * m, seconds=0.2)
    assert np.abs(unbounded[-1]) > 100 * STEP                  # diverges
    gains = model_gains(model, np.array([0]), np.array([0.0]), np.array([1000.0]), period,
                        bandwidth_hz=20.0)
    omega = 2 * np.pi * gains.bandwidth_hz[0]
    assert omega * period == pytest.approx(MAX_OMEGA_PERIOD)
    assert gains.kd[0] * period / m <= MAX_DAMPING_PERIOD
    assert gains.reason[0].startswith('control period 10 ms')
    _, bounded = step_response(model, gains.kp[0], gains.kd[0], seconds=8.0)
    assert np.max(np.abs(bounded[-100:])) < 1e-3 * STEP         # settles
    strong = model_gains(model, np.array([0]), np.array([0.0]), np.array([1000.0]), period,
                         bandwidth_hz=20.0, damping_ratio=3.0)      # kd binds before omega
    assert strong.kd[0] * period / m == pytest.approx(MAX_DAMPING_PERIOD)
    assert strong.damping_ratio[0] < 3.0 and 'damping ratio' in strong.reason[0]


@pytest.mark.parametrize('scale', [0.01, 0.5, 7.0])
def test_the_gains_scale_with_the_inertia(scale):
    """Every mass, inertia and the armature times s: kp and kd times s (torque limits that
    scale alike), the bandwidth unchanged."""
    one = model_gains(pendulum(), np.array([0]), np.array([0.3]), np.array([5.0]), TIMESTEP)
    scaled = model_gains(pendulum(scale), np.array([0]), np.array([0.3]),
                         np.array([5.0 * scale]), TIMESTEP)
    np.testing.assert_allclose(scaled.inertia, scale * one.inertia, rtol=1e-12)
    np.testing.assert_allclose([scaled.kp, scaled.kd], [scale * one.kp, scale * one.kd],
                               rtol=1e-9)
    np.testing.assert_allclose(scaled.bandwidth_hz, one.bandwidth_hz, rtol=1e-9)


def test_bad_input_is_refused_with_the_reason():
    model = pendulum()
    dofs, posture = np.array([0]), np.array([0.0])
    with pytest.raises(ValueError, match='torque_limits has 2 entries for 1 dofs'):
        model_gains(model, dofs, posture, np.array([1.0, 1.0]), TIMESTEP)
    with pytest.raises(ValueError, match='torque_limits must be finite and > 0'):
        model_gains(model, dofs, posture, np.array([0.0]), TIMESTEP)
    with pytest.raises(ValueError, match='control_period must be finite and > 0'):
        model_gains(model, dofs, posture, np.array([1.0]), 0.0)
    with pytest.raises(ValueError, match='posture_qpos has 3 entries'):
        model_gains(model, dofs, np.zeros(3), np.array([1.0]), TIMESTEP)
    with pytest.raises(ValueError, match='outside the model'):
        model_gains(model, np.array([1]), posture, np.array([1.0]), TIMESTEP)
    with pytest.raises(ValueError, match='posture_qpos must be finite'):
        model_gains(model, dofs, np.array([np.nan]), np.array([1.0]), TIMESTEP)


def test_a_tasks_arm_at_its_start_posture():
    """arm_gains: the task's model, dofs, the smaller torque magnitude and the control
    period; designed at the start posture (the inertia MuJoCo's mass matrix diagonal there),
    its coupled modes bounded along the demonstration too."""
    from psl_task.arm_model import ArmModel
    from psl_task.gain_rule import arm_gains
    from psl_task.task import load_task
    task = load_task('point_reach_3d')
    arm = ArmModel(task)
    gains = arm_gains(arm)
    data = mujoco.MjData(arm.model)
    data.qpos[arm.qpos_adr] = task.start_posture
    mujoco.mj_forward(arm.model, data)
    dense = np.zeros((arm.model.nv, arm.model.nv))
    mujoco.mj_fullM(arm.model, data, dense)
    np.testing.assert_allclose(gains.inertia, np.diag(dense)[arm.dof_adr], rtol=1e-12)
    start = model_gains(arm.model, arm.dof_adr, task.start_posture,
                        np.minimum(-arm.torque_low, arm.torque_high), task.control_period)
    np.testing.assert_array_equal(gains.kp, start.kp)    # no bound binds on this arm ...
    np.testing.assert_array_equal(gains.kd, start.kd)
    assert np.all(gains.free_inertia <= start.free_inertia)   # ... along its demonstration
    assert np.any(gains.free_inertia < start.free_inertia)


I_INNER, I_OUTER = 0.005, 0.2           # kg m^2 about the common axis (outer: 0.02 + 2 kg 0.3^2)


def coaxial(inner: float = I_INNER) -> mujoco.MjModel:
    """Two hinges on one axis: a light inner link and a heavy outer one. M = [[Ii + Io, Io],
    [Io, Io]]: joint 1 moves Ii + Io with joint 2 held, only Ii with joint 2 yielding."""
    return mujoco.MjModel.from_xml_string(f"""
<mujoco>
  <option timestep="{TIMESTEP}" gravity="0 0 0" integrator="Euler"/>
  <worldbody>
    <body name="inner">
      <joint name="j1" type="hinge" axis="0 0 1"/>
      <inertial pos="0 0 0" mass="0.1" diaginertia="{inner} {inner} {inner}"/>
      <body name="outer">
        <joint name="j2" type="hinge" axis="0 0 1"/>
        <inertial pos="0.3 0 0" mass="2" diaginertia="0.015 0.015 0.02"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="j1" ctrllimited="false"/><motor joint="j2" ctrllimited="false"/>
  </actuator>
</mujoco>""")


def sampled_loop(mass: np.ndarray, kp: np.ndarray, kd: np.ndarray) -> np.ndarray:
    """Eigenvalues of the sampled PD loop (state x = q - q_ref, v) under semi-implicit Euler:
    v' = v - T M^-1 (Kp x + Kd v), x' = x + T v'."""
    n = len(kp)
    p = TIMESTEP * np.linalg.solve(mass, np.diag(kp))
    d = TIMESTEP * np.linalg.solve(mass, np.diag(kd))
    eye = np.eye(n)
    return np.linalg.eigvals(np.block([[eye - TIMESTEP * p, TIMESTEP * (eye - d)],
                                       [-p, eye - d]]))


def test_coupled_joints_keep_every_mode_of_the_sampled_loop_stable():
    """Designed on M's diagonal alone the coaxial pair's relative mode (the light inner link
    between the two) has a pole far outside the unit circle: the arm diverges within 10
    periods. The rule's coupling bounds (the inertia each joint moves with the other yielding,
    here Ii) keep every pole inside and off the negative real axis (no chatter), and the step
    response settles; the heavy mode keeps the asked bandwidth on joint 2."""
    model = coaxial()
    dofs, posture, limits = np.array([0, 1]), np.zeros(2), np.array([1e3, 1e3])
    gains = model_gains(model, dofs, posture, limits, TIMESTEP)
    mass = np.array([[I_INNER + I_OUTER, I_OUTER], [I_OUTER, I_OUTER]])
    np.testing.assert_allclose(gains.inertia, np.diag(mass), rtol=1e-9)
    np.testing.assert_allclose(gains.free_inertia, [I_INNER, 1 / np.linalg.inv(mass)[1, 1]],
                               rtol=1e-9)
    omega = 2 * np.pi * 3.0
    diagonal = (np.diag(mass) * omega ** 2, 2 * 0.7 * omega * np.diag(mass))
    assert np.max(np.abs(sampled_loop(mass, *diagonal))) > 1.5
    poles = sampled_loop(mass, gains.kp, gains.kd)
    assert np.max(np.abs(poles)) < 1 and np.min(poles.real) > 0
    np.testing.assert_allclose(gains.kp, diagonal[0], rtol=1e-12)          # 3 Hz kept
    np.testing.assert_allclose(gains.kd * TIMESTEP / gains.free_inertia, MAX_DAMPING_PERIOD,
                               rtol=1e-9)
    assert np.all(gains.damping_ratio < 0.7)
    assert all(r.startswith('damping: kd T / ') for r in gains.reason)
    # a lighter inner link: the stiffness binds too (kp T^2 / Ii at its bound)
    light = model_gains(coaxial(0.0005), dofs, posture, limits, TIMESTEP)
    np.testing.assert_allclose(light.kp * TIMESTEP ** 2 / light.free_inertia,
                               MAX_STIFFNESS_PERIOD, rtol=1e-9)
    assert np.all(light.bandwidth_hz < 3.0)
    assert all(r.startswith('coupled: with the other joints yielding') for r in light.reason)

    def run(kp, kd, steps):
        law = PDLaw.symmetric(kp, kd, 1e12)
        data = mujoco.MjData(model)
        for _ in range(steps):
            data.ctrl[:] = law.torque(data.qpos, data.qvel, [STEP, -STEP], [0, 0], [0, 0])
            mujoco.mj_step(model, data)
        return data.qpos - [STEP, -STEP]

    assert np.max(np.abs(run(*diagonal, 10))) > 100 * STEP      # diverges: a pole at -3.4
    assert np.max(np.abs(run(gains.kp, gains.kd, 5000))) < 1e-3 * STEP   # settles (10 s)


def test_the_coupled_modes_are_bounded_over_every_posture_given():
    """Joints 1 and 3 about z, joint 2 about y between them: coaxial at q2 = 0 (a 7-joint arm's
    upright upper arm), apart at q2 = 1. Gains designed at q2 = 1 alone leave the sampled loop
    at q2 = 0 unstable; given both postures (the design posture first), the least free
    inertia over them bounds kd and every pole at q2 = 0 lies inside, off the negative axis."""
    model = mujoco.MjModel.from_xml_string(f"""
<mujoco>
  <option timestep="{TIMESTEP}" gravity="0 0 0" integrator="Euler"/>
  <worldbody>
    <body>
      <joint type="hinge" axis="0 0 1"/>
      <inertial pos="0 0 0.1" mass="0.3" diaginertia="0.003 0.003 0.002"/>
      <body pos="0 0 0.3">
        <joint type="hinge" axis="0 1 0"/>
        <inertial pos="0 0 0.1" mass="0.3" diaginertia="0.003 0.003 0.002"/>
        <body pos="0 0 0.2">
          <joint type="hinge" axis="0 0 1"/>
          <inertial pos="0.3 0 0.1" mass="2" diaginertia="0.02 0.02 0.02"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>""")
    dofs, limits = np.arange(3), np.full(3, 1e3)
    apart, coaxial_posture = np.array([0.0, 1.0, 0.0]), np.zeros(3)
    alone = model_gains(model, dofs, apart, limits, TIMESTEP)
    both = model_gains(model, dofs, np.vstack([apart, coaxial_posture]), limits, TIMESTEP)
    np.testing.assert_array_equal(both.inertia, alone.inertia)       # designed at q2 = 1
    assert both.free_inertia[0] < 0.5 * alone.free_inertia[0] and both.kd[0] < alone.kd[0]
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    mass = np.zeros((3, 3))
    mujoco.mj_fullM(model, data, mass)                               # at q2 = 0
    assert np.min(sampled_loop(mass, alone.kp, alone.kd).real) < -1   # unstable there
    poles = sampled_loop(mass, both.kp, both.kd)
    assert np.max(np.abs(poles)) < 1 and np.min(poles.real) > 0
    with pytest.raises(ValueError, match='one posture or a'):
        model_gains(model, dofs, np.zeros((1, 1, 3)), limits, TIMESTEP)


@pytest.mark.parametrize('limit', [0.5, 2.0, 1000.0])
def test_psl_inits_settle_time_covers_the_measured_settling(limit):
    """psl init gives the hand `settle_time(gains)` after the movement: the pendulum's step
    response under the rule's gains, simulated, stays within 2 % of the step from then on (a
    small torque limit lowers the bandwidth and lengthens it; the default is 0.5 s)."""
    from psl_optimizer.task_generator import SETTLE_TIME, settle_time

    model = pendulum()
    gains = model_gains(model, np.array([0]), np.array([0.0]), np.array([limit]), TIMESTEP)
    settle = settle_time(gains)
    t, e = step_response(model, gains.kp[0], gains.kd[0], seconds=settle + 2.0)
    outside = np.flatnonzero(np.abs(e) > 0.02 * STEP)
    measured = t[outside[-1] + 1]
    assert measured <= settle, (measured, settle, gains.bandwidth_hz)
    assert settle - measured < 0.5 + 0.25 * measured or settle == SETTLE_TIME
