"""What the reward and the simulation take of a robot's geometry as it comes: the geoms that
collide, not the visual meshes (psl_task.model_spec.robot_geoms); the robot's parts in
contact with themselves at rest, named and excluded (contacts_at_rest); and what psl check says
of both (psl_optimizer.robot_check)."""
import dataclasses
import textwrap

import numpy as np
import pytest
import yaml

from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.robot_check import (GEOMETRY_WARNING, check_robot, format_report,
                                       geometry_warning)
from psl_task.arm_model import ArmModel
from psl_task.model_spec import robot_contacts_at_rest
from psl_task.task import TaskError, load_task

# two links, each with a collision capsule (group 0), a visual capsule (group 1, no contacts,
# as robosuite and MuJoCo's URDF import write them) and, on the second, a contact-free group-0
# geom (the robot's shape in a model that turns contacts off, as gymnasium's pusher does)
MJCF = """
<mujoco model="dressed_arm">
  <compiler angle="radian"/>
  <option timestep="0.002" gravity="0 0 0"/>
  <worldbody>
    <body name="upper">
      <joint name="shoulder" type="hinge" axis="0 -1 0" range="-3 3" damping="0.1"/>
      <geom name="upper_collision" type="capsule" fromto="0 0 0 0.5 0 0" size="0.03" mass="1"/>
      <geom name="upper_visual" type="capsule" fromto="0 0 0 0.5 0 0" size="0.035" mass="0"
            contype="0" conaffinity="0" group="1"/>
      <body name="fore" pos="0.5 0 0">
        <joint name="elbow" type="hinge" axis="0 -1 0" range="-3 3" damping="0.1"/>
        <geom name="fore_collision" type="capsule" fromto="0 0 0 0.4 0 0" size="0.03"
              mass="0.5"/>
        <geom name="fore_visual" type="capsule" fromto="0 0 0 0.4 0 0" size="0.035" mass="0"
              contype="0" conaffinity="0" group="2"/>
        <geom name="fore_shape" type="sphere" pos="0.4 0 0" size="0.04" mass="0"
              contype="0" conaffinity="0"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="shoulder" ctrlrange="-30 30"/>
    <motor joint="elbow" ctrlrange="-20 20"/>
  </actuator>
</mujoco>
"""

TASK = textwrap.dedent("""
    name: dressed_arm_reach
    robot:
      model: dressed_arm.xml
      end_effector: {body: fore, offset: [0.4, 0.0, 0.0]}
    scene:
      - {name: pillar, type: capsule, size: [0.04, 0.15], position: [0.6, 0.0, 0.15]}
    control_rate: 500.0
    duration: 1.0
    settle_time: 0.2
    start_posture: [1.2, -1.0]
    goal_posture: [0.3, -0.6]
    task_parameters:
      - {name: pillar_x, low: 0.5, high: 0.8,
         binds: {kind: mocap_position, body: pillar, axis: 0}}
    controller: {kp: [100.0, 60.0], kd: [8.0, 5.0]}
    policy: {kind: dmp, n_basis: 5}
    demonstration: {times: [0.0, 1.0], positions: [[1.2, -1.0], [0.3, -0.6]]}
    reward:
      weights: {goal_error: 1.0, penetration: 10.0}
      success_threshold: -0.05
      obstacle_geoms: [pillar]
""")

# TALOS's left arm from its ROS URDF (example-robot-data, unmodified): collision meshes of
# its shoulder and its base, and of links 5 and 7, overlap at every posture
TALOS = textwrap.dedent("""
    name: talos_left_arm_reach
    robot:
      model: package://example-robot-data/robots/talos_data/robots/talos_left_arm.urdf
      end_effector: {body: arm_left_7_link, offset: [0.0, 0.0, -0.1]}
      joints: [arm_left_2_joint, arm_left_3_joint, arm_left_4_joint, arm_left_5_joint,
               arm_left_6_joint, arm_left_7_joint]
      gravity_compensation: true
    control_rate: 500.0
    duration: 2.0
    settle_time: 0.5
    start_posture: [0.3, 0.0, -1.2, 0.0, 0.0, 0.0]
    goal_posture: [0.8, 0.3, -0.8, 0.0, 0.0, 0.0]
    task_parameters:
      - {name: duration, low: 1.8, high: 2.2, binds: {kind: duration}}
    controller:
      kp: [100.0, 60.0, 60.0, 10.0, 10.0, 10.0]
      kd: [10.0, 6.0, 6.0, 1.0, 1.0, 1.0]
    policy: {n_basis: 5}
    demonstration:
      times: [0.0, 2.0]
      positions: [[0.3, 0.0, -1.2, 0.0, 0.0, 0.0], [0.8, 0.3, -0.8, 0.0, 0.0, 0.0]]
    reward:
      weights: {goal_error: 1.0, smoothness: 0.001}
      success_threshold: -0.05
""")


