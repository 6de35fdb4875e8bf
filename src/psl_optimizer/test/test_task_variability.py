"""The chapter's task variability: target position and orientation, duration, a learned goal.

References are independent of the code under test: rotation matrices written by hand, the
DMP's temporal scaling against the unscaled DMP at stretched times, forward kinematics of the
planar arm in closed form, the episode length from the YAML numbers.
"""
import copy
import shutil

import numpy as np
import pytest
import yaml

from psl_controller.dmp import DMP
from psl_controller.policy import TaskPolicy
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.reward import orientation_error
from psl_task.task import EMBEDDED_TASKS, TaskError, load_task, rotation_xyz

PLANAR = 'planar_10dof_reach'
TIMED = 'payload_transport_timed'


def planar_data() -> dict:
    return yaml.safe_load((EMBEDDED_TASKS / f'{PLANAR}.yaml').read_text())


def write(folder, data, name='variant'):
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(EMBEDDED_TASKS / data['model'], folder / data['model'])
    path = folder / f'{name}.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def planar_hand(q: np.ndarray, link: float = 0.1) -> np.ndarray:
    """Closed-form hand position of the 10-link planar arm (links of 0.1 m about z)."""
    angles = np.cumsum(q)
    return np.array([link * np.cos(angles).sum(), link * np.sin(angles).sum(), 0.0])


# -- the task section -----------------------------------------------------------------------
def test_target_of_takes_bound_coordinates_from_tau_and_the_rest_from_the_yaml(tmp_path):
    data = planar_data()
    data['target']['position'] = [0.5, 0.2, 0.07]
    data['target']['orientation'] = [0.0, 0.0, 0.3]
    data['task_parameters'].append({'name': 'target_yaw', 'low': -1.0, 'high': 1.0,
                                    'binds': {'kind': 'target_orientation', 'axis': 2}})
    task = write(tmp_path, data)
    position, rotation = task.target_of(np.array([0.61, 0.33, -0.4]))
    np.testing.assert_array_equal(position, [0.61, 0.33, 0.07])      # z from the YAML
    c, s = np.cos(-0.4), np.sin(-0.4)
    np.testing.assert_allclose(rotation, [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-15)


def test_rotation_xyz_is_rz_ry_rx():
    angles = np.array([0.3, -0.5, 1.1])
    rx = np.array([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]])
    ry = np.array([[np.cos(-0.5), 0, np.sin(-0.5)], [0, 1, 0],
                   [-np.sin(-0.5), 0, np.cos(-0.5)]])
    rz = np.array([[np.cos(1.1), -np.sin(1.1), 0], [np.sin(1.1), np.cos(1.1), 0], [0, 0, 1]])
    np.testing.assert_allclose(rotation_xyz(angles), rz @ ry @ rx, atol=1e-15)


def test_target_default_is_where_the_demonstration_ends():
    """The embedded target tasks: the default instance's target is the hand at the goal
    posture (closed-form FK of the planar arm), so the demonstration fulfils it."""
    task = load_task(PLANAR)
    position, _ = task.target_of(task.tau_default)
    np.testing.assert_allclose(position, planar_hand(task.goal_posture), atol=5e-4)   # rad rounding


@pytest.mark.parametrize('change, words', [
    (lambda d: d.pop('target'), 'need a target section'),
    (lambda d: d['task_parameters'][0]['binds'].update(axis=3), r'binds.axis must be one of 0, 1 or 2, got 3'),
    (lambda d: d['target'].update(position=[0.1, 0.2]), 'target.position must be 3'),
    (lambda d: d['target'].update(colour='red'), "target has unknown key 'colour'"),
    (lambda d: d['policy'].update(space='cartesian'), 'policy.space'),
    (lambda d: d['policy'].update(learn_goal='yes'), 'learn_goal must be true or false'),
    (lambda d: d['task_parameters'].append(
        {'name': 'duration', 'low': -0.5, 'high': 1.0, 'binds': {'kind': 'duration'}}),
     'stay above 0 s'),
    (lambda d: d['task_parameters'].extend(
        [{'name': f'd{i}', 'low': 0.5, 'high': 1.0, 'binds': {'kind': 'duration'}}
         for i in range(2)]), 'at most one'),
])
def test_bad_task_variability_keys_are_refused(tmp_path, change, words):
    data = copy.deepcopy(planar_data())
    change(data)
    with pytest.raises(TaskError, match=words):
        write(tmp_path, data)


def test_a_target_body_that_is_not_mocap_is_refused(tmp_path):
    from psl_task.arm_model import ArmModel
    data = planar_data()
    data['target']['body'] = 'link3'
    with pytest.raises(TaskError, match='not mocap'):
        ArmModel(write(tmp_path, data))


