"""The safety check against independent references: references with closed-form velocity and
acceleration, a cart whose inverse dynamics is m a, the reward geometry's own replay for
collisions, and an arm the test folds onto itself."""
import textwrap

import numpy as np
import pytest
import yaml

from psl_task.arm_model import ArmModel
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
    verdict = SafetyCheck(ArmModel(task)).check(task.tau_default, q, qd)
    assert verdict.safe == safe
    if not safe:
        assert 'velocity of 1.257 rad/s, above the limit 1' in verdict.reason
        assert verdict.violation == pytest.approx(amplitude * 2 * np.pi - 1.0, rel=1e-9)


def test_the_acceleration_limit_uses_the_forward_difference(tmp_path):
    task = variant(tmp_path, {'max_acceleration': 5.0})
    q, qd = sine(task, 0.1, 1.0)                           # peak ~0.1 (2 pi)^2 = 3.95 rad/s^2
    check = SafetyCheck(ArmModel(task))
    assert check.check(task.tau_default, q, qd).safe
    q, qd = sine(task, 0.2, 1.0)                           # ~7.9 rad/s^2
    verdict = check.check(task.tau_default, q, qd)
    assert not verdict.safe and 'acceleration' in verdict.reason
    expected = np.abs(np.diff(qd, axis=0) / task.control_period).max() / 5.0 - 1.0
    assert verdict.violation == pytest.approx(expected, rel=1e-12)


def test_joint_ranges_with_a_margin(tmp_path):
    task = variant(tmp_path, {'joint_margin': 0.1})
    arm = ArmModel(task)
    high = arm.model.jnt_range[arm.joint_ids[1], 1]        # joint2's upper limit
    q = np.tile(task.start_posture, (task.num_steps + 1, 1))
    q[50, 1] = high - 0.05                                 # inside the range, not the margin
    verdict = SafetyCheck(arm).check(task.tau_default, q, np.zeros_like(q))
    assert not verdict.safe
    assert f"joint 'joint2' at {high - 0.05:.4g} is above its limit {high - 0.1:.4g}" in \
        verdict.reason
    assert 't = 0.100 s' in verdict.reason                 # step 50 at 500 Hz
    q[50, 1] = high - 0.15
    assert SafetyCheck(arm).check(task.tau_default, q, np.zeros_like(q)).safe



def leaving_from(task, start: np.ndarray, path) -> tuple[np.ndarray, np.ndarray]:
    """A reference from `start` (n,) along joint2's values `path`, the other joints still."""
    q = np.tile(start, (len(path), 1))
    q[:, 1] = path
    return q, np.zeros_like(q)


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
    verdict = check.check(task.tau_default, q, qd, start=start)
    assert verdict.safe == (not reason) and reason in verdict.reason, verdict.reason
    if reason:
        assert verdict.violation > 0
    candidate = check.check(task.tau_default, q, qd)
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
        assert check.check(task.tau_default, q, qd, start=task.start_posture) == \
            check.check(task.tau_default, q, qd)


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
    assert SafetyCheck(ArmModel(cart_task(tmp_path, 1.0))).check(tau, q, qd).safe
    verdict = SafetyCheck(ArmModel(cart_task(tmp_path, 0.5))).check(tau, q, qd)
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
    verdict = SafetyCheck(arm).check(tau, reference.q, reference.qd)
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
    verdict = check.check(np.array([0.0]), folded, np.gradient(folded, 0.002, axis=0))
    assert not verdict.safe and "touches itself: geoms 'g1' and 'g3'" in verdict.reason
    bent = s * np.array([0.0, 0.8, 0.8])                   # bent, but clear of itself
    assert check.check(np.array([0.0]), bent, np.gradient(bent, 0.002, axis=0)).safe


@pytest.mark.parametrize('section, words', [
    ({'max_velocity': -1.0}, 'safety.max_velocity must be >= 0'),
    ({'collisions': 'yes'}, 'safety.collisions must be true or false'),
    ({'speed': 1.0}, "safety has unknown key 'speed'; known: joint_margin, max_velocity"),
    ({'penalty': float('nan')}, 'safety.penalty must be finite'),
])
def test_bad_safety_sections_are_refused(tmp_path, section, words):
    with pytest.raises(TaskError, match=words):
        variant(tmp_path, section)


@pytest.mark.parametrize('safety', [{}, {'max_velocity': 2.0}])
def test_screening_a_population_gives_the_verdicts_of_one_by_one(tmp_path, safety):
    """The vectorised pass (default limits) and the detailed check agree on every member."""
    task = variant(tmp_path, safety)
    check = SafetyCheck(ArmModel(task))
    rng = np.random.default_rng(4)
    q, qd = sine(task, 0.1, 1.0)
    qs = np.stack([q + rng.normal(0.0, s, q.shape) for s in (0.0, 0.5, 2.0, 4.0)])
    qs[1, 30, 2] = np.nan
    qds = np.stack([qd] * 4) * np.array([1.0, 1.0, 3.0, 0.5])[:, None, None]
    taus = np.tile(task.tau_default, (4, 1))
    screened = check.screen(taus, qs, qds)
    assert screened == [check.check(tau, a, b) for tau, a, b in zip(taus, qs, qds)]
    assert any(v.safe for v in screened) and not all(v.safe for v in screened)


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
