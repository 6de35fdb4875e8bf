"""``psl init``'s library (psl_optimizer.task_generator): a task from a robot description as
published. On published arms (example-robot-data's URDFs, an MJCF): the file loads, its
postures keep the margin inside every range, every corner of its target box is reached (the
policy's joint reference at the corner, its hand by forward kinematics on a fresh MjData),
``psl check`` has no warning; the end-effector point from a link's geometry; refusals."""
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

import gymnasium

from psl_controller.policy import policy_for
from psl_optimizer import task_generator
from psl_optimizer.robot_check import check_robot
from psl_optimizer.task_generator import InitError, generate, tool_point
from psl_task.arm_model import ArmModel
from psl_task.inverse_kinematics import VELOCITY_MARGIN
from psl_task.task import load_task, task_from_data

EMBEDDED = Path(task_generator.__file__).resolve().parents[2] / 'psl_task' / 'psl_task' / 'tasks'
ERD = 'package://example-robot-data/robots/'
GYMNASIUM = Path(gymnasium.__file__).parent / 'envs' / 'mujoco' / 'assets'
ARMS = {    # name -> (model, end-effector link, base link)
    'xarm7': (ERD + 'xarm_description/urdf/xarm7.urdf', 'link7', None),
    'panda': (ERD + 'panda_description/urdf/panda.urdf', 'panda_hand_tcp', None),
    'so_arm100': (ERD + 'so_arm_description/urdf/so100.urdf', 'gripper', None),
    'talos_left_arm': (ERD + 'talos_data/robots/talos_left_arm.urdf', 'arm_left_7_link', None),
    'point_reach_3d_mjcf': (str(EMBEDDED / 'point_reach_3d.xml'), 'hand', None),
    # COLLADA meshes, joints as slow as 0.63 rad/s
    'kinova_jaco2': (ERD + 'kinova_description/robots/kinova.urdf', 'j2s6s200_end_effector',
                     None),
    # an MJCF at 100 Hz, +-2 N m on a shoulder moving 13.7 kg: a slow closed loop, a long settle
    'gymnasium_pusher': (str(GYMNASIUM / 'pusher_v5.xml'), 'tips_arm', None),
    # a humanoid's arm from its full-body MJCF: tendons, motors geared 25:1, physics at 333 Hz
    'gymnasium_humanoid_left_arm': (str(GYMNASIUM / 'humanoid.xml'), 'left_lower_arm', 'torso'),
    # a pose: the point and a turn about the vertical
    'panda_pose': (ERD + 'panda_description/urdf/panda.urdf', 'panda_hand_tcp', None, 'pose'),
}


@pytest.fixture(scope='module', params=sorted(ARMS))
def generated(request, tmp_path_factory):
    model, link, base, *kind = ARMS[request.param]
    out = tmp_path_factory.mktemp(request.param) / 'task.yaml'
    result = generate(model, link, out, base=base, kind=(kind or ['point'])[0])
    out.write_text(result.text)
    return request.param, out, result


def test_the_file_loads_as_generated(generated):
    name, out, result = generated
    task = load_task(str(out))
    assert task.n_joints == result.task.n_joints >= 3
    assert task.policy.space == 'end_effector' and task.policy.learn_goal
    assert task.policy.feedforward
    pose = ['target_yaw'] if len(ARMS[name]) > 3 else []
    assert [p.name for p in task.parameters] == ['target_x', 'target_y', 'target_z'] + pose
    assert task.policy.orientation == bool(pose)
    assert ('orientation_error' in task.reward.weights) == bool(pose)
    data = yaml.safe_load(out.read_text())
    assert data['robot']['joints'] == task_generator.split_joints(
        ARMS[name][0] if ARMS[name][0].startswith('package://') else data['robot']['model'],
        ARMS[name][1], out).driven


