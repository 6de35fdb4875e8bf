"""A ROS robot as it comes: a URDF with ``package://`` STL meshes (written by the test: a
two-link arm, its collision meshes binary STL boxes, a COLLADA visual mesh MuJoCo cannot read,
a Gazebo tag) loaded through the task YAML, driven by motors psl adds with the URDF's effort
limits, rolled out in batch mode and learned for a few tasks."""
import struct
import textwrap

import mujoco
import numpy as np
import pytest
import yaml

from psl_task.arm_model import ArmModel
from psl_task.task import TaskError, load_task

LINKS = (('upper', 0.5), ('fore', 0.4))        # name, length [m]
EFFORT = {'shoulder': 30.0, 'elbow': 20.0}      # N m, the URDF's effort limits


def box_stl(path, size):
    """A binary STL of a box of the given extents (x, y, z), from its corner at the origin."""
    x, y, z = size
    v = np.array([[i * x, j * y, k * z] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
             (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    with open(path, 'wb') as f:
        f.write(b'\0' * 80 + struct.pack('<I', len(faces)))
        for a, b, c in faces:
            normal = np.cross(v[b] - v[a], v[c] - v[a])
            normal /= np.linalg.norm(normal)
            f.write(struct.pack('<12fH', *normal, *v[a], *v[b], *v[c], 0))


def urdf(package: str) -> str:
    links = ''.join(textwrap.dedent(f"""
        <link name="{name}">
          <inertial><origin xyz="{length / 2} 0 0"/><mass value="{1.0 / (i + 1)}"/>
            <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.02"/></inertial>
          <visual><geometry><mesh filename="package://{package}/meshes/{name}.dae"/></geometry></visual>
          <collision><origin xyz="0 -0.02 -0.02"/>
            <geometry><mesh filename="package://{package}/meshes/{name}.stl"/></geometry></collision>
        </link>""") for i, (name, length) in enumerate(LINKS))
    return f"""<?xml version="1.0"?>
<robot name="urdf_arm">
  <link name="base"/>
  {links}
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/>
    <axis xyz="0 -1 0"/><limit lower="-3" upper="3" effort="{EFFORT['shoulder']}" velocity="3"/>
    <dynamics damping="0.1"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/>
    <origin xyz="{LINKS[0][1]} 0 0"/><axis xyz="0 -1 0"/>
    <limit lower="-3" upper="3" effort="{EFFORT['elbow']}" velocity="3"/>
    <dynamics damping="0.1"/></joint>
  <gazebo reference="upper"><material>Gazebo/Blue</material></gazebo>
</robot>
"""


def task_data() -> dict:
    return yaml.safe_load(textwrap.dedent("""
        name: urdf_arm_reach
        robot:
          model: description/urdf/arm.urdf
          package_paths: {urdf_arm_description: description}
          end_effector: {body: fore, offset: [0.4, 0.0, 0.0]}
        scene:
          - {name: pillar, type: capsule, size: [0.04, 0.15], position: [0.6, 0.0, 0.15]}
        control_rate: 500.0
        duration: 1.0
        settle_time: 0.3
        start_posture: [1.2, -1.0]
        goal_posture: [0.3, -0.6]
        task_parameters:
          - {name: pillar_x, low: 0.5, high: 0.8,
             binds: {kind: mocap_position, body: pillar, axis: 0}}
        controller: {kp: [150.0, 80.0], kd: [10.0, 5.0]}
        policy: {kind: dmp, n_basis: 5, feedforward: true}
        demonstration:
          times: [0.0, 1.0]
          positions: [[1.2, -1.0], [0.3, -0.6]]
        reward:
          obstacle_geoms: [pillar]
          weights: {goal_error: 10.0, penetration: 100.0, tracking_error: 1.0}
          success_threshold: -0.3
        """))


@pytest.fixture
def folder(tmp_path):
    meshes = tmp_path / 'description' / 'meshes'
    meshes.mkdir(parents=True)
    (tmp_path / 'description' / 'urdf').mkdir()
    for name, length in LINKS:
        box_stl(meshes / f'{name}.stl', (length, 0.04, 0.04))
        (meshes / f'{name}.dae').write_text('<COLLADA/>')         # MuJoCo cannot read these
    (tmp_path / 'description' / 'urdf' / 'arm.urdf').write_text(urdf('urdf_arm_description'))
    return tmp_path


def write(folder, data):
    path = folder / 'urdf_arm_reach.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def test_the_urdf_loads_with_its_meshes_and_added_motors(folder):
    arm = ArmModel(write(folder, task_data()))
    m = arm.model
    assert arm.joint_names == ['shoulder', 'elbow']
    np.testing.assert_array_equal(arm.torque_high, [EFFORT['shoulder'], EFFORT['elbow']])
    assert m.nmesh == 2 and all(m.mesh_vertnum[i] == 8 for i in range(m.nmesh))   # the STLs
    assert m.opt.timestep == pytest.approx(1 / 500.0)
    assert m.opt.gravity[2] == pytest.approx(-9.81)
    assert len(arm.arm_geoms) == 2                # the collision meshes, named by psl
    arm.data.qpos[arm.qpos_adr] = [0.0, 0.0]
    mujoco.mj_forward(m, arm.data)
    np.testing.assert_allclose(arm.end_effector_pose()[0], [0.9, 0.0, 0.0], atol=1e-12)


def test_the_urdf_robot_rolls_out_and_learns(folder, tmp_path):
    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_optimizer.learning import Learner, LearnSettings
    from psl_optimizer.policy_search import SearchSettings
    task = write(folder, task_data())
    batch = BatchRollouts(task, n_threads=1)
    result = batch.run(batch.policy.default_theta[None], task.tau_default)[0]
    assert np.all(np.isfinite(result.q)) and np.isfinite(result.evaluation.reward)
    metrics = Learner(task, LearnSettings(strategy='bootstrap', num_tasks=3, num_test=3,
                                          search=SearchSettings(max_rollouts=60)),
                      tmp_path / 'run', batch).run()
    assert len(metrics.tasks) == 3 and metrics.summary is not None


@pytest.mark.parametrize('change, words', [
    (lambda d: d['robot'].update(package_paths={}), "package 'urdf_arm_description' is nowhere: give robot.package_paths"),
    (lambda d: d['robot'].update(package_paths={'urdf_arm_description': 'elsewhere'}),
     'is not a file'),
])
def test_a_mesh_that_cannot_be_found_names_the_fix(folder, change, words, monkeypatch):
    monkeypatch.delenv('ROS_PACKAGE_PATH', raising=False)
    monkeypatch.setenv('AMENT_PREFIX_PATH', '')
    data = task_data()
    change(data)
    with pytest.raises(TaskError, match=words):
        ArmModel(write(folder, data))


def test_the_ros_package_path_finds_the_package(folder, monkeypatch):
    (folder / 'description').rename(folder / 'urdf_arm_description')
    data = task_data()
    data['robot'].update(model='urdf_arm_description/urdf/arm.urdf', package_paths={})
    monkeypatch.setenv('ROS_PACKAGE_PATH', str(folder))
    assert ArmModel(write(folder, data)).model.nmesh == 2