def write(folder, text: str, **robot) -> str:
    data = yaml.safe_load(text)
    data['robot'].update(robot)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f'{data["name"]}.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.fixture
def dressed(tmp_path):
    (tmp_path / 'dressed_arm.xml').write_text(MJCF)
    return load_task(write(tmp_path, TASK))


def test_the_reward_measures_what_collides_not_what_is_seen(dressed):
    arm = ArmModel(dressed)
    assert arm.arm_geoms == ('upper_collision', 'fore_collision', 'fore_shape')
    report = check_robot(dressed)
    assert report.arm_geoms == list(arm.arm_geoms)
    assert set(report.pair_seconds) == {f'{g} / pillar' for g in arm.arm_geoms}
    assert all(t > 0.0 for t in report.pair_seconds.values()) and report.step_seconds > 0.0
    assert "the reward's 3 distances per physics step" in format_report(report)


def test_a_session_dominated_by_its_geometry_is_warned_of():
    step = 1e-5
    cheap = {'a / o': 1e-6, 'b / o': 2e-6}
    costly = {'a / o': 1e-6, 'mesh_3 / o': GEOMETRY_WARNING * step, 'mesh_9 / o': 2e-4}
    assert geometry_warning(step, cheap) == ''
    assert geometry_warning(step, {}) == ''
    words = geometry_warning(step, costly)
    assert 'mesh_9 / o 200 us, mesh_3 / o 50 us, a / o 1 us' in words
    assert words.startswith("the reward's geometry: 3 distances cost 251 us per physics step")


def _rms_acceleration(task) -> tuple[float, object]:
    batch = BatchRollouts(task)
    result = batch.run(batch.policy.default_theta[None], task.tau_default)[0]
    qdd = np.diff(result.q, 2, axis=0) / task.control_period ** 2
    return float(np.sqrt(np.mean(qdd ** 2))), result.evaluation


def test_a_robot_in_contact_with_itself_at_rest_is_named_and_moves_smoothly(tmp_path):
    task = load_task(write(tmp_path, TALOS))
    resting = {(c.body1, c.body2): c for c in robot_contacts_at_rest(task)}
    assert set(resting) == {('world', 'arm_left_2_link'), ('arm_left_5_link', 'arm_left_7_link')}
    for contact in resting.values():
        assert contact.postures == ('start', 'goal') and 0.03 < contact.depth < 0.08
    report = check_robot(task)
    assert report.contacts_excluded and not report.warnings
    assert 'arm_left_5_link / arm_left_7_link 4.' in format_report(report)
    smooth, evaluation = _rms_acceleration(task)
    kept = load_task(write(tmp_path / 'kept', TALOS, contacts_at_rest='keep'))
    chattering, _ = _rms_acceleration(kept)
    # measured: 0.25 rad/s^2 against about 1,000 with the contacts kept
    assert smooth < 5.0 and chattering > 100.0 * smooth, (smooth, chattering)
    assert evaluation.fulfilled
    warned = check_robot(kept).warnings
    assert any('in contact with itself at rest' in w for w in warned), warned


def test_excluded_contacts_name_bodies_the_model_has(dressed):
    mine = dataclasses.replace(dressed, exclude_contacts=(('upper', 'elbow_link'),))
    with pytest.raises(TaskError, match="exclude_contacts names the body 'elbow_link'"):
        ArmModel(mine)
    assert ArmModel(dataclasses.replace(dressed, exclude_contacts=(('upper', 'fore'),))) \
        .model.nexclude == 1
