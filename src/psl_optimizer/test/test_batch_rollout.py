"""Batch mode against a second implementation: the same law stepped in Python, step by step,
scored from a kinematic replay."""
import numpy as np
import pytest
import yaml

from psl_controller.pd_law import PDLaw, law_for
from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.reward import Reward
from psl_task.arm_model import ArmModel
from psl_task.reward_geometry import RewardGeometry
from psl_task.task import EMBEDDED_TASKS, TaskError, load_task

Q_TOLERANCE = 1e-12        # rad; only the order of floating-point additions differs
REWARD_TOLERANCE = 1e-9


@pytest.fixture(scope='module')
def task():
    return load_task('reach_over_obstacle')


@pytest.fixture(scope='module')
def batch(task):
    return BatchRollouts(task)


def step_by_step(task, theta, tau, law=None):
    """The graph's semantics in one process: the law on each state (as the controller node
    computes it), one mj_step (as the simulator node), the reward from a replay (as the
    evaluator node)."""
    law = law or law_for(task)
    arm = ArmModel(task)
    ref = policy_for(task).reference(theta)
    arm.reset(tau)
    q, torque = [arm.q], [np.zeros(len(arm.joint_names))]
    for k in range(task.num_steps):
        u = law.torque(arm.q, arm.qd, ref.q[k], ref.qd[k], ref.u_ffwd[k])
        torque.append(arm.step(u))
        q.append(arm.q)
    q, torque = np.array(q), np.array(torque)
    reward = Reward(task, RewardGeometry(arm))
    return q, torque, reward.evaluate_replayed(q[None], torque[None], ref.q[None],
                                               np.asarray(tau)[None])[0]


def assert_equals_step_by_step(task, theta, tau, result, law=None):
    """The batch result against `step_by_step`: trajectory, torques, reward, components."""
    q, torque, evaluation = step_by_step(task, theta, tau, law)
    assert np.abs(result.q - q).max() < Q_TOLERANCE
    assert np.abs(result.torque - torque).max() < 1e-9
    assert result.evaluation.reward == pytest.approx(evaluation.reward, abs=REWARD_TOLERANCE)
    for name, value in evaluation.components.items():
        assert result.evaluation.components[name] == pytest.approx(value, rel=1e-9, abs=1e-12)
    return q, torque, evaluation


def test_batch_equals_step_by_step_simulation(task, batch):
    rng = np.random.default_rng(3)
    default = policy_for(task).default_theta
    thetas = default + rng.normal(0.0, 0.2 * np.abs(default).max(), (4, default.size))
    # a violent policy that stays in the joint ranges (the safety check's default): its
    # torques saturate
    thetas[0] = default + 3.0 * (thetas[0] - default)
    taus = np.array([task.sample_tau(rng) for _ in range(4)])
    results = batch.run(thetas, taus)
    saturated = 0
    for theta, tau, result in zip(thetas, taus, results):
        q, torque, _ = assert_equals_step_by_step(task, theta, tau, result)
        saturated += np.any(np.abs(torque) >= 40.0 - 1e-9)
    assert saturated > 0, 'the perturbed policies should hit the torque limit somewhere'


def test_a_candidate_leaving_the_joint_ranges_is_refused_and_not_simulated(task, batch):
    """theta * 6 drives joint2 far beyond its range [-3, 3]: refused with the reason and the
    penalty; the other members of the population are what they are alone."""
    default = policy_for(task).default_theta
    wild, tau = 6.0 * default, task.tau_default
    reference = batch.policy.reference(wild, tau)
    assert np.abs(reference.q).max() > 3.0
    checked, refused = batch.checked, batch.refused
    wilder = 8.0 * default
    results = batch.run(np.array([default, wild, wilder]), tau)
    assert [bool(r.refused) for r in results] == [False, True, True]
    assert 'below its limit -3' in results[1].refused or 'above its limit 3' in results[1].refused
    for r in results[1:]:
        assert not r.evaluation.fulfilled and r.q is None
        assert r.evaluation.reward < task.safety.penalty
    assert results[2].evaluation.reward < results[1].evaluation.reward     # graded
    # theta = 1e308 never gets as far: the range policy refuses it with the range
    with pytest.raises(ValueError, match='a units or scaling error'):
        batch.run(1e308 * np.ones_like(default)[None], tau)
    alone = batch.run(default[None], tau)[0]
    assert np.array_equal(alone.q, results[0].q)
    assert alone.evaluation.reward == results[0].evaluation.reward
    assert (batch.checked - checked, batch.refused - refused) == (4, 2)


def test_a_feed_forward_past_the_torque_limits_runs_at_the_limits():
    """payload_transport's theta_D (the feed-forward on the DMP's basis) scaled until its
    torque passes the joints' limits: the reference's feed-forward is clipped into them (the
    graph's controller rejects an effort past them, the law clips the torque anyway), so the
    candidate runs, not refused, and five or ten times the limit run alike (both at the
    limits); within the limits it runs as asked."""
    task = load_task('payload_transport')
    batch = BatchRollouts(task)
    policy = batch.policy
    theta = policy.default_theta.copy()
    limit = batch.arm.torque_high.min()
    thetas = np.tile(theta, (3, 1))
    for row, weight in zip(thetas, (0.4, 5.0, 10.0)):     # x the limit, on every basis
        row[policy.dynamics] = weight * limit
    refs = [policy.reference(t, task.tau_default) for t in thetas]
    assert np.abs(refs[0].u_ffwd).max() <= limit
    for ref in refs[1:]:
        assert np.all(ref.u_ffwd <= batch.arm.torque_high)
        assert np.any(ref.u_ffwd == batch.arm.torque_high)
    np.testing.assert_array_equal(refs[1].u_ffwd, refs[2].u_ffwd)
    results = batch.run(thetas, task.tau_default)
    assert all(not r.refused and r.q is not None for r in results), \
        [r.refused for r in results]
    np.testing.assert_array_equal(results[1].q, results[2].q)