def test_the_target_body_follows_the_instance():
    from psl_task.arm_model import ArmModel
    arm = ArmModel(load_task(PLANAR))
    arm.reset(np.array([0.42, 0.11]))
    mocap = arm.model.body_mocapid[arm.model.body('target').id]
    np.testing.assert_array_equal(arm.data.mocap_pos[mocap], [0.42, 0.11, 0.0])


# -- duration -------------------------------------------------------------------------------
def test_duration_sets_the_episode_length():
    task = load_task(TIMED)
    settle, rate = 0.5, 500.0                      # from the YAML
    for duration in (1.2, 1.5, 2.0):
        assert task.duration_of(np.array([1.0, duration])) == duration
        assert task.num_steps_of(np.array([1.0, duration])) == round((duration + settle) * rate)


def test_time_scaled_dmp_is_the_same_path_stretched():
    """tau_s^2 ydd = k_s (g - y) - k_d tau_s yd + f: y_T(t) = y_T0(t T0 / T). Checked on a
    fine grid (the zero-order hold differs from continuous time by O(dt))."""
    rng = np.random.default_rng(3)
    theta = rng.normal(0, 200, 2 * 6)
    base = DMP(2, 6, 1.0, [0.0, 1.0], [1.0, -0.5])
    slow = DMP(2, 6, 1.6, [0.0, 1.0], [1.0, -0.5], time_scale=1.6)
    base.set_theta(theta)
    slow.set_theta(theta)
    dt = 1e-4
    y0 = base.integrate(dt, 1.5).y
    y1 = slow.integrate(dt * 1.6, 1.5 * 1.6).y     # the same grid, stretched
    np.testing.assert_allclose(y1, y0, atol=1e-9)   # exact: the scaled ZOH system is the same
    coarse = slow.integrate(2e-3, 2.4)             # on another grid: the same path within O(dt)
    t = coarse.t / 1.6
    fine = base.integrate(1e-5, 1.5)
    ref = np.column_stack([np.interp(t, fine.t, fine.y[:, d]) for d in range(2)])
    assert np.max(np.abs(coarse.y - ref)) < 0.02 * np.max(np.abs(fine.y))


def test_a_learned_goal_is_the_end_of_theta_and_the_end_of_the_path():
    dmp = DMP(3, 4, 1.0, [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], learn_goal=True)
    assert dmp.num_parameters == 3 * 4 + 3
    theta = np.r_[np.zeros(12), [0.3, -0.2, 0.9]]
    dmp.set_theta(theta)
    np.testing.assert_array_equal(dmp.get_theta(), theta)
    end = dmp.integrate(1e-3, 3.0).y[-1]            # long after the motion: at the attractor
    np.testing.assert_allclose(end, [0.3, -0.2, 0.9], atol=1e-6)
    with pytest.raises(ValueError, match='goal'):
        dmp.set_theta(np.zeros(12))


def test_batch_rollouts_of_different_durations_equal_separate_runs():
    task = load_task(TIMED)
    batch = BatchRollouts(task, n_threads=1)
    theta = batch.policy.default_theta
    taus = np.array([[1.0, 1.3], [2.0, 1.9], [1.5, 1.3]])
    together = batch.run(np.tile(theta, (3, 1)), taus)
    for tau, result in zip(taus, together):
        alone = batch.run(theta[None], tau)[0]
        assert len(result.q) == task.num_steps_of(tau) + 1
        np.testing.assert_array_equal(result.q, alone.q)
        assert result.evaluation.reward == alone.evaluation.reward


def test_a_shorter_movement_needs_more_torque():
    """The same theta_K stretched in time: the faster lift's inverse-dynamics torque peaks
    higher (a property of the dynamics, not of the code)."""
    from psl_optimizer.inverse_dynamics import inverse_dynamics_torque
    task = load_task(TIMED)
    policy = TaskPolicy(task)
    theta = policy.default_theta
    peaks = []
    for duration in (1.2, 2.0):
        tau = np.array([1.5, duration])
        torque = inverse_dynamics_torque(task, tau, policy.reference(theta, tau))
        peaks.append(np.max(np.abs(torque[:, 1])))
    assert peaks[0] > peaks[1]


# -- the target in the reward ---------------------------------------------------------------
def test_orientation_error_is_the_rotation_angle():
    rng = np.random.default_rng(0)
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0, np.pi)
        quat = np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis]       # from the identity
        got = orientation_error(quat[None], np.eye(3)[None])[0]
        assert got == pytest.approx(angle, abs=1e-7)


