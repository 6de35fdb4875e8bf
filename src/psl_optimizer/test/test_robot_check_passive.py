"""psl check warns when passive joints move under gravity at rest
(`psl_optimizer.robot_check.passive_motion`): the Unitree G1's left arm taken from its
full-body URDF (example-robot-data, as published) without locks — its waist folds and the
hand drops — is told which joints moved, how far, and the lock to paste; pasted, the warning
is gone. A loose object (the ball of ball_throw) is no joint of the robot."""
import re
import textwrap

import pytest
import yaml

from psl_optimizer.robot_check import (PASSIVE_SWING_WARNING, check_robot, passive_motion,
                                       passive_warning)
from psl_task.arm_model import ArmModel
from psl_task.task import load_task

ARM = ['left_shoulder_pitch_joint', 'left_shoulder_roll_joint', 'left_shoulder_yaw_joint',
       'left_elbow_joint', 'left_wrist_roll_joint', 'left_wrist_pitch_joint',
       'left_wrist_yaw_joint']
START = [0.3, 0.3, 0.0, 0.8, 0.0, 0.0, 0.0]
GOAL = [0.0, 0.3, 0.0, 0.3, 0.0, 0.0, 0.0]


def g1_task(folder, locked: dict | None = None, name: str = 'g1'):
    """The G1's left arm driven (gains for a 20 rad/s bandwidth of each joint's inertia at
    the start, the arm's weight cancelled), the rest of the body as the URDF has it."""
    data = yaml.safe_load(textwrap.dedent(f"""
        robot:
          model: package://example-robot-data/robots/g1_description/urdf/g1_29dof_rev_1_0.urdf
          end_effector: {{body: left_wrist_yaw_link, offset: [0.1, 0.0, 0.0]}}
          joints: {ARM}
          gravity_compensation: true
        control_rate: 500.0
        duration: 1.0
        start_posture: {START}
        goal_posture: {GOAL}
        task_parameters:
          - {{name: target_x, low: 0.1, high: 0.2, binds: {{kind: target_position, axis: 0}}}}
        target: {{position: [0.15, 0.2, 0.1]}}
        controller:
          kp: [70.0, 60.0, 8.0, 14.0, 0.15, 2.0, 0.7]
          kd: [7.0, 6.0, 0.8, 1.4, 0.015, 0.2, 0.07]
        policy: {{kind: dmp, n_basis: 5}}
        demonstration: {{times: [0.0, 1.0], positions: [{START}, {GOAL}]}}
        reward: {{weights: {{goal_error: 10.0}}, success_threshold: -0.2}}
        """))
    if locked is not None:
        data['robot']['locked_joints'] = locked
    path = folder / f'{name}.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def test_the_g1_arm_without_locks_is_told_to_lock_the_body_and_the_lock_works(tmp_path):
    report = check_robot(g1_task(tmp_path))
    warning = next(w for w in report.warnings if w.startswith('passive joints move'))
    assert '22 passive joints of the robot moved (waist_' in warning   # the hand's carriers
    hand = float(re.search(r'moved the hand ([0-9.]+) mm', warning).group(1))
    assert hand > 50.0                           # measured: 185 mm in 1 s
    lock = yaml.safe_load(warning.split('robot.locked_joints: ', 1)[1])
    assert len(lock) == 22 and set(lock) == set(report.passive_joints)
    assert lock['waist_pitch_joint'] == 0.0      # the URDF's reference pose: 0
    locked = check_robot(g1_task(tmp_path, lock, 'g1_locked'))
    assert locked.passive_joints == []
    assert not [w for w in locked.warnings if w.startswith('passive joints move')]


def test_limbs_that_swing_without_moving_the_hand_are_named_too(tmp_path):
    """The waist locked, the legs and the right arm left free: they hang from the fixed
    pelvis and the locked torso without moving the hand, but they swing (> 0.05 rad)."""
    waist = {'waist_yaw_joint': 0.0, 'waist_roll_joint': 0.0, 'waist_pitch_joint': 0.0}
    task = g1_task(tmp_path, waist)
    arm = ArmModel(task)
    arm.reset(task.tau_default)
    motion = passive_motion(arm)
    assert motion.hand_by_passive == pytest.approx(0.0, abs=1e-12)
    assert 'waist_pitch_joint' not in motion.moved and motion.carry_hand == ()
    assert max(motion.moved.values()) > PASSIVE_SWING_WARNING
    warning = passive_warning(motion)
    assert 'which moved the hand 0.0 mm' in warning and 'right_elbow_joint' in warning


