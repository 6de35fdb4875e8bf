"""The safety check against independent references: references with closed-form velocity and
acceleration, a cart whose inverse dynamics is m a, the reward geometry's own replay for
collisions, and an arm the test folds onto itself."""
import textwrap

import numpy as np
import pytest
import yaml

from psl_task.arm_model import ArmModel
from psl_task.joint_limits import MAX_VELOCITY, POSITION_SLACK
from psl_task.reward_geometry import RewardGeometry
from psl_task.safety_check import SafetyCheck, tracking_abort
from psl_task.task import EMBEDDED_TASKS, TaskError, load_task


def variant(tmp_path, safety, name='reach_over_obstacle'):
    data = yaml.safe_load((EMBEDDED_TASKS / f'{name}.yaml').read_text())
    data['model'] = str(EMBEDDED_TASKS / data['model'])
    data['safety'] = safety
    path = tmp_path / f'{name}_safety.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def sine(task, amplitude, frequency):
    """q = start + A sin(w t) on every joint: max |qd| = A w, max |qdd| ~ A w^2."""
    t = np.arange(task.num_steps + 1) * task.control_period
    w = 2 * np.pi * frequency
    q = task.start_posture + amplitude * np.sin(w * t)[:, None] * np.ones(task.n_joints)
    qd = amplitude * w * np.cos(w * t)[:, None] * np.ones(task.n_joints)
    return q, qd


@pytest.mark.parametrize('amplitude, safe', [(0.05, True), (0.2, False)])
def test_the_velocity_limit_is_the_closed_form_peak(tmp_path, amplitude, safe):
    task = variant(tmp_path, {'max_velocity': 1.0})        # rad/s; peak A * 2 pi * 1 Hz
    q, qd = sine(task, amplitude, 1.0)
    verdict = SafetyCheck(ArmModel(task)).check(task.tau_default, q, qd, np.zeros_like(q))
    assert verdict.safe == safe
    if not safe:
        assert 'velocity of 1.257 rad/s, above the limit 1' in verdict.reason
        assert verdict.violation == pytest.approx(amplitude * 2 * np.pi - 1.0, rel=1e-9)


def test_the_acceleration_limit_uses_the_forward_difference(tmp_path):
    task = variant(tmp_path, {'max_acceleration': 5.0})
    q, qd = sine(task, 0.1, 1.0)                           # peak ~0.1 (2 pi)^2 = 3.95 rad/s^2
    check = SafetyCheck(ArmModel(task))
    assert check.check(task.tau_default, q, qd, np.zeros_like(q)).safe
    q, qd = sine(task, 0.2, 1.0)                           # ~7.9 rad/s^2
    verdict = check.check(task.tau_default, q, qd, np.zeros_like(q))
    assert not verdict.safe and 'acceleration' in verdict.reason
    expected = np.abs(np.diff(qd, axis=0) / task.control_period).max() / 5.0 - 1.0
    assert verdict.violation == pytest.approx(expected, rel=1e-12)


def bump(task, joint: int, peak: float, at: int) -> tuple[np.ndarray, np.ndarray]:
    """The start posture with joint `joint` raised smoothly (a raised cosine of 0.2 s) to
    `peak` at step `at` and back: q and its qd (T, n)."""
    t = np.arange(task.num_steps + 1) * task.control_period
    width, t0 = 0.2, at * task.control_period - 0.1
    phase = np.clip((t - t0) / width, 0.0, 1.0)
    q = np.tile(task.start_posture, (len(t), 1))
    qd = np.zeros_like(q)
    rise = peak - task.start_posture[joint]
    q[:, joint] += rise * 0.5 * (1.0 - np.cos(2 * np.pi * phase))
    qd[:, joint] = rise * np.pi / width * np.sin(2 * np.pi * phase)
    return q, qd