def test_goal_error_measures_the_distance_to_the_instances_target():
    """The default theta ends at the default target: the goal error grows with the distance
    of the instance's target from it."""
    task = load_task(PLANAR)
    batch = BatchRollouts(task, n_threads=1)
    theta = batch.policy.default_theta
    taus = np.array([task.tau_default, task.tau_default + [0.1, 0.0],
                     task.tau_default + [0.1, 0.2]])
    results = batch.run(np.tile(theta, (3, 1)), taus)
    hand = planar_hand(results[0].q[-1])
    for tau, result in zip(taus, results):
        expected = np.linalg.norm(hand[:2] - tau)
        assert result.evaluation.components['goal_error'] == pytest.approx(expected, abs=1e-6)


def test_orientation_error_without_a_target_is_refused(tmp_path):
    from psl_optimizer.reward import Reward
    from psl_task.arm_model import ArmModel
    from psl_task.reward_geometry import RewardGeometry
    data = yaml.safe_load((EMBEDDED_TASKS / 'reach_over_obstacle.yaml').read_text())
    data['reward']['weights']['orientation_error'] = 1.0
    task = write(tmp_path, data)
    with pytest.raises(ValueError, match='needs a target'):
        Reward(task, RewardGeometry(ArmModel(task)))


# -- end-effector space ---------------------------------------------------------------------
@pytest.fixture(scope='module')
def hand_space_task(tmp_path_factory):
    data = planar_data()
    data['policy'].update(space='end_effector')
    return write(tmp_path_factory.mktemp('hand_space'), data, 'hand_space')


def test_the_hand_follows_the_dmp_path_through_inverse_kinematics(hand_space_task):
    """The joint reference's hand (closed-form FK) is the DMP's hand path; the path starts at
    the start posture's hand and ends at the learned goal point."""
    policy = TaskPolicy(hand_space_task)
    theta = policy.default_theta.copy()
    theta[policy.goal] = [0.6, 0.35, 0.0]
    reference = policy.reference(theta)
    policy.dmp.set_theta(theta[policy.kinematics])
    dt = hand_space_task.control_period
    path = policy.dmp.integrate(dt, hand_space_task.num_steps * dt).y
    hands = np.array([planar_hand(q) for q in reference.q])
    np.testing.assert_allclose(hands[:, :2], path[:, :2], atol=1e-4)
    np.testing.assert_allclose(hands[0], planar_hand(hand_space_task.start_posture), atol=1e-12)
    np.testing.assert_allclose(hands[-1, :2], [0.6, 0.35], atol=1e-4)
    np.testing.assert_allclose(reference.q[0], hand_space_task.start_posture, atol=1e-12)


def test_an_unreachable_goal_point_is_penalised_not_nan(hand_space_task):
    """A goal point 3 m away from a 1 m arm: a finite reference, the arm stretched toward it
    (the hand about 1 m from the base); the rollout scores the miss of the target."""
    batch = BatchRollouts(hand_space_task, n_threads=1)
    theta = batch.policy.default_theta.copy()
    theta[batch.policy.goal] = [3.0, 0.0, 0.0]
    result = batch.run(theta[None], hand_space_task.tau_default)[0]
    assert np.all(np.isfinite(result.reference.q)) and np.all(np.isfinite(result.q))
    hand = planar_hand(result.q[-1])
    assert np.linalg.norm(hand) > 0.97 and hand[0] > 0.9
    assert result.evaluation.components['goal_error'] == pytest.approx(
        np.linalg.norm(hand[:2] - hand_space_task.tau_default), abs=1e-6)
    assert not result.evaluation.fulfilled


# -- ILC of a learned hand goal -------------------------------------------------------------
def hand_by_mujoco(task, q):
    """The palm position at joint angles q, by MuJoCo's own forward kinematics."""
    import mujoco
    from psl_task.arm_model import ArmModel
    arm = ArmModel(task)
    arm.data.qpos[arm.qpos_adr] = q
    mujoco.mj_forward(arm.model, arm.data)
    return arm.data.site_xpos[arm.ee_site].copy()


def test_an_ilc_step_takes_the_hands_miss_off_the_goal_point():
    from psl_optimizer.ilc import ILCSettings, ilc_step
    task = load_task('point_reach_3d')
    batch = BatchRollouts(task, n_threads=1)
    policy = batch.policy
    tau = np.array([0.37, 0.1, -0.02])
    theta = policy.default_theta
    result = batch.run(theta[None], tau)[0]
    miss = hand_by_mujoco(task, result.q[-1]) - tau
    assert np.linalg.norm(miss) > 0.05                    # the default goal is far from it
    stepped = ilc_step(policy, theta, result, ILCSettings(goal_gain=0.5), tau)
    np.testing.assert_allclose(stepped[policy.goal], theta[policy.goal] - 0.5 * miss, atol=1e-12)
    assert np.any(stepped[policy.dynamics] != theta[policy.dynamics])   # theta_D learned too


