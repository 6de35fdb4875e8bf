"""robot.locked_joints compiles as fixed joints (`psl_task.model_spec.lock_joints`): a
humanoid's arm taken from its full-body URDF (Unitree G1 of example-robot-data, as published)
is an arm — without locks its 22 other joints are passive and the body falls; with them locked
the hand holds — and a locked body sits where MuJoCo's own kinematics of the unlocked model
puts it at the locked values (an independent reference), in a URDF and in an MJCF with what
MJCF allows (degrees, Euler angles, frames, a joint's ref, slides, two joints on a body,
floating bases, static bodies fused into their parents, actuators, sensors and keyframes on
the locked joints)."""
import textwrap

import mujoco
import numpy as np
import pytest
import yaml

from psl_task.arm_model import ArmModel
from psl_task.model_spec import (driven_joints, robot_bodies, robot_contacts_at_rest,
                                 task_model, task_spec)
from psl_task.task import TaskError, load_task

G1 = 'package://example-robot-data/robots/g1_description/urdf/g1_29dof_rev_1_0.urdf'
ARM = ['left_shoulder_pitch_joint', 'left_shoulder_roll_joint', 'left_shoulder_yaw_joint',
       'left_elbow_joint', 'left_wrist_roll_joint', 'left_wrist_pitch_joint',
       'left_wrist_yaw_joint']
START = [0.3, 0.3, 0.0, 0.8, 0.0, 0.0, 0.0]
HOLD = 0.5          # s held at the start posture
ONE_DOF = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


def g1_data() -> dict:
    """The G1's left arm driven, the rest as the URDF has it; gains for a 20 rad/s bandwidth
    of each joint's own inertia at the start (the wrist's 4e-4 kg m^2 needs kd 0.015), the
    arm's weight cancelled (gravity_compensation), so that what moves is the body."""
    return yaml.safe_load(textwrap.dedent(f"""
        name: g1_left_arm
        robot:
          model: {G1}
          end_effector: {{body: left_wrist_yaw_link, offset: [0.1, 0.0, 0.0]}}
          joints: {ARM}
          gravity_compensation: true
        control_rate: 500.0
        duration: 1.0
        start_posture: {START}
        goal_posture: [0.0, 0.3, 0.0, 0.3, 0.0, 0.0, 0.0]
        task_parameters:
          - {{name: target_x, low: 0.1, high: 0.2, binds: {{kind: target_position, axis: 0}}}}
        target: {{position: [0.15, 0.2, 0.1]}}
        controller:
          kp: [70.0, 60.0, 8.0, 14.0, 0.15, 2.0, 0.7]
          kd: [7.0, 6.0, 0.8, 1.4, 0.015, 0.2, 0.07]
        policy: {{kind: dmp, n_basis: 5}}
        demonstration:
          times: [0.0, 1.0]
          positions: [{START}, [0.0, 0.3, 0.0, 0.3, 0.0, 0.0, 0.0]]
        reward:
          weights: {{goal_error: 10.0}}
          success_threshold: -0.2
        """))


def g1_joints(folder) -> list[str]:
    """Every joint of the G1 URDF as MuJoCo reads it (29 hinges)."""
    return [j.name for j in task_spec(_task_of(g1_data(), folder, 'probe')).joints]


def _task_of(data: dict, folder, name: str = 'task'):
    path = folder / f'{name}.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def hold(task) -> tuple[ArmModel, float]:
    """The arm held at its start posture by its PD law for HOLD s: the arm and the hand's
    largest distance from where it started [m]."""
    arm = ArmModel(task)
    arm.reset(task.tau_default)
    kp, kd = task.controller.kp, task.controller.kd
    start = arm.end_effector_pose()[0]
    moved = 0.0
    for _ in range(int(round(HOLD * task.control_rate))):
        arm.step(kp * (task.start_posture - arm.q) - kd * arm.data.qvel[arm.dof_adr])
        moved = max(moved, float(np.linalg.norm(arm.end_effector_pose()[0] - start)))
    return arm, moved


def locked_everything_but_the_arm(folder) -> dict:
    data = g1_data()
    data['robot']['locked_joints'] = {name: 0.0 for name in g1_joints(folder)
                                      if name not in ARM}
    return data


def test_the_g1_body_falls_without_locks_and_holds_with_them(tmp_path):
    arm, moved = hold(_task_of(g1_data(), tmp_path))
    assert len(arm.passive_joints) == 22            # the count: legs, waist, an arm
    assert moved > 0.05                             # measured: 0.205 m in 0.5 s
    data = locked_everything_but_the_arm(tmp_path)
    arm, moved = hold(_task_of(data, tmp_path, 'locked'))
    assert arm.passive_joints == [] and arm.joint_names == ARM
    assert moved < 1e-6                             # measured: 1e-17 m
    assert arm.model.njnt == 7 and arm.model.nu == 7