def test_postures_keep_the_margin_inside_every_range(generated):
    _, out, _ = generated
    task = load_task(str(out))
    arm = ArmModel(task)
    low, high = arm.limits.position_low, arm.limits.position_high
    margin = task_generator.range_margin(np.maximum(low, -np.pi), np.minimum(high, np.pi))
    for q in (task.start_posture, task.goal_posture, *task.demo_positions):
        assert np.all(q >= low + margin - 1e-4) and np.all(q <= high - margin + 1e-4), q


def test_every_corner_of_the_box_is_reached(generated):
    """The policy's joint reference toward each corner, its last posture's hand by forward
    kinematics on a fresh MjData of the task's model: within REACH_MARGIN of the corner."""
    _, out, _ = generated
    task = load_task(str(out))
    policy = policy_for(task)
    arm = ArmModel(task)
    data = mujoco.MjData(arm.model)
    corners = 0
    for x in (task.tau_low[0], task.tau_high[0]):
        for y in (task.tau_low[1], task.tau_high[1]):
            for z in (task.tau_low[2], task.tau_high[2]):
                tau = task.tau_default.copy()
                tau[:3] = x, y, z
                theta = policy.default_theta.copy()
                theta[policy.goal] = task.target_of(tau)[0]
                q = policy.reference(theta, tau).q[-1]
                data.qpos[arm.qpos_adr] = q
                mujoco.mj_kinematics(arm.model, data)
                hand = data.site_xpos[arm.ee_site]
                assert np.linalg.norm(hand - tau[:3]) <= task_generator.REACH_MARGIN, (tau, hand)
                corners += 1
    assert corners == 8
    assert np.all(task.tau_high - task.tau_low >= 0.02)     # a box, not a point


def test_a_pose_task_reaches_every_orientation_corner(generated):
    """A pose task: each of the 16 corners (the box's and the yaw's ends) through the
    policy's own pose DMP and IK ends within ORIENTATION_MARGIN of the target's orientation;
    and the target's orientation is the hand's at the goal posture (the file's Euler angles
    read back): with the default goal orientation the hand ends turned from the target at
    the yaw's high end by exactly that yaw's offset, by forward kinematics on a fresh MjData
    and the angle of R_hand^T R_target. A point task has no orientation corners."""
    from psl_optimizer.robot_check import orientation_reach
    name, out, _ = generated
    task = load_task(str(out))
    corners = orientation_reach(task)
    if len(ARMS[name]) < 4:
        assert corners == []
        return
    assert len(corners) == 16
    assert max(angle for _, angle in corners) <= task_generator.ORIENTATION_MARGIN
    policy = policy_for(task)
    arm = ArmModel(task)
    data = mujoco.MjData(arm.model)
    theta = policy.default_theta.copy()
    tau = task.tau_default.copy()
    tau[3] = task.tau_high[3]
    theta[policy.goal] = task.target_of(tau)[0]
    data.qpos[arm.qpos_adr] = policy.reference(theta, tau).q[-1]
    mujoco.mj_kinematics(arm.model, data)
    hand = data.site_xmat[arm.ee_site].reshape(3, 3)
    target = task.target_of(tau)[1]
    turn = np.arccos(np.clip((np.trace(hand.T @ target) - 1) / 2, -1, 1))
    assert turn == pytest.approx(task.tau_high[3] - task.tau_default[3], abs=2e-3)


def test_the_demonstration_keeps_within_the_joints_speeds(generated):
    """The policy's default joint reference (the demonstration through the differential IK),
    differentiated: each joint's peak speed within the share of its velocity limit the IK
    keeps (1 - VELOCITY_MARGIN), however slow the arm (Kinova JACO2's 0.63 rad/s gets a
    longer movement: without it psl init finds no goal)."""
    _, out, _ = generated
    task = load_task(str(out))
    arm = ArmModel(task)
    policy = policy_for(task)
    reference = policy.reference(policy.default_theta.copy(), task.tau_default)
    speed = np.max(np.abs(np.diff(reference.q, axis=0)), axis=0) * task.control_rate
    bound = (1.0 - VELOCITY_MARGIN) * arm.limits.velocity
    assert np.all(speed <= bound * (1 + 1e-6)), (speed / arm.limits.velocity, task.duration)


