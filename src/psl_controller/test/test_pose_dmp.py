"""Tests of PoseDMP (the position DMP and the orientation DMP on one phase) and of the policy
that moves the hand's pose (``policy.orientation``): against the two DMPs run alone (a second
computation of the same thing), the hand's pose by MuJoCo's forward kinematics on a separate
MjData, and the quaternion algebra's closed forms."""

import mujoco
import numpy as np
import pytest

from psl_task import quaternion
from psl_controller.dmp import DMP
from psl_controller.policy import TaskPolicy
from psl_controller.pose_dmp import PoseDMP
from psl_controller.quaternion_dmp import QuaternionDMP
from psl_task.arm_model import ArmModel
from psl_task.task import load_task

DT = 0.002
TOL_IK = 2e-5          # m, twice the inverse kinematics' tolerance (its knots)
TOL_ANGLE = 2e-4       # rad, the same stacked tolerance over the orientation weight 0.1 m/rad
Q0 = quaternion.exp_map(np.array([0.1, -0.2, 0.3]))
GOAL = quaternion.exp_map(np.array([-0.4, 0.5, 0.9]))


def pose_dmp(learn_goal=True, **changes):
    settings = dict(n_basis=5, duration=1.0, learn_goal=learn_goal)
    position = DMP(n_dims=3, y0=[0.1, 0.2, 0.3], goal=[0.4, -0.1, 0.0],
                   **{**settings, **changes.get('position', {})})
    orientation = QuaternionDMP(q0=Q0, goal=GOAL, **{**settings, **changes.get('orientation', {})})
    return PoseDMP(position, orientation)


def random_theta(pose, seed=0):
    return np.random.default_rng(seed).normal(0.0, 0.3, pose.num_parameters)


def test_theta_is_the_position_dmps_then_the_orientation_dmps():
    pose = pose_dmp()
    assert pose.num_parameters == (15 + 3) + (15 + 3)
    assert (pose.position_goal, pose.orientation_goal) == (slice(15, 18), slice(33, 36))
    theta = random_theta(pose)
    pose.set_theta(theta)
    np.testing.assert_array_equal(pose.get_theta(), theta)
    np.testing.assert_array_equal(pose.position.get_theta(), theta[:18])
    np.testing.assert_array_equal(pose.orientation.get_theta(), theta[18:])
    # the goal rotation vector turns the default goal: g = exp(r) * g0
    np.testing.assert_allclose(pose.orientation.goal, quaternion.product(
        quaternion.exp_map(theta[33:36]), GOAL), rtol=0, atol=1e-15)
    assert pose_dmp(learn_goal=False).num_parameters == 30


def test_integrate_is_the_two_dmps_on_one_grid():
    pose = pose_dmp()
    theta = random_theta(pose, 1)
    pose.set_theta(theta)
    traj = pose.integrate(DT, 1.5)
    alone = pose_dmp()
    alone.position.set_theta(theta[:18])
    alone.orientation.set_theta(theta[18:])
    position, orientation = alone.position.integrate(DT, 1.5), alone.orientation.integrate(DT, 1.5)
    for mine, theirs in ((traj.y, position.y), (traj.yd, position.yd), (traj.t, position.t),
                         (traj.quat, orientation.q), (traj.omega, orientation.omega)):
        np.testing.assert_array_equal(mine, theirs)
    # both reach their goals by the end of the settling (zero gate after the duration)
    np.testing.assert_allclose(traj.y[-1], pose.position.goal, atol=1e-3)
    assert np.linalg.norm(quaternion.log_map(quaternion.product(
        pose.orientation.goal, quaternion.conjugate(traj.quat[-1])))) < 1e-3


def test_a_population_row_is_the_single_integration():
    pose = pose_dmp()
    thetas = np.stack([random_theta(pose, seed) for seed in range(3)])
    population = pose.integrate_population(DT, thetas, 1.2)
    for row, theta in enumerate(thetas):
        pose.set_theta(theta)
        single = pose.integrate(DT, 1.2)
        # the forcing of both is one matrix product, which BLAS may sum in another order for
        # another population size (docs/testing.md, "What is equal to what"): within rounding
        np.testing.assert_allclose(population.quat[row], single.quat, rtol=0, atol=1e-12)
        np.testing.assert_allclose(population.y[row], single.y, rtol=0, atol=1e-12)


