"""A robot as it comes: an MJCF with no end-effector site and no obstacle, completed by the
task YAML (robot.end_effector on a body, a scene object bound by a task parameter, the arm's
geoms found by psl). The model is written by the test; positions are checked against closed-form
kinematics of the two links."""
import textwrap

import mujoco
import numpy as np
import pytest
import yaml

from psl_task.arm_model import ArmModel
from psl_task.model_spec import task_spec
from psl_task.reward_geometry import RewardGeometry
from psl_task.task import END_EFFECTOR_SITE, TaskError, load_task

# two links of 0.5 m and 0.4 m in the x-z plane (hinges about -y), no site, no obstacle; the
# second link's geom is unnamed (as in many published models)
MJCF = """
<mujoco model="bare_arm">
  <compiler angle="radian"/>
  <option timestep="0.002" gravity="0 0 0"/>
  <worldbody>
    <body name="upper" pos="0 0 0">
      <joint name="shoulder" type="hinge" axis="0 -1 0" range="-3 3" damping="0.1"/>
      <geom name="upper" type="capsule" fromto="0 0 0 0.5 0 0" size="0.03" mass="1"
            contype="0" conaffinity="0"/>
      <body name="fore" pos="0.5 0 0">
        <joint name="elbow" type="hinge" axis="0 -1 0" range="-3 3" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" mass="0.5"
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


def task_data() -> dict:
    return yaml.safe_load(textwrap.dedent("""
        name: bare_arm_reach
        robot:
          model: bare_arm.xml
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
        demonstration:
          times: [0.0, 1.0]
          positions: [[1.2, -1.0], [0.3, -0.6]]
        reward:
          obstacle_geoms: [pillar]
          weights: {goal_error: 10.0, penetration: 100.0}
          success_threshold: -0.2
        """))


@pytest.fixture
def folder(tmp_path):
    (tmp_path / 'bare_arm.xml').write_text(MJCF)
    return tmp_path


def write(folder, data):
    path = folder / 'bare_arm_reach.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def hand(q):
    """Closed form: the hand 0.4 m along the second link."""
    a1, a2 = q[0], q[0] + q[1]
    return np.array([0.5 * np.cos(a1) + 0.4 * np.cos(a2), 0.0,
                     0.5 * np.sin(a1) + 0.4 * np.sin(a2)])


def test_the_yaml_adds_the_end_effector_site_on_the_body(folder):
    arm = ArmModel(write(folder, task_data()))
    assert arm.task.end_effector_site == END_EFFECTOR_SITE
    for q in ([0.0, 0.0], [0.7, -1.1], [1.2, -1.0]):
        arm.data.qpos[arm.qpos_adr] = q
        mujoco.mj_forward(arm.model, arm.data)
        np.testing.assert_allclose(arm.end_effector_pose()[0], hand(q), atol=1e-12)


def test_scene_objects_are_mocap_bodies_bound_by_name_and_measured(folder):
    """The pillar moves with tau; psl finds the arm's geoms (the unnamed one too) and the
    penetration sensor sees the arm inside the pillar and not beside it."""
    task = write(folder, task_data())
    arm = ArmModel(task)
    assert len(arm.arm_geoms) == 2 and 'upper' in arm.arm_geoms
    geometry = RewardGeometry(arm)
    assert len(geometry.pairs) == 2
    arm.reset(np.array([0.55]))
    mocap = arm.model.body_mocapid[arm.model.body('pillar').id]
    np.testing.assert_array_equal(arm.data.mocap_pos[mocap], [0.55, 0.0, 0.15])
    through = np.array([[[0.0, 0.0]]])          # the upper link along x passes x = 0.55, z = 0
    clear = np.array([[[1.4, 0.0]]])            # the arm up high, far from the pillar
    assert geometry.replay(through, [[0.55]]).distance[0, 0] < 0
    assert geometry.replay(clear, [[0.55]]).distance[0, 0] > 0.1
    geom = arm.model.geom('pillar')
    assert geom.contype[0] == 0 and geom.conaffinity[0] == 0       # no contacts by default


@pytest.mark.parametrize('change, words', [
    (lambda d: d['robot']['end_effector'].update(body='nope'), "names the body 'nope'"),
    (lambda d: d['scene'].append(dict(d['scene'][0])), 'two scene objects'),
    (lambda d: d['scene'][0].update(name='upper'), 'has a body of that name already'),
    (lambda d: d['scene'][0].update(type='cone'), 'type must be one of'),
    (lambda d: d['scene'][0].update(size=[0.1]), 'size must be 2 finite numbers'),
    (lambda d: d['robot'].update(end_effector={'site': 'a', 'body': 'b'}), 'robot.end_effector is'),
    (lambda d: d.update(end_effector_site='x'), 'give the end effector once'),
])
def test_bad_robot_and_scene_keys_are_refused(folder, change, words):
    data = task_data()
    change(data)
    with pytest.raises(TaskError, match=words):
        task = write(folder, data)
        task_spec(task)
        ArmModel(task)


def test_batch_mode_scores_the_scene_object_as_the_graph_does(folder):
    """Batch mode's recorded sensors and graph mode's kinematic replay of the same joint
    angles give the same reward on the completed model; the pillar's position matters."""
    from psl_optimizer.batch_rollout import BatchRollouts
    task = write(folder, task_data())
    batch = BatchRollouts(task, n_threads=1)
    theta = batch.policy.default_theta
    taus = np.array([[0.5], [0.8]])
    results = batch.run(np.tile(theta, (2, 1)), taus)
    for tau, result in zip(taus, results):
        replayed = batch.reward.evaluate_replayed(result.q[None], result.torque[None],
                                                  result.q_ref[None], tau[None])[0]
        for name, value in result.evaluation.components.items():
            assert replayed.components[name] == pytest.approx(value, abs=1e-9)
    distances = [batch.geometry.replay(r.q[None], tau[None]).distance[0]
                 for r, tau in zip(results, taus)]
    assert not np.allclose(distances[0], distances[1])     # the pillar moved with tau
