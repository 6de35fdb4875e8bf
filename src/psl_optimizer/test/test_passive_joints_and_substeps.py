"""Robots with joints psl does not drive, and control periods longer than a physics step.

The models are written by the test: a two-link arm whose forearm carries a passive pendulum,
with a finger on a position servo and a box that slides freely on the floor. Batch mode is
checked against the graph's own stepping code (`ArmModel.step` with the law of each control
period, what the simulator and the controller node run) and the held command against a
closed-form recurrence of a sliding mass.
"""
import textwrap

import numpy as np
import pytest
import yaml

from psl_controller.pd_law import law_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.robot_check import check_robot, format_report
from psl_task.arm_model import ArmModel
from psl_task.task import TaskError, load_task

MJCF = """
<mujoco model="arm_with_passive_parts">
  <compiler angle="radian"/>
  <option timestep="{timestep}" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="upper">
      <joint name="shoulder" type="hinge" axis="0 -1 0" range="-3 3" damping="0.2"/>
      <geom name="upper" type="capsule" fromto="0 0 0 0.5 0 0" size="0.03" mass="1"
            contype="0" conaffinity="0"/>
      <body name="fore" pos="0.5 0 0">
        <joint name="elbow" type="hinge" axis="0 -1 0" range="-3 3" damping="0.2"/>
        <geom name="fore" type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" mass="0.5"
              contype="0" conaffinity="0"/>
        <body name="finger" pos="0.4 0 0">
          <joint name="finger" type="slide" axis="1 0 0" range="0 0.05"/>
          <geom name="finger" type="box" size="0.01 0.01 0.01" mass="0.05"
                contype="0" conaffinity="0"/>
        </body>
        <body name="pendulum" pos="0.2 0 0">
          <joint name="swing" type="hinge" axis="0 -1 0" damping="0.01"/>
          <geom name="bob" type="capsule" fromto="0 0 0 0 0 -0.15" size="0.01" mass="0.2"
                contype="0" conaffinity="0"/>
        </body>
      </body>
    </body>
    <body name="box" pos="1 0.5 0">
      <joint name="box_x" type="slide" axis="1 0 0"/>
      <joint name="box_y" type="slide" axis="0 1 0"/>
      <geom name="box" type="box" size="0.05 0.05 0.05" mass="0.3" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="shoulder" ctrlrange="-40 40"/>
    <motor joint="elbow" ctrlrange="-25 25"/>
    <position joint="finger" kp="50" ctrlrange="0 0.05"/>
  </actuator>
</mujoco>
"""


def task_data(joints=('shoulder', 'elbow'), control_rate=500.0) -> dict:
    data = yaml.safe_load(textwrap.dedent("""
        name: passive_arm
        robot:
          model: arm.xml
          end_effector: {body: fore, offset: [0.4, 0.0, 0.0]}
        scene:
          - {name: post, type: box, size: [0.03, 0.03, 0.2], position: [0.6, 0.0, 0.0]}
        duration: 0.6
        settle_time: 0.2
        start_posture: [0.9, -0.8]
        goal_posture: [0.2, -0.4]
        task_parameters:
          - {name: post_x, low: 0.5, high: 0.8, binds: {kind: mocap_position, body: post, axis: 0}}
        controller: {kp: [200.0, 100.0], kd: [10.0, 5.0]}
        policy: {kind: dmp, n_basis: 4}
        demonstration:
          times: [0.0, 0.6]
          positions: [[0.9, -0.8], [0.2, -0.4]]
        reward:
          obstacle_geoms: [post]
          weights: {goal_error: 10.0, penetration: 100.0, tracking_error: 1.0}
          success_threshold: -0.2
        """))
    data['control_rate'] = control_rate
    order = list(joints)
    if order != ['shoulder', 'elbow']:          # postures, gains and rows follow robot.joints
        index = [['shoulder', 'elbow'].index(j) for j in order]
        for key in ('start_posture', 'goal_posture'):
            data[key] = [data[key][i] for i in index]
        for key in ('kp', 'kd'):
            data['controller'][key] = [data['controller'][key][i] for i in index]
        data['demonstration']['positions'] = [[row[i] for i in index]
                                              for row in data['demonstration']['positions']]
    data['robot']['joints'] = order
    return data


def write(folder, data, timestep=0.002, name='passive_arm.yaml'):
    (folder / 'arm.xml').write_text(MJCF.format(timestep=timestep))
    path = folder / name
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def graph_steps(task, theta, tau):
    """What the graph runs: the simulator's ArmModel.step with the controller's law of each
    control period (the state of the period's start), qpos of every joint recorded."""
    arm, law = ArmModel(task), law_for(task)
    reference = BatchRollouts(task).policy.reference(theta, tau)
    arm.reset(tau)
    q, qpos = [], []
    for k in range(task.num_steps_of(tau) + 1):
        q.append(arm.q)
        qpos.append(arm.data.qpos.copy())
        arm.step(law.torque(arm.q, arm.qd, reference.q[k], reference.qd[k],
                            reference.u_ffwd[k]))
    return np.array(q), np.array(qpos)