def test_each_member_sees_its_own_task_instance(task, batch):
    theta = policy_for(task).default_theta
    low, high = task.tau_low, task.tau_high
    results = batch.run(np.tile(theta, (2, 1)), np.array([low, high]))
    # same motion, different obstacles: only the obstacle terms differ
    assert np.array_equal(results[0].q, results[1].q)
    assert results[0].evaluation.components != results[1].evaluation.components


def test_bad_inputs_are_refused(task, batch):
    theta = policy_for(task).default_theta
    with pytest.raises(TaskError):
        batch.run(theta[None], np.array([10.0, 10.0]))
    with pytest.raises(ValueError):
        batch.run(theta[None, :5], task.tau_default)
    bad = theta.copy()
    bad[0] = np.nan
    with pytest.raises(ValueError):
        batch.run(bad[None], task.tau_default)


def test_population_reward_equals_member_by_member(task, batch):
    """The reward of a population (sensors recorded by mujoco.rollout) against the reward of
    each member alone (a population of one, the same sensors on a kinematic replay)."""
    rng = np.random.default_rng(5)
    default = policy_for(task).default_theta
    thetas = default + rng.normal(0.0, 0.3 * np.abs(default).max(), (6, default.size))
    taus = np.array([task.sample_tau(rng) for _ in range(6)])
    for result, tau in zip(batch.run(thetas, taus), taus):
        single = batch.reward.evaluate_replayed(result.q[None], result.torque[None],
                                                result.q_ref[None], tau[None])[0]
        assert result.evaluation.fulfilled == single.fulfilled
        for name, value in single.components.items():
            assert result.evaluation.components[name] == pytest.approx(value, rel=1e-9,
                                                                       abs=1e-12)


def test_both_modes_follow_a_changed_law(task):
    """Other gains and limits in the law: batch mode (the law as MuJoCo actuators) and the
    graph's step-by-step semantics (the law on each state) change alike."""
    default = law_for(task)
    changed = PDLaw(0.5 * default.kp, 2.0 * default.kd, 0.5 * default.torque_low,
                    0.5 * default.torque_high)
    theta = policy_for(task).default_theta * 1.5
    tau = task.tau_default
    before = BatchRollouts(task).run(theta[None], tau)[0]
    after = BatchRollouts(task, law=changed).run(theta[None], tau)[0]
    assert np.abs(after.q - before.q).max() > 1e-3          # the law matters
    _, torque, _ = assert_equals_step_by_step(task, theta, tau, after, law=changed)
    assert np.abs(torque).max() <= 0.5 * np.abs(default.torque_high).max() + 1e-12


# -- a model unlike reach_over_obstacle's ------------------------------------------------------
def payload_task(folder):
    """The 4-joint arm of reach_4dof without its post (no mocap body, no obstacle), with
    sensors of its own, and a payload mass on the hand as the task parameter."""
    xml = (EMBEDDED_TASKS / 'reach_4dof.xml').read_text()
    start = xml.index('<body name="post"')
    end = xml.index('</body>', start) + len('</body>')
    xml = xml[:start] + xml[end:].replace('</actuator>', """</actuator>
  <sensor>
    <jointpos joint="elbow"/>
    <framepos objtype="site" objname="tool_tip"/>
  </sensor>""")
    (folder / 'payload_arm.xml').write_text(xml)
    data = yaml.safe_load((EMBEDDED_TASKS / 'reach_4dof.yaml').read_text())
    data.update(name='payload_reach', model='payload_arm.xml', task_parameters=[
        {'name': 'payload', 'unit': 'kg', 'low': 0.1, 'high': 3.0, 'default': 0.25,
         'binds': {'kind': 'body_mass', 'body': 'hand'}}])
    data['reward'] = dict(data['reward'], obstacle_geoms=[])
    path = folder / 'payload_reach.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def test_mass_parameters_own_sensors_and_no_mocap(tmp_path):
    """A task parameter that changes the model (a payload mass) reaches every rollout of the
    population; the model's own sensors and its lack of mocap bodies change nothing."""
    task = payload_task(tmp_path)
    batch = BatchRollouts(task)
    assert batch.model.nmocap == 0 and batch.arm.model.nsensor == 2
    theta = policy_for(task).default_theta
    taus = np.array([[0.1], [3.0], [0.1]])
    results = batch.run(np.tile(theta, (3, 1)), taus)
    assert not np.allclose(results[0].q, results[1].q, atol=1e-4)    # the payload matters
    np.testing.assert_array_equal(results[0].q, results[2].q)
    for tau, result in zip(taus, results):
        assert_equals_step_by_step(task, theta, tau, result)
    np.testing.assert_array_equal(batch.model.body_mass, batch.arm.model.body_mass)