def _same_poses(locked: mujoco.MjModel, free: mujoco.MjModel, values: dict) -> int:
    """Compare the world poses of the bodies (by name) and of the geoms (by name, else by
    their mesh's name) of the locked model at its reference pose with those of the unlocked model at the
    locked values (MuJoCo's kinematics: the independent reference); returns how many were
    compared."""
    d_locked, d_free = mujoco.MjData(locked), mujoco.MjData(free)
    for name, value in values.items():      # a free or ball joint at 0: its reference pose
        if int(free.joint(name).type[0]) in ONE_DOF:
            d_free.qpos[free.jnt_qposadr[free.joint(name).id]] = value
    mujoco.mj_kinematics(locked, d_locked)
    mujoco.mj_kinematics(free, d_free)
    pairs = [(b, free.body(locked.body(b).name).id) for b in range(1, locked.nbody)]
    for a, b in pairs:
        np.testing.assert_allclose(d_locked.xpos[a], d_free.xpos[b], rtol=0, atol=1e-9)
        sign = np.sign(d_locked.xquat[a] @ d_free.xquat[b])          # q and -q: one turn
        np.testing.assert_allclose(d_locked.xquat[a], sign * d_free.xquat[b], rtol=0,
                                   atol=1e-9)
    def key(model, g):             # a geom by its name, else by its mesh's
        if model.geom(g).name:
            return model.geom(g).name
        return model.mesh(model.geom_dataid[g]).name if model.geom_dataid[g] >= 0 else None

    geoms = {key(free, g): g for g in range(free.ngeom)}
    count = len(pairs)
    for g in range(locked.ngeom):
        if key(locked, g) is None:
            continue
        h = geoms[key(locked, g)]
        np.testing.assert_allclose(d_locked.geom_xpos[g], d_free.geom_xpos[h], rtol=0,
                                   atol=1e-9)
        np.testing.assert_allclose(d_locked.geom_xmat[g], d_free.geom_xmat[h], rtol=0,
                                   atol=1e-9)
        count += 1
    return count


def test_a_locked_urdf_body_sits_where_mujoco_kinematics_puts_it(tmp_path):
    values = {'waist_yaw_joint': 0.3, 'waist_roll_joint': 0.2, 'waist_pitch_joint': -0.1,
              'left_knee_joint': 0.5, 'right_elbow_joint': 1.0}
    data = g1_data()
    data['robot']['locked_joints'] = values
    locked = task_model(_task_of(data, tmp_path, 'locked'))
    free = task_model(_task_of(g1_data(), tmp_path))
    assert locked.njnt == free.njnt - len(values)
    # the torso and the knee and elbow links fused into their parents (a URDF's fusestatic):
    # their meshes are compared as geoms
    assert _same_poses(locked, free, values) > 40


MJCF = """
<mujoco>
  <compiler angle="degree" fusestatic="true"/>
  <default><joint axis="0 1 0" damping="0.1"/></default>
  <worldbody>
    <body name="base" pos="0.1 0.2 1.0">
      <freejoint name="float"/>
      <geom name="g_base" type="box" size="0.1 0.1 0.1"/>
      <body name="plate" pos="0 0.05 0.02" euler="0 0 20">
      <frame pos="0 0 0.2" euler="0 30 0">
        <body name="upper" euler="10 0 90" pos="0.05 0 0">
          <joint name="yaw" axis="0 0 1" pos="0.02 0.01 0" range="-90 90" ref="10"/>
          <joint name="pitch" pos="0 0 0.03" range="-90 90"/>
          <geom name="g_upper" type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
          <body name="fore" pos="0.3 0 0" axisangle="1 1 0 20">
            <joint name="slide" type="slide" axis="1 0 0.5" range="-0.1 0.2"/>
            <geom name="g_fore" type="capsule" fromto="0 0 0 0.25 0 0" size="0.02"/>
            <body name="hand" pos="0.25 0 0">
              <joint name="wrist" pos="0.01 0 0" range="-90 90"/>
              <geom name="g_hand" type="sphere" size="0.03"/>
              <site name="tip" pos="0.05 0 0"/>
            </body>
          </body>
        </body>
      </frame>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="m_yaw" joint="yaw" ctrlrange="-5 5"/>
    <motor name="m_pitch" joint="pitch" ctrlrange="-5 5"/>
    <motor name="m_slide" joint="slide" ctrlrange="-5 5"/>
    <motor name="m_wrist" joint="wrist" ctrlrange="-5 5"/>
  </actuator>
  <sensor><jointpos joint="yaw"/><jointpos joint="wrist"/></sensor>
  <keyframe><key name="home" qpos="0.1 0.2 1.0 1 0 0 0 0.2 0.1 0.05 0.3"/></keyframe>
</mujoco>
"""