def perturbed_theta(batch, seed=0):
    rng = np.random.default_rng(seed)
    theta = batch.policy.default_theta
    return theta + rng.normal(0.0, 0.05 * np.abs(theta).max(), theta.size)


def test_joints_without_a_driven_motor_stay_passive(tmp_path):
    task = write(tmp_path, task_data())
    arm = ArmModel(task)
    assert arm.joint_names == ['shoulder', 'elbow']
    assert arm.passive_joints == ['finger', 'swing', 'box_x', 'box_y']
    assert arm.model.nu == 2             # the finger's servo is gone: robot.joints leaves it out
    assert arm.model.nq == 6
    # the reward's arm geoms: the bodies the driven joints move (the pendulum hangs from the
    # forearm), not the box that slides on its own
    assert set(arm.arm_geoms) == {'upper', 'fore', 'finger', 'bob'}
    report = format_report(check_robot(task))
    assert 'passive joints (no motor, move freely): finger, swing, box_x, box_y' in report


def test_a_passive_pendulum_swings_alike_in_batch_mode_and_in_the_graphs_stepping(tmp_path):
    task = write(tmp_path, task_data())
    batch = BatchRollouts(task)
    theta, tau = perturbed_theta(batch), task.tau_default
    q_graph, qpos = graph_steps(task, theta, tau)
    result = batch.run(theta[None], tau)[0]
    np.testing.assert_allclose(result.q, q_graph, rtol=0, atol=1e-12)
    swing = ArmModel(task).model.joint('swing').qposadr[0]
    assert np.ptp(qpos[:, swing]) > 0.01       # the arm's motion swings the pendulum