def test_joint_ranges_with_a_margin(tmp_path):
    task = variant(tmp_path, {'joint_margin': 0.1})
    arm = ArmModel(task)
    high = arm.model.jnt_range[arm.joint_ids[1], 1]        # joint2's upper limit
    q, qd = bump(task, 1, high - 0.05, 50)                 # inside the range, not the margin
    verdict = SafetyCheck(arm).check(task.tau_default, q, qd, np.zeros_like(q))
    assert not verdict.safe
    assert f"joint 'joint2' at {high - 0.05:.4g} is above its limit {high - 0.1:.4g}" in \
        verdict.reason
    assert 't = 0.100 s' in verdict.reason                 # step 50 at 500 Hz
    q, qd = bump(task, 1, high - 0.15, 50)
    assert SafetyCheck(arm).check(task.tau_default, q, qd, np.zeros_like(q)).safe



def leaving_from(task, start: np.ndarray, path) -> tuple[np.ndarray, np.ndarray]:
    """A reference from `start` (n,) along joint2's values `path`, 0.5 s from each to the
    next (straight, its velocity the segments' slope), the other joints still."""
    knots = np.arange(len(path)) * 250
    k = np.arange(knots[-1] + 1)
    q = np.tile(start, (len(k), 1))
    q[:, 1] = np.interp(k, knots, path)
    return q, np.gradient(q, task.control_period, axis=0)


@pytest.mark.parametrize('path, reason', [
    ([3.2, 3.1, 3.1, 3.0, 2.0], ''),                   # toward the range, pausing, inside
    ([3.2, 3.2, 3.2, 3.2, 3.2], 'ends at 3.2, outside its range'),
    ([3.2, 3.1, 3.15, 3.0, 2.0], "joint 'joint2' at 3.15 is above its limit 3"),   # back out
    ([3.2, 3.25, 3.0, 2.0, 2.0], "joint 'joint2' at 3.25 is above its limit 3"),   # further
    ([3.2, 2.5, -3.1, -2.0, 2.0], "joint 'joint2' at -3.1 is below its limit -3"),  # across
])
def test_a_homing_from_outside_may_only_come_closer_and_must_end_inside(path, reason):
    """The law of the ranges with a start outside (a homing from where a foreign goal left
    the arm: joint2 at 3.2, its limit 3): no joint's distance to its range grows from the
    start's along the reference, and every joint ends inside. The same reference as a
    candidate (no start: from the start posture, inside) is refused at its first point."""
    task = load_task('reach_over_obstacle')
    check = SafetyCheck(ArmModel(task))
    start = np.array(task.start_posture, dtype=float)
    start[1] = 3.2
    q, qd = leaving_from(task, start, path)
    verdict = check.check(task.tau_default, q, qd, np.zeros_like(q), start=start)
    assert verdict.safe == (not reason) and reason in verdict.reason, verdict.reason
    if reason:
        assert verdict.violation > 0
    candidate = check.check(task.tau_default, q, qd, np.zeros_like(q))
    assert not candidate.safe and "joint 'joint2' at 3." in candidate.reason
    assert 'come to' not in candidate.reason
    np.testing.assert_array_equal(check.outside(start), [0.0, start[1] - 3.0, 0.0])


def test_from_inside_the_homing_law_is_the_candidates(tmp_path):
    """A start inside the ranges: every reference gets the candidate's verdict, reason and
    violation (one law; the start only lets a reference begin outside)."""
    task = variant(tmp_path, {'joint_margin': 0.1})
    check = SafetyCheck(ArmModel(task))
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = task.start_posture + rng.uniform(-1.5, 1.5, (40, task.n_joints)).cumsum(axis=0) / 8
        qd = np.zeros_like(q)
        u = np.zeros_like(q)
        assert check.check(task.tau_default, q, qd, u, start=task.start_posture) == \
            check.check(task.tau_default, q, qd, u)


CART = """
<mujoco model="cart">
  <option timestep="0.002" gravity="0 0 0"/>
  <worldbody>
    <body name="cart">
      <joint name="x" type="slide" axis="1 0 0" range="-5 5"/>
      <geom type="box" size="0.05 0.05 0.05" mass="3" contype="0" conaffinity="0"/>
      <site name="tip"/>
    </body>
  </worldbody>
  <actuator><motor joint="x" ctrlrange="-30 30"/></actuator>
</mujoco>
"""