def test_ilc_reaches_a_new_target_in_a_few_rollouts():
    """From the default theta, ILC alone (goal point and feed-forward) fulfils an instance the
    default misses by centimetres."""
    from psl_optimizer.ilc import ILCSettings, ilc_search
    task = load_task('point_reach_3d')
    batch = BatchRollouts(task, n_threads=1)
    tau = np.array([0.48, -0.1, -0.18])
    start = batch.run(batch.policy.default_theta[None], tau)[0]
    assert not start.evaluation.fulfilled
    found = ilc_search(batch, tau, batch.policy.default_theta, ILCSettings(iterations=10))
    assert found.fulfilled and found.rollouts <= 5
    final = batch.run(found.theta[None], tau)[0]
    assert np.linalg.norm(hand_by_mujoco(task, final.q[-1]) - tau) < 0.015


def test_an_ilc_step_turns_the_goal_orientation_by_the_hands_miss():
    """pose_reach_3d: the goal rotation vector r becomes log(exp(g c) * exp(r)), c the
    rotation from the hand's final orientation to the target's (MuJoCo's quaternions), and
    the goal point takes the position miss off as in point_reach_3d."""
    import mujoco

    from psl_task import quaternion
    from psl_optimizer.ilc import ILCSettings, ilc_step
    from psl_task.arm_model import ArmModel
    task = load_task('pose_reach_3d')
    batch = BatchRollouts(task, n_threads=1)
    policy = batch.policy
    tau = np.array([0.45, 0.05, -0.05, 3.3])            # the yaw 0.215 rad off the default
    theta = policy.default_theta
    result = batch.run(theta[None], tau)[0]
    arm = ArmModel(task)
    arm.data.qpos[arm.qpos_adr] = result.q[-1]
    mujoco.mj_kinematics(arm.model, arm.data)
    hand, target = np.empty(4), np.empty(4)
    mujoco.mju_mat2Quat(hand, arm.data.site_xmat[arm.ee_site])
    mujoco.mju_mat2Quat(target, task.target_of(tau)[1].reshape(-1))
    turn = quaternion.log_map(quaternion.product(target, quaternion.conjugate(hand)))
    assert np.linalg.norm(turn) > 0.1
    stepped = ilc_step(policy, theta, result, ILCSettings(goal_gain=0.5), tau)
    expected = quaternion.log_map(quaternion.product(
        quaternion.exp_map(0.5 * turn), quaternion.exp_map(theta[policy.orientation_goal])))
    np.testing.assert_allclose(stepped[policy.orientation_goal], expected, rtol=0, atol=1e-12)
    miss = arm.data.site_xpos[arm.ee_site] - tau[:3]
    np.testing.assert_allclose(stepped[policy.goal], theta[policy.goal] - 0.5 * miss, atol=1e-12)


def test_ilc_reaches_a_new_target_pose_in_a_few_rollouts():
    """From the default theta, ILC alone (goal point, goal orientation and feed-forward)
    fulfils a pose the default misses by centimetres and a tenth of a radian."""
    from psl_optimizer.ilc import ILCSettings, ilc_search
    task = load_task('pose_reach_3d')
    batch = BatchRollouts(task, n_threads=1)
    tau = np.array([0.47, -0.08, -0.15, 2.85])
    start = batch.run(batch.policy.default_theta[None], tau)[0]
    assert not start.evaluation.fulfilled
    found = ilc_search(batch, tau, batch.policy.default_theta, ILCSettings(iterations=10))
    assert found.fulfilled and found.rollouts <= 5
    final = batch.run(found.theta[None], tau)[0].evaluation.components
    assert final['goal_error'] < 0.015 and final['orientation_error'] < 0.05


def test_a_pose_goal_is_a_point_and_a_rotation():
    """Reward.goal_of on pose_reach_3d: 3 values the point (the orientation stays the
    instance's), 7 the point and a quaternion, whose rotation matrix is the closed form of a
    turn about z; other sizes and non-unit quaternions are refused."""
    from psl_optimizer.batch_rollout import BatchRollouts
    reward = BatchRollouts(load_task('pose_reach_3d'), n_threads=1).reward
    point, rotation = reward.goal_of([0.4, 0.1, -0.1])
    np.testing.assert_array_equal(point, [0.4, 0.1, -0.1])
    assert rotation is None
    a = 0.3
    point, rotation = reward.goal_of([0.4, 0.1, -0.1, np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)])
    np.testing.assert_allclose(rotation, [[np.cos(a), -np.sin(a), 0.0],
                                          [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]],
                               rtol=0, atol=1e-15)
    for goal, words in (([0.4, 0.1], '3 or 7 finite values'),
                        ([0.4, 0.1, -0.1, 2.0, 0.0, 0.0, 0.0], 'unit quaternion')):
        with pytest.raises(ValueError, match=words):
            reward.goal_of(goal)