def test_the_driven_joints_may_come_in_any_order(tmp_path):
    """robot.joints reversed (postures, gains and demonstration rows with it): the same
    physical motion, every command in the new order."""
    forward = write(tmp_path, task_data(), name='forward.yaml')
    reverse = write(tmp_path, task_data(joints=('elbow', 'shoulder')), name='reverse.yaml')
    assert ArmModel(reverse).joint_names == ['elbow', 'shoulder']
    a, b = BatchRollouts(forward), BatchRollouts(reverse)
    ra = a.run(a.policy.default_theta[None], forward.tau_default)[0]
    rb = b.run(b.policy.default_theta[None], reverse.tau_default)[0]
    np.testing.assert_allclose(rb.q, ra.q[:, ::-1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(rb.torque, ra.torque[:, ::-1], rtol=0, atol=1e-9)
    assert rb.evaluation.reward == pytest.approx(ra.evaluation.reward, abs=1e-12)
    q_graph, _ = graph_steps(reverse, b.policy.default_theta, reverse.tau_default)
    np.testing.assert_allclose(rb.q, q_graph, rtol=0, atol=1e-12)


@pytest.mark.parametrize('joints, words', [
    (('shoulder', 'wrist'), "robot.joints names 'wrist'; arm.xml has the joints shoulder, elbow"),
    (('shoulder', 'shoulder'), 'names a joint twice'),
])
def test_bad_driven_joints_are_named(tmp_path, joints, words):
    data = task_data()
    data['robot']['joints'] = list(joints)
    with pytest.raises(TaskError, match=words):
        ArmModel(write(tmp_path, data))


def driving_one_more(data: dict, joint: str) -> dict:
    """The task data with `joint` driven too: one more entry in postures, gains and rows."""
    data['robot']['joints'] = data['robot']['joints'] + [joint]
    for key in ('start_posture', 'goal_posture'):
        data[key] = data[key] + [0.0]
    for key in ('kp', 'kd'):
        data['controller'][key] = data['controller'][key] + [1.0]
    data['demonstration']['positions'] = [r + [0.0] for r in data['demonstration']['positions']]
    return data


def test_a_ball_joint_cannot_be_driven(tmp_path):
    data = driving_one_more(task_data(), 'ball')
    (tmp_path / 'arm.xml').write_text(MJCF.format(timestep=0.002).replace(
        '<joint name="swing" type="hinge" axis="0 -1 0" damping="0.01"/>',
        '<joint name="ball" type="ball"/>'))
    path = tmp_path / 'ball.yaml'
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(TaskError, match="'ball', a ball joint: psl drives hinge and slide"):
        ArmModel(load_task(str(path)))


def test_a_servo_on_a_driven_joint_is_named_by_its_joint(tmp_path):
    data = driving_one_more(task_data(), 'finger')
    with pytest.raises(TaskError, match="on joint finger.*not plain joint motors"):
        ArmModel(write(tmp_path, data))


# -- substeps -------------------------------------------------------------------------------
@pytest.mark.parametrize('rate, substeps', [(500.0, 1), (250.0, 2), (100.0, 5)])
def test_the_command_is_held_over_whole_physics_steps(tmp_path, rate, substeps):
    task = write(tmp_path, task_data(control_rate=rate))
    arm = ArmModel(task)
    assert arm.n_substeps == substeps
    assert task.num_steps == round(0.8 * rate)
    batch = BatchRollouts(task)
    theta, tau = perturbed_theta(batch, seed=3), task.tau_low
    result = batch.run(theta[None], tau)[0]
    q_graph, _ = graph_steps(task, theta, tau)
    np.testing.assert_allclose(result.q, q_graph, rtol=0, atol=1e-12)
    assert np.isfinite(result.evaluation.reward)


@pytest.mark.parametrize('rate', [300.0, 1000.0, 0.0001 + 250.0])
def test_a_control_rate_that_does_not_divide_the_physics_rate_is_refused(tmp_path, rate):
    with pytest.raises(TaskError, match='must divide the physics rate 1 / timestep = 500 Hz'):
        ArmModel(write(tmp_path, task_data(control_rate=rate)))


SLIDER = """
<mujoco model="slider">
  <option timestep="0.001" gravity="0 0 0" integrator="Euler"/>
  <worldbody>
    <body name="cart">
      <joint name="x" type="slide" axis="1 0 0"/>
      <geom name="cart" type="box" size="0.05 0.05 0.05" mass="2" contype="0" conaffinity="0"/>
      <site name="tip"/>
    </body>
  </worldbody>
  <actuator><motor joint="x" ctrlrange="-100 100"/></actuator>
</mujoco>
"""


def test_a_held_command_moves_a_mass_as_the_closed_form_recurrence(tmp_path):
    """A 2 kg cart under PD at 100 Hz on 1 kHz physics (semi-implicit Euler): the force of
    each control period is u_k = kp (r_k - x_k) + kd (rd_k - v_k) + 0, held for 10 steps of
    v += u / m dt, x += v dt. An in-actuator PD would update u every step and differ."""
    (tmp_path / 'slider.xml').write_text(SLIDER)
    data = {
        'name': 'slider', 'model': 'slider.xml', 'end_effector_site': 'tip',
        'control_rate': 100.0, 'duration': 0.5, 'settle_time': 0.1,
        'start_posture': [0.0], 'goal_posture': [0.3],
        'task_parameters': [{'name': 'unused', 'low': 0.0, 'high': 1.0,
                             'binds': {'kind': 'duration', 'offset': 0.5}}],
        'controller': {'kp': [400.0], 'kd': [20.0]},
        'policy': {'kind': 'dmp', 'n_basis': 3},
        'demonstration': {'times': [0.0, 0.5], 'positions': [[0.0], [0.3]]},
        'reward': {'weights': {'tracking_error': 1.0}, 'success_threshold': -1.0}}
    path = tmp_path / 'slider.yaml'
    path.write_text(yaml.safe_dump(data))
    task = load_task(str(path))
    batch = BatchRollouts(task)
    tau = np.array([0.0])
    result = batch.run(batch.policy.default_theta[None], tau)[0]
    reference = batch.policy.reference(batch.policy.default_theta, tau)

    def recurrence(physics_steps_per_update):
        x = v = 0.0
        trajectory = []
        for k in range(len(result.q)):
            trajectory.append(x)
            for step in range(10):
                if step % physics_steps_per_update == 0:
                    u = float(np.clip(400.0 * (reference.q[k, 0] - x)
                                      + 20.0 * (reference.qd[k, 0] - v), -100.0, 100.0))
                v += u / 2.0 * 0.001
                x += v * 0.001
        return np.array(trajectory)

    np.testing.assert_allclose(result.q[:, 0], recurrence(10), rtol=0, atol=1e-12)
    # the law evaluated on every physics step (what an in-actuator PD does) ends elsewhere
    assert np.abs(result.q[:, 0] - recurrence(1)).max() > 1e-4


@pytest.mark.parametrize('control_rate', [500.0, 250.0])     # one physics step; two, held
def test_batch_mode_gives_every_joint_as_the_graph_steps_it(tmp_path, control_rate):
    """RolloutResult.qpos (what psl render draws): the whole model's qpos, passive joints
    too, state for state as the graph's stepping leaves them."""
    task = write(tmp_path, task_data(control_rate=control_rate))
    batch = BatchRollouts(task)
    theta, tau = perturbed_theta(batch), task.tau_default
    _, qpos = graph_steps(task, theta, tau)
    result = batch.run(theta[None], tau)[0]
    assert result.qpos.shape == qpos.shape == (task.num_steps_of(tau) + 1, 6)
    np.testing.assert_allclose(result.qpos, qpos, rtol=0, atol=1e-12)