def cart_task(tmp_path, torque_share):
    (tmp_path / 'cart.xml').write_text(CART)
    data = yaml.safe_load(textwrap.dedent(f"""
        name: cart
        model: cart.xml
        end_effector_site: tip
        control_rate: 500.0
        duration: 1.0
        start_posture: [0.0]
        goal_posture: [0.5]
        task_parameters: [{{name: unused, low: 0, high: 1, binds: {{kind: duration, offset: 1}}}}]
        controller: {{kp: [100.0], kd: [10.0]}}
        policy: {{n_basis: 3}}
        demonstration: {{times: [0.0, 1.0], positions: [[0.0], [0.5]]}}
        reward: {{weights: {{tracking_error: 1.0}}, success_threshold: -1.0}}
        safety: {{torque_share: {torque_share}}}
        """))
    path = tmp_path / 'cart.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def test_the_torque_along_the_reference_is_mass_times_acceleration(tmp_path):
    """A 3 kg cart under a constant 8 m/s^2: 24 N, within 30 N; at 0.5 x the limit (15 N)
    it is refused with the excess ratio 24 / 15 - 1."""
    t = np.arange(501) * 0.002
    q, qd = 0.5 * 8.0 * t[:, None] ** 2, 8.0 * t[:, None]
    tau = np.array([0.0])
    assert SafetyCheck(ArmModel(cart_task(tmp_path, 1.0))).check(tau, q, qd, 0 * q).safe
    verdict = SafetyCheck(ArmModel(cart_task(tmp_path, 0.5))).check(tau, q, qd, 0 * q)
    assert not verdict.safe and "joint 'x' needs 24 N m" in verdict.reason
    assert verdict.violation == pytest.approx(24.0 / 15.0 - 1.0, rel=1e-9)


# (obstacle_x, obstacle_height) in units of their ranges, and whether the demonstration
# enters the pillar there: clear over the low one, into the high one (link3, by 65 and 45 mm)
@pytest.mark.parametrize('corner, collides', [((0.0, 0.0), False), ((1.0, 1.0), True),
                                              ((0.5, 1.0), True)])
def test_collisions_agree_with_the_reward_geometrys_replay(tmp_path, corner, collides):
    """The demonstration on a low and a high pillar: refused exactly when the reward
    geometry's replay (a second implementation: distance sensors) finds a penetration, and
    both find the one the corner has."""
    task = variant(tmp_path, {'collisions': True, 'replay_period': 0.002})
    arm = ArmModel(task)
    from psl_controller.policy import policy_for     # the policy is one layer up: test only
    policy = policy_for(task)
    tau = task.tau_low + np.array(corner) * (task.tau_high - task.tau_low)
    reference = policy.reference(policy.default_theta, tau)
    verdict = SafetyCheck(arm).check(tau, reference.q, reference.qd, reference.u_ffwd)
    distance = RewardGeometry(arm).replay(reference.q[None], tau[None]).distance[0]
    assert (distance.min() < 0.0) == collides, distance.min()
    assert verdict.safe == (not collides), verdict.reason
    if collides:
        assert 'enters obstacle' in verdict.reason
        assert verdict.violation == pytest.approx(-distance.min(), abs=1e-9)