def mjcf_data(folder, locked: dict) -> dict:
    (folder / 'arm.xml').write_text(MJCF)
    return {'name': 'mjcf_locks', 'model': 'arm.xml', 'end_effector_site': 'tip',
            'robot': {'locked_joints': locked}, 'control_rate': 500.0, 'duration': 1.0,
            'start_posture': [0.0], 'goal_posture': [0.1],
            'task_parameters': [{'name': 'x', 'low': 0.0, 'high': 1.0,
                                 'binds': {'kind': 'target_position', 'axis': 0}}],
            'target': {'position': [0.0, 0.0, 0.0]},
            'controller': {'kp': [10.0], 'kd': [1.0]}, 'policy': {'n_basis': 3},
            'demonstration': {'times': [0.0, 1.0], 'positions': [[0.0], [0.1]]},
            'reward': {'weights': {'goal_error': 1.0}, 'success_threshold': -1.0}}


def test_mjcf_locks_compose_as_mujoco_kinematics_does(tmp_path):
    values = {'float': 0.0, 'yaw': 0.7, 'pitch': -0.4, 'slide': 0.15}
    task = _task_of(mjcf_data(tmp_path, values), tmp_path)
    spec = task_spec(task)
    assert driven_joints(task, spec) == ['wrist']     # the locked joints' motors went too
    locked = spec.compile()
    assert locked.nu == 1 and locked.nsensor == 1 and locked.nq == 1
    np.testing.assert_array_equal(locked.key_qpos[0], [0.3])     # the wrist's entry kept
    free = mujoco.MjModel.from_xml_path(str(tmp_path / 'arm.xml'))
    # base, upper and fore fused into the world (fusestatic) with the plate: the hand and
    # the four geoms
    assert _same_poses(locked, free, values) == 5
    assert locked.nbody == 2
    arm = ArmModel(task)                                # the arm model takes it as it is
    assert arm.joint_names == ['wrist'] and arm.passive_joints == []


def test_locking_the_first_joint_of_a_body_leaves_the_second_free(tmp_path):
    values = {'yaw': -0.5}
    data = mjcf_data(tmp_path, values)
    data['robot']['joints'] = ['pitch']
    task = _task_of(data, tmp_path)
    locked = task_model(task)
    free = mujoco.MjModel.from_xml_path(str(tmp_path / 'arm.xml'))
    for pitch in (0.0, 0.6):        # the pitch joint still turns about its own axis
        d_locked, d_free = mujoco.MjData(locked), mujoco.MjData(free)
        d_locked.qpos[locked.jnt_qposadr[locked.joint('pitch').id]] = pitch
        d_free.qpos[free.jnt_qposadr[free.joint('pitch').id]] = pitch
        d_free.qpos[free.jnt_qposadr[free.joint('yaw').id]] = values['yaw']
        mujoco.mj_kinematics(locked, d_locked)
        mujoco.mj_kinematics(free, d_free)
        for body in ('upper', 'fore', 'hand'):
            np.testing.assert_allclose(d_locked.xpos[locked.body(body).id],
                                       d_free.xpos[free.body(body).id], rtol=0, atol=1e-9)


@pytest.mark.parametrize('locked, joints, words', [
    ({'elbow': 0.1}, [], "robot.locked_joints names 'elbow'; arm.xml has the joints float, "
                         'yaw, pitch, slide, wrist'),
    ({'yaw': 2.0}, [], r"robot.locked_joints: 'yaw' at 2 is outside its range \[-1.5708, "
                       r'1.5708\]'),
    ({'slide': -0.2}, [], r"'slide' at -0.2 is outside its range \[-0.1, 0.2\]"),
    ({'float': 0.1}, [], "'float' is a free joint, which locks at 0 only"),
    ({'pitch': 0.1}, [], "robot.locked_joints: the body 'upper' moves with yaw, pitch in this "
                         "order; 'yaw' stays free before a locked one"),
    ({'wrist': 0.1}, ['wrist'], "robot.locked_joints locks 'wrist', which robot.joints drives"),
    ({'yaw': float('nan')}, [], 'robot.locked_joints.yaw must be finite'),
    ({'yaw': float('inf')}, [], 'robot.locked_joints.yaw must be finite'),
])
def test_a_lock_that_cannot_be_is_refused_naming_the_key(tmp_path, locked, joints, words):
    data = mjcf_data(tmp_path, locked)
    if joints:
        data['robot']['joints'] = joints
    with pytest.raises(TaskError, match=words) as error:
        task_model(_task_of(data, tmp_path))
    assert '\n' not in str(error.value)


def test_the_locked_g1_arm_is_the_robot_of_every_part_of_psl(tmp_path):
    """robot_bodies are the arm's alone (the locked body is fused into the world: a URDF's
    fusestatic), and no part of it rests in contact with another."""
    task = _task_of(locked_everything_but_the_arm(tmp_path), tmp_path)
    arm = ArmModel(task)
    m = arm.model
    moved = robot_bodies(m, arm.joint_ids)
    assert [m.body(b).name for b in np.flatnonzero(moved)] == [
        name.replace('_joint', '_link') for name in ARM]
    assert np.count_nonzero(moved[m.geom_bodyid]) == 7      # a collision mesh per link
    assert np.count_nonzero(m.geom_bodyid == 0) > 10       # the body's meshes, in the world
    assert robot_contacts_at_rest(task) == ()