def test_a_goal_change_moves_the_position_goal_and_keeps_the_orientation():
    pose = pose_dmp()
    pose.set_theta(random_theta(pose, 2))
    plain = pose.integrate(DT, 1.5)
    changed = pose.integrate_goal_change(DT, 0.4, [0.3, 0.3, 0.3], 1.5)
    np.testing.assert_array_equal(changed.quat, plain.quat)
    k = int(round(0.4 / DT))
    np.testing.assert_array_equal(changed.y[:k + 1], plain.y[:k + 1])
    np.testing.assert_allclose(changed.y[-1], [0.3, 0.3, 0.3], atol=2e-3)


@pytest.mark.parametrize('changes, words', [
    ({'orientation': {'n_basis': 4}}, 'n_basis'),
    ({'orientation': {'duration': 2.0}}, 'duration'),
    ({'orientation': {'learn_goal': False}}, 'learn_goal'),
])
def test_dmps_on_different_phases_are_refused(changes, words):
    with pytest.raises(ValueError, match=words):
        pose_dmp(**changes)


def test_a_theta_of_the_wrong_size_is_refused():
    pose = pose_dmp()
    with pytest.raises(ValueError, match='36 entries .* got 35'):
        pose.set_theta(np.zeros(35))


# -- the policy of pose_reach_3d ------------------------------------------------------------------
@pytest.fixture(scope='module')
def pose_task():
    return load_task('pose_reach_3d')


def hand_pose(task, q):
    """Palm position (T, 3) and orientation (T, 4) along q (T, n) by MuJoCo on a fresh
    MjData."""
    arm = ArmModel(task)
    x, quat = np.empty((len(q), 3)), np.empty((len(q), 4))
    for k, qk in enumerate(q):
        arm.data.qpos[arm.qpos_adr] = qk
        mujoco.mj_kinematics(arm.model, arm.data)
        x[k] = arm.data.site_xpos[arm.ee_site]
        mujoco.mju_mat2Quat(quat[k], arm.data.site_xmat[arm.ee_site])
    return x, quat


def angles(quat, quat_ref):
    return np.linalg.norm(quaternion.log_map(quaternion.product(
        quat_ref, quaternion.conjugate(quat))), axis=-1)


def test_the_hand_follows_the_pose_dmp(pose_task):
    """The joint reference puts the palm on the pose DMP's path: position and orientation
    (MuJoCo's forward kinematics), for the default theta and one with the goal turned."""
    policy = TaskPolicy(pose_task)
    assert policy.controls_orientation
    turned = policy.default_theta.copy()
    turned[policy.orientation_goal] += [0.0, 0.0, 0.25]            # 0.25 rad about world z
    for theta in (policy.default_theta, turned):
        reference = policy.reference(theta)
        policy.movement.set_theta(theta[policy.kinematics])
        path = policy.movement.integrate(pose_task.control_period, reference.t[-1])
        x, quat = hand_pose(pose_task, reference.q)
        assert np.linalg.norm(x - path.y, axis=1).max() < TOL_IK
        assert angles(quat, path.quat).max() < TOL_ANGLE
    # the goal's turn is the hand's final turn
    np.testing.assert_allclose(angles(quat[-1], hand_pose(pose_task, policy.reference(
        policy.default_theta).q[-1:])[1][0]), 0.25, atol=2e-3)


def test_the_default_hand_pose_is_the_targets(pose_task):
    """The demonstration ends at the goal posture, where the target section's pose is the
    palm's: the default theta's hand ends on the default target, position and orientation."""
    from psl_task.quaternion import quaternion_of
    policy = TaskPolicy(pose_task)
    x, quat = hand_pose(pose_task, policy.reference(policy.default_theta).q[-1:])
    target, rotation = pose_task.target_of(None)
    assert np.linalg.norm(x[0] - target) < 1e-3
    assert angles(quat[0], quaternion_of(rotation)) < 2e-3