FOLDING = """
<mujoco model="folding">
  <compiler angle="radian"/>
  <option timestep="0.002" gravity="0 0 0"/>
  <worldbody>
    <body name="l1">
      <joint name="j1" type="hinge" axis="0 0 1"/>
      <geom name="g1" type="capsule" fromto="0 0 0 0.5 0 0" size="0.04" mass="1"/>
      <body name="l2" pos="0.5 0 0">
        <joint name="j2" type="hinge" axis="0 0 1" range="-3.1 3.1"/>
        <geom name="g2" type="capsule" fromto="0 0 0 0.3 0 0" size="0.04" mass="1"/>
        <body name="l3" pos="0.3 0 0">
          <joint name="j3" type="hinge" axis="0 0 1" range="-3.1 3.1"/>
          <geom name="g3" type="capsule" fromto="0 0 0 0.4 0 0" size="0.04" mass="1"/>
          <site name="tip" pos="0.4 0 0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="j1" ctrlrange="-10 10"/><motor joint="j2" ctrlrange="-10 10"/>
    <motor joint="j3" ctrlrange="-10 10"/>
  </actuator>
</mujoco>
"""


def test_an_arm_folded_onto_itself_is_refused(tmp_path):
    """Elbow and wrist folded by ~pi/2 each: the third link lies across the first (two bodies
    apart: MuJoCo's parent-child filter does not hide the contact)."""
    (tmp_path / 'folding.xml').write_text(FOLDING)
    data = yaml.safe_load(textwrap.dedent("""
        name: folding
        model: folding.xml
        end_effector_site: tip
        control_rate: 500.0
        duration: 1.0
        start_posture: [0.0, 0.0, 0.0]
        goal_posture: [0.0, 1.6, 1.6]
        task_parameters: [{name: unused, low: 0, high: 1, binds: {kind: duration, offset: 1}}]
        controller: {kp: [10.0, 10.0, 10.0], kd: [1.0, 1.0, 1.0]}
        policy: {n_basis: 3}
        demonstration: {times: [0.0, 1.0], positions: [[0, 0, 0], [0, 1.6, 1.6]]}
        reward: {weights: {tracking_error: 1.0}, success_threshold: -1.0}
        safety: {self_collision: true}
        """))
    path = tmp_path / 'folding.yaml'
    path.write_text(yaml.safe_dump(data))
    task = load_task(str(path))
    check = SafetyCheck(ArmModel(task))
    s = np.linspace(0.0, 1.0, 501)[:, None]
    folded = s * np.array([0.0, 2.2, 2.2])
    verdict = check.check(np.array([0.0]), folded, np.gradient(folded, 0.002, axis=0), 0 * folded)
    assert not verdict.safe and "touches itself: geoms 'g1' and 'g3'" in verdict.reason
    bent = s * np.array([0.0, 0.8, 0.8])                   # bent, but clear of itself
    assert check.check(np.array([0.0]), bent, np.gradient(bent, 0.002, axis=0),
                       0 * bent).safe


@pytest.mark.parametrize('section, words', [
    ({'max_velocity': -1.0}, 'safety.max_velocity must be >= 0'),
    ({'collisions': 'yes'}, 'safety.collisions must be true or false'),
    ({'speed': 1.0}, "safety has unknown key 'speed'; known: joint_margin, max_velocity"),
    ({'penalty': float('nan')}, 'safety.penalty must be finite'),
])
def test_bad_safety_sections_are_refused(tmp_path, section, words):
    with pytest.raises(TaskError, match=words):
        variant(tmp_path, section)


def touching(task, wobble: float) -> tuple[np.ndarray, np.ndarray]:
    """joint2 raised to its upper limit (3 rad: a smoothstep over 0.4 s), held there for
    0.1 s and lowered again, its velocities while held +-`wobble` rad/s, alternating: every
    point inside the range and within the velocity bound, the cubic through two of them
    (v0 = -v1 = wobble, no net motion) bulging past the limit by wobble dt / 4."""
    t = np.arange(task.num_steps + 1) * task.control_period
    up, down = np.clip((t - 0.1) / 0.4, 0.0, 1.0), np.clip((t - 0.6) / 0.4, 0.0, 1.0)
    rise = 3.0 - task.start_posture[1]
    q = np.tile(task.start_posture, (len(t), 1))
    qd = np.zeros_like(q)
    for sign, s in ((1.0, up), (-1.0, down)):
        q[:, 1] += sign * rise * s ** 3 * (10 - 15 * s + 6 * s ** 2)
        qd[:, 1] += sign * rise * 30 * s ** 2 * (1 - s) ** 2 / 0.4
    held = np.flatnonzero((t > 0.5 + 1e-9) & (t < 0.6 - 1e-9))
    qd[held, 1] += wobble * (-1.0) ** np.arange(len(held))
    return q, qd