def test_a_loose_object_is_not_the_robot():
    task = load_task('ball_throw')
    arm = ArmModel(task)
    arm.reset(task.tau_default)
    assert arm.passive_joints == ['ball']
    motion = passive_motion(arm)
    assert motion.moved == {} and passive_warning(motion) == ''


STIFF_BASE = """
<mujoco>
  <compiler angle="radian"/>
  <option timestep="0.002"/>
  <worldbody>
    <body name="mount">
      <joint name="mount" axis="0 1 0" stiffness="1000" damping="30" range="-0.5 0.5"/>
      <geom type="box" size="0.05 0.05 0.05" mass="1" contype="0" conaffinity="0"/>
      <body name="link" pos="0.05 0 0">
        <joint name="shoulder" axis="0 1 0" range="-3 3"/>
        <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.03" mass="2"
              contype="0" conaffinity="0"/>
        <site name="tip" pos="0.5 0 0"/>
        <body name="finger" pos="0.5 0 0">
          <joint name="finger" axis="1 0 0" range="0.2 0.6"/>
          <geom type="box" size="0.01 0.01 0.03" pos="0 0 -0.03" mass="0.05"
                contype="0" conaffinity="0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="shoulder" ctrlrange="-50 50"/></actuator>
</mujoco>
"""


def stiff_base_task(folder, locked: dict):
    """A one-joint arm on a stiff passive mount (1000 N m/rad under 6 N m: it gives 0.006 rad,
    the hand 3 mm), a finger at its tip whose range leaves out its reference angle 0."""
    (folder / 'stiff.xml').write_text(STIFF_BASE)
    data = {'model': 'stiff.xml', 'end_effector_site': 'tip',
            'robot': {'joints': ['shoulder'], 'locked_joints': locked},
            'control_rate': 500.0, 'duration': 1.0, 'start_posture': [0.0],
            'goal_posture': [0.1],
            'task_parameters': [{'name': 'x', 'low': 0.0, 'high': 1.0,
                                 'binds': {'kind': 'target_position', 'axis': 0}}],
            'target': {'position': [0.5, 0.0, 0.0]},
            'controller': {'kp': [2000.0], 'kd': [50.0]}, 'policy': {'n_basis': 3},
            'demonstration': {'times': [0.0, 1.0], 'positions': [[0.0], [0.1]]},
            'reward': {'weights': {'goal_error': 1.0}, 'success_threshold': -1.0}}
    (folder / 'stiff.yaml').write_text(yaml.safe_dump(data))
    task = load_task(str(folder / 'stiff.yaml'))
    arm = ArmModel(task)
    arm.reset(task.tau_default)
    return passive_motion(arm)


def test_a_passive_joint_that_gives_a_little_under_the_arm_is_warned_about(tmp_path):
    """The mount gives less than a swing worth a warning, but it moves the hand by more than
    a millimetre."""
    motion = stiff_base_task(tmp_path, {'finger': 0.4})
    assert motion.moved['mount'] < PASSIVE_SWING_WARNING
    assert motion.hand_by_passive > 0.002 and motion.carry_hand == ('mount',)
    assert passive_warning(motion).endswith('robot.locked_joints: {mount: 0}')


def test_the_lock_offered_lies_inside_the_joint_range(tmp_path):
    """The finger starts at its reference angle 0, outside its range [0.2, 0.6] (MuJoCo's
    limit pushes it in): the lock offered is 0.2, which robot.locked_joints accepts."""
    motion = stiff_base_task(tmp_path, {'mount': 0.0})
    assert motion.moved['finger'] > PASSIVE_SWING_WARNING
    assert motion.start == {'finger': 0.2}
    assert passive_warning(motion).endswith('robot.locked_joints: {finger: 0.2}')