def test_psl_check_has_no_warning(generated):
    _, out, result = generated
    assert result.warnings == []
    assert check_robot(load_task(str(out))).warnings == []


def _link_model(geoms: str, site_body: str = 'tip') -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(f"""
<mujoco><worldbody><body name="arm"><joint name="j0" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02"/>
  <body name="tip" pos="0 0 -0.3"><joint name="j1" axis="0 1 0"/>
    <inertial pos="0 0 -0.05" mass="0.1" diaginertia="1e-4 1e-4 1e-4"/>{geoms}
  </body></body></worldbody></mujoco>""")


def test_tool_point_is_the_far_end_of_the_link_geometry():
    """A box 0.1 m long hanging below the last joint: the point is its lower end (on the line
    from the joint through the box's centre); a link without geometry is a tool frame."""
    m = _link_model('<geom type="box" size="0.02 0.03 0.05" pos="0 0 -0.05"/>')
    offset, where = tool_point(m, m.body('tip').id, m.joint('j1').id)
    np.testing.assert_allclose(offset, [0.0, 0.0, -0.1], atol=1e-9)
    assert 'collision' in where
    m = _link_model('')
    offset, where = tool_point(m, m.body('tip').id, m.joint('j1').id)
    np.testing.assert_array_equal(offset, np.zeros(3))
    assert 'tool frame' in where


def test_tool_point_takes_the_visual_geometry_where_there_is_no_other():
    m = _link_model('<geom type="box" size="0.02 0.02 0.04" pos="0 0 -0.04" contype="0" '
                    'conaffinity="0" group="1"/>')
    offset, where = tool_point(m, m.body('tip').id, m.joint('j1').id)
    np.testing.assert_allclose(offset, [0.0, 0.0, -0.08], atol=1e-9)
    assert 'visual' in where


@pytest.mark.parametrize('link, base, words', [
    ('no_such_link', None, ('no such link', 'link7')),
    ('link3', 'link5', ('not below',)),
    ('link_base', None, ('nothing to drive',)),
])
def test_refusals_name_the_cause(tmp_path, link, base, words):
    with pytest.raises(InitError) as caught:
        generate(ARMS['xarm7'][0], link, tmp_path / 'task.yaml', base=base)
    message = str(caught.value)
    assert '\n' not in message
    for word in words:
        assert word in message, message


def test_an_unreadable_model_is_refused(tmp_path):
    model = tmp_path / 'arm.urdf'
    model.write_text('<robot name="broken"><link name="a"></robot>')
    with pytest.raises(InitError, match='cannot read the model'):
        generate(str(model), 'a', tmp_path / 'task.yaml')


def test_a_start_posture_outside_the_margin_is_refused(tmp_path):
    with pytest.raises(InitError, match='--posture puts joint2'):
        generate(ARMS['xarm7'][0], 'link7', tmp_path / 'task.yaml',
                 posture=np.array([0.0, 5.0, 0.0, 0.5, 0.0, 0.3, 0.0]))


def test_a_given_start_posture_is_the_start(tmp_path):
    start = np.array([0.0, 0.2, 0.0, 0.5, 0.0, 0.3, 0.0])
    result = generate(ARMS['xarm7'][0], 'link7', tmp_path / 'task.yaml', posture=start)
    np.testing.assert_allclose(result.task.start_posture, start, atol=1e-4)
    assert result.warnings == []


def test_draft_reads_as_the_file(tmp_path):
    """task_from_data on the text: what load_task makes of the written file."""
    result = generate(ARMS['xarm7'][0], 'link7', tmp_path / 'task.yaml')
    (tmp_path / 'task.yaml').write_text(result.text)
    again = task_from_data(tmp_path / 'task.yaml', yaml.safe_load(result.text))
    np.testing.assert_array_equal(again.start_posture, load_task(
        str(tmp_path / 'task.yaml')).start_posture)