def cruising(task, speed: float) -> tuple[np.ndarray, np.ndarray]:
    """joint3 speeding up to `speed` rad/s (a smoothstep over 30 ms), cruising 4 ms, slowing
    to rest; its positions the trapezoidal sums of the velocities, so the cubic between two
    points stays within their velocities."""
    t = np.arange(task.num_steps + 1) * task.control_period
    s = np.clip((t - 0.1) / 0.03, 0, 1) - np.clip((t - 0.134) / 0.03, 0, 1)
    qd = np.zeros((len(t), task.n_joints))
    qd[:, 2] = speed * s ** 2 * (3 - 2 * s)
    q = task.start_posture + np.concatenate([np.zeros((1, task.n_joints)), np.cumsum(
        0.5 * (qd[1:] + qd[:-1]) * task.control_period, axis=0)])
    return q, qd


@pytest.mark.parametrize('safety', [{}, {'max_velocity': 2.0}, {'max_acceleration': 50.0}])
def test_screening_a_population_gives_the_verdicts_of_one_by_one(tmp_path, safety):
    """The vectorised pass (default limits) and the detailed check agree on every member:
    safe ones, and ones refused for each rule the pass covers (not finite, a range, the
    velocity bound, the feed-forward, the interpolation between points)."""
    task = variant(tmp_path, safety)
    check = SafetyCheck(ArmModel(task))
    rng = np.random.default_rng(4)
    q, qd = sine(task, 0.1, 1.0)
    fast_q, fast_qd = sine(task, 0.1, 200.0)                   # 126 rad/s at the points
    limit = check.limits.effort_high
    cases = [(q, qd, 0 * q), (q, qd, 0.5 * limit + 0 * q),      # safe
             (q + rng.normal(0.0, 0.5, q.shape), qd, 0 * q),     # out of range, jumpy
             (q, qd * 3.0, 0 * q), (q, qd * 0.5, 0 * q),
             (fast_q, fast_qd, 0 * q),                           # velocity
             (*cruising(task, 100.5), 0 * q),                    # at its points only
             (q, qd, 1.5 * limit + 0 * q),                       # feed-forward
             (*touching(task, 5.0), 0 * q)]                      # between points
    qs, qds, us = (np.stack([case[i] for case in cases]) for i in range(3))
    qs[1, 30, 2] = np.nan
    taus = np.tile(task.tau_default, (len(cases), 1))
    screened = check.screen(taus, qs, qds, us)
    assert screened == [check.check(tau, *arrays) for tau, *arrays in zip(taus, qs, qds, us)]
    assert any(v.safe for v in screened) and not all(v.safe for v in screened)
    if not safety:
        reasons = ' | '.join(v.reason for v in screened)
        for words in ('not finite', 'its limit', 'reaches a velocity', 'the feed-forward',
                      'the cubic a controller interpolates'):
            assert words in reasons, reasons


def test_the_tracking_bound_replayed_names_the_first_state_past_it():
    q_ref = np.zeros((10, 3))
    q = q_ref.copy()
    q[4, 2] = 0.05                       # within the bound
    q[6, 1], q[6, 2] = 0.25, -0.3        # the first state past 0.2: joint c, 0.1 beyond
    q[8, 0] = 1.0                        # later and larger: not the abort
    verdict = tracking_abort(q, q_ref, 0.2, ['a', 'b', 'c'], 0.002)
    assert not verdict.safe
    assert verdict.violation == pytest.approx(0.1, abs=1e-15)
    assert "joint 'c' is 0.3 rad from its reference at 0.012 s" in verdict.reason
    assert tracking_abort(q, q_ref, float('inf'), ['a', 'b', 'c'], 0.002).safe
    assert tracking_abort(q, q_ref, 1.0, ['a', 'b', 'c'], 0.002).safe    # not beyond: equal