def test_a_longer_instance_stretches_both_dmps(pose_task, tmp_path):
    """With a duration task parameter the pose DMP is stretched in time as a whole: the hand
    ends at the same pose, later."""
    import shutil

    import yaml
    from psl_task.task import EMBEDDED_TASKS
    data = yaml.safe_load((EMBEDDED_TASKS / 'pose_reach_3d.yaml').read_text())
    data['task_parameters'].append({'name': 'duration', 'unit': 's', 'low': 1.0, 'high': 1.6,
                                    'binds': {'kind': 'duration'}})
    shutil.copy(EMBEDDED_TASKS / data['model'], tmp_path / data['model'])
    (tmp_path / 'timed.yaml').write_text(yaml.safe_dump(data))
    task = load_task(str(tmp_path / 'timed.yaml'))
    policy = TaskPolicy(task)
    tau = np.append(task.tau_default[:4], 1.5)
    slow = policy.reference(policy.default_theta, tau)
    fast = policy.reference(policy.default_theta, np.append(task.tau_default[:4], 1.0))
    assert len(slow.t) > len(fast.t)
    x_slow, q_slow = hand_pose(task, slow.q[-1:])
    x_fast, q_fast = hand_pose(task, fast.q[-1:])
    assert np.linalg.norm(x_slow - x_fast) < 2e-3 and angles(q_slow[0], q_fast[0]) < 5e-3


def test_orientation_needs_end_effector_space(tmp_path):
    import shutil

    import yaml
    from psl_task.task import EMBEDDED_TASKS
    data = yaml.safe_load((EMBEDDED_TASKS / 'pose_reach_3d.yaml').read_text())
    data['policy']['space'] = 'joint'
    shutil.copy(EMBEDDED_TASKS / data['model'], tmp_path / data['model'])
    (tmp_path / 'joint.yaml').write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match='orientation needs space end_effector'):
        TaskPolicy(load_task(str(tmp_path / 'joint.yaml')))


def test_a_goal_change_of_the_pose_turns_the_hand_without_a_jump(pose_task):
    """A new goal of 7 values (the point and the hand's orientation, [w, x, y, z]) at 0.4 s:
    the joint reference is the reference's up to the switch, has no step larger than the
    plain one's plus the goal filter's, and brings the palm to the new pose (MuJoCo's
    forward kinematics)."""
    policy = TaskPolicy(pose_task)
    theta = policy.default_theta
    plain = policy.reference(theta)
    policy.movement.set_theta(theta[policy.kinematics])
    goal_quat = policy.movement.orientation.goal
    turned = quaternion.product(quaternion.exp_map([0.0, 0.0, 0.3]), goal_quat)
    point = policy.movement.position.goal + [0.02, -0.03, 0.02]
    changed = policy.reference_with_new_goal(theta, None, 0.4, np.concatenate([point, turned]))
    k = int(round(0.4 / pose_task.control_period))
    np.testing.assert_array_equal(changed.q[:k + 1], plain.q[:k + 1])
    steps, plain_steps = (np.abs(np.diff(r.q, axis=0)).max(axis=0) for r in (changed, plain))
    assert np.all(steps <= plain_steps + 0.3 * policy.dmp.alpha_goal * pose_task.control_period)
    x, quat = hand_pose(pose_task, changed.q[-1:])
    assert np.linalg.norm(x[0] - point) < 2e-3 and angles(quat[0], turned) < 5e-3
    # 3 values: the point only, the orientation as before
    point_only = policy.reference_with_new_goal(theta, None, 0.4, point)
    assert angles(hand_pose(pose_task, point_only.q[-1:])[1][0], goal_quat) < 5e-3


@pytest.mark.parametrize('goal, words', [([0.4, 0.0], 'needs 3 or 7 values'),
                                         ([0.4, 0.0, -0.1, 2.0, 0.0, 0.0, 0.0], 'unit'),
                                         ([0.4, 0.0, -0.1, np.nan, 0.0, 0.0, 1.0], 'finite')])
def test_bad_pose_goals_are_refused(pose_task, goal, words):
    policy = TaskPolicy(pose_task)
    with pytest.raises(ValueError, match=words):
        policy.reference_with_new_goal(policy.default_theta, None, 0.4, goal)