# -- the arm's limits: what every controller psl serves holds a goal to (issue 46) ------------
@pytest.mark.parametrize('frequency, violation', [
    (18.0, 0.0), (22.0, 0.8 * 2 * np.pi * 22 / 100 - 1), (26.0, 0.8 * 2 * np.pi * 26 / 100 - 1)])
def test_the_arms_velocity_bound_holds_without_a_task_limit(frequency, violation):
    """No safety.max_velocity: a reference past the arm's velocity bound (an MJCF's: 100
    rad/s, which the controllers reject) is refused, its violation the excess ratio, growing
    with the excess. Catches: the bound only where the task sets one (before issue 46's
    controllers' limits, any velocity passed)."""
    task = load_task('reach_over_obstacle')
    t = np.arange(task.num_steps + 1) * task.control_period
    w = 2 * np.pi * frequency                              # whole periods: at rest at the end
    q = np.tile(task.start_posture, (len(t), 1))
    qd = np.zeros_like(q)
    q[:, 2] += 0.8 * (1 - np.cos(w * t))                   # joint3: -1.12 .. 0.48 rad
    qd[:, 2] = 0.8 * w * np.sin(w * t)                     # peak 0.8 w
    check = SafetyCheck(ArmModel(task))
    np.testing.assert_array_equal(check.limits.velocity, MAX_VELOCITY)
    verdict = check.check(task.tau_default, q, qd, np.zeros_like(q))
    assert verdict.safe == (violation == 0.0), verdict.reason
    if violation:
        assert "joint 'joint3' reaches a velocity of" in verdict.reason
        assert 'above the limit 100 at t = ' in verdict.reason
        assert verdict.violation == pytest.approx(np.abs(qd).max() / 100 - 1, rel=1e-12)
        assert verdict.violation == pytest.approx(violation, rel=1e-2)


@pytest.mark.parametrize('share', [1.0, 1.2, 2.0])
def test_a_feed_forward_beyond_the_torque_limits_is_refused(share):
    """u_ffwd at `share` of joint3's torque limit (40 N m) at one point, either sign: at the
    limit it passes (a controller takes an effort on its limit), beyond it is refused with
    the excess as a share of the limit. Catches: the feed-forward unchecked (the law clips
    the torque in batch mode, and the graph's controller rejected the goal)."""
    task = load_task('reach_over_obstacle')
    check = SafetyCheck(ArmModel(task))
    q, qd = sine(task, 0.05, 1.0)
    for sign in (1.0, -1.0):
        u = np.zeros_like(q)
        u[100, 2] = sign * share * 40.0
        verdict = check.check(task.tau_default, q, qd, u)
        assert verdict.safe == (share == 1.0), verdict.reason
        if share > 1.0:
            side = 'above' if sign > 0 else 'below'
            assert (f"joint 'joint3': the feed-forward of {sign * share * 40:.4g} N m at "
                    f't = 0.200 s is {side} its torque limit {sign * 40:g} N m') in verdict.reason
            assert verdict.violation == pytest.approx(share - 1.0, rel=1e-12)
    u = np.zeros_like(q)
    u[7, 0] = np.inf
    assert check.check(task.tau_default, q, qd, u).reason == 'the reference is not finite'


def test_a_bulge_between_points_is_refused_and_its_violation_grows():
    """Every point inside the range and within the velocity bound, the cubic a controller
    interpolates between them past the range by more than its slack: refused, the violation
    the overshoot beyond the slack [rad], growing with the wobble; a bulge within the slack
    passes. Catches: only the points checked (the controllers' rule checks the
    interpolation)."""
    task = load_task('reach_over_obstacle')
    check = SafetyCheck(ArmModel(task))
    violations = []
    for wobble in (1.0, 1.5, 4.0, 8.0):                    # bulge wobble dt / 4
        q, qd = touching(task, wobble)
        assert q.max(axis=0)[1] <= 3.0 and np.abs(qd).max() < 100.0
        verdict = check.check(task.tau_default, q, qd, np.zeros_like(q))
        violations.append(verdict.violation)
        if wobble * task.control_period / 4 < POSITION_SLACK:
            assert verdict.safe, verdict.reason
            continue
        assert verdict.violation == pytest.approx(
            wobble * task.control_period / 4 - POSITION_SLACK, rel=1e-6)
        assert "joint 'joint2': between the points at t = 0.5" in verdict.reason
        assert 'above its limit 3 rad by' in verdict.reason
        assert 'more than the 0.001 rad the controllers psl serve tolerate' in verdict.reason
    assert violations[0] == violations[1] == 0.0 < violations[2] < violations[3]


def test_a_reference_ending_in_motion_is_checked_as_it_is_sent():
    """joint3 speeding up to 90 rad/s at the episode's last point (within the bound at every
    point): psl sends the last point at rest (a JTC refuses a trajectory that ends moving),
    and the cubic of the last segment then reaches 109 rad/s, past the bound and its slack:
    refused, as the controllers reject that goal. Catches: the reference checked with the
    velocity it does not send."""
    task = load_task('reach_over_obstacle')
    dt = task.control_period
    t = np.arange(task.num_steps + 1) * dt
    s = np.clip((t - (t[-1] - 0.02)) / 0.02, 0.0, 1.0)      # the last 20 ms
    q = np.tile(task.start_posture, (len(t), 1))
    qd = np.zeros_like(q)
    qd[:, 2] = 90.0 * s ** 2
    q[:, 2] += 90.0 * 0.02 * s ** 3 / 3
    verdict = SafetyCheck(ArmModel(task)).check(task.tau_default, q, qd, np.zeros_like(q))
    assert np.abs(qd).max() == 90.0
    assert "joint 'joint3': between the points at t = 1.998 and 2.000 s" in verdict.reason
    assert 'reaches velocity 108.' in verdict.reason, verdict.reason


def test_a_urdfs_velocity_limits_are_the_arms(tmp_path):
    """MuJoCo drops a URDF's <limit velocity>: the arm's limits read them from the file
    (else 100 rad/s), and the safety check holds a reference to them."""
    (tmp_path / 'arm.urdf').write_text(textwrap.dedent("""\
        <robot name="two">
          <link name="base"/>
          <link name="upper"><inertial><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0"
            iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
          <link name="fore"><inertial><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0"
            iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
          <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/>
            <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="30" velocity="2"/></joint>
          <joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/>
            <origin xyz="0.5 0 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3"
            effort="20"/></joint>
        </robot>"""))
    (tmp_path / 'arm.yaml').write_text(textwrap.dedent("""\
        name: two
        robot: {model: arm.urdf, end_effector: {body: fore, offset: [0.4, 0.0, 0.0]}}
        control_rate: 500.0
        duration: 1.0
        start_posture: [0.0, 0.0]
        goal_posture: [0.5, 0.5]
        task_parameters: [{name: unused, low: 0, high: 1, binds: {kind: duration, offset: 1}}]
        controller: {kp: [10.0, 10.0], kd: [1.0, 1.0]}
        policy: {n_basis: 3}
        demonstration: {times: [0.0, 1.0], positions: [[0, 0], [0.5, 0.5]]}
        reward: {weights: {tracking_error: 1.0}, success_threshold: -1.0}
        """))
    task = load_task(str(tmp_path / 'arm.yaml'))
    check = SafetyCheck(ArmModel(task))
    assert check.limits.velocity.tolist() == [2.0, MAX_VELOCITY]
    q, qd = sine(task, 0.4, 1.0)                           # 2.51 rad/s on both joints
    verdict = check.check(np.array([0.5]), q, qd, np.zeros_like(q))
    assert "joint 'shoulder' reaches a velocity of 2.513 rad/s, above the limit 2" in \
        verdict.reason
