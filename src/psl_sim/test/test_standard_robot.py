"""The standard robot without ROS (`psl_sim.standard_robot`): its trajectory controller on the
measured state, latency, noise, model error, joint order, its own gains, placing a task
instance, and the parameters' checks. References are computed here from the MuJoCo model by
joint name, not through the robot's own index tables, and the law from the task's gains."""
import dataclasses

import numpy as np
import pytest
from scipy import stats

from psl_controller.trajectory_controller import Goal, Tolerances, hold_at
from psl_sim.standard_robot import StandardRobot
from psl_sim.standard_robot_parameters import StandardRobotParameters
from psl_task.arm_model import ArmModel
from psl_task.task import load_task

TASK = 'reach_over_obstacle'        # joints joint1..joint3, 500 Hz, limits +-40 N m
P_FAIL = 1e-6                       # two-sided probability of a statistical bound failing


def robot(**kwargs) -> StandardRobot:
    return StandardRobot(StandardRobotParameters(task=kwargs.pop('task', TASK), **kwargs))


def by_name(r: StandardRobot, what: str) -> dict[str, float]:
    """Joint name -> qpos / qvel / ctrl of the robot's MuJoCo data, read by name."""
    m, d = r.arm.model, r.arm.data
    out = {}
    for name in r.arm.joint_names:
        joint = m.joint(name)
        if what == 'ctrl':
            actuator = [a for a in range(m.nu) if m.actuator_trnid[a, 0] == joint.id][0]
            out[name] = float(d.ctrl[actuator])
        elif what == 'qpos':
            out[name] = float(d.qpos[joint.qposadr[0]])
        else:
            out[name] = float(d.qvel[joint.dofadr[0]])
    return out


def hold(r: StandardRobot, q) -> None:
    """A goal for the robot's controller: hold the position q (task order) from now on."""
    r.controller.submit(Goal('hold', hold_at(np.asarray(q, dtype=float)), 0,
                             Tolerances.none(len(q))))


@pytest.mark.parametrize('latency', [0, 1, 3])
def test_the_controllers_torque_is_applied_exactly_latency_periods_later(latency):
    r = robot(latency_periods=latency)
    start = load_task(TASK).start_posture
    hold(r, start + [0.1, -0.2, 0.05])              # away from where the arm is: a torque
    computed, applied = [], []
    for _ in range(latency + 6):
        state, _ = r.step()
        computed.append(r.controller.last.torque.copy())
        applied.append(r.applied.copy())
    for k, torque in enumerate(applied):
        expected = computed[k - latency] if k >= latency else np.zeros(3)
        np.testing.assert_array_equal(torque, expected, err_msg=f'step {k}')
    assert np.any(computed[0])


def test_the_controller_acts_on_the_measured_state_with_the_robots_gains():
    """The torque is the law on the noisy measurement (not the exact state), with the gains
    given to the robot (not the task's)."""
    kp, kd = [50.0, 40.0, 30.0], [2.0, 3.0, 4.0]
    r = robot(position_noise=0.01, velocity_noise=0.05, seed=3, kp=kp, kd=kd,
              joint_order=['joint3', 'joint1', 'joint2'])
    target = load_task(TASK).start_posture + 0.1
    hold(r, target)
    for _ in range(5):
        exact = np.array([by_name(r, 'qpos')[j] for j in r.arm.joint_names])
        state, _ = r.step()
        order = [state.name.index(j) for j in r.arm.joint_names]
        q, qd = state.position[order], state.velocity[order]
        np.testing.assert_allclose(r.controller.last.torque,
                                   np.clip(np.array(kp) * (target - q) - np.array(kd) * qd,
                                           -40.0, 40.0), rtol=1e-12, atol=1e-12)
        assert np.abs(q - exact).max() > 0.0        # it was the measurement, with its noise


def test_zero_noise_gives_the_exact_state():
    r = robot(joint_order=['joint2', 'joint3', 'joint1'])
    hold(r, load_task(TASK).start_posture + 0.2)
    for _ in range(20):
        r.step()
    m = r.measure()
    qpos, qvel = by_name(r, 'qpos'), by_name(r, 'qvel')
    assert m.name == ['joint2', 'joint3', 'joint1']
    assert m.position.tolist() == [qpos[n] for n in m.name]
    assert m.velocity.tolist() == [qvel[n] for n in m.name]
    assert m.time == pytest.approx(20 * 0.002)


def test_noise_has_the_standard_deviation_asked_for():
    sigma_q, sigma_qd, n = 0.01, 0.05, 20000
    r = robot(position_noise=sigma_q, velocity_noise=sigma_qd, seed=7)
    for _ in range(10):
        r.step()
    exact_q, exact_qd = by_name(r, 'qpos'), by_name(r, 'qvel')
    samples = [r.measure() for _ in range(n)]       # the same state measured n times
    q = np.array([s.position for s in samples]) - [exact_q[j] for j in r.names]
    qd = np.array([s.velocity for s in samples]) - [exact_qd[j] for j in r.names]
    low, high = stats.chi2.ppf([P_FAIL / 2, 1 - P_FAIL / 2], n - 1) / (n - 1)
    z = stats.norm.ppf(1 - P_FAIL / 2)
    for error, sigma in ((q, sigma_q), (qd, sigma_qd)):
        variance = error.var(axis=0, ddof=1) / sigma**2      # (n_joints,) ~ chi2(n-1)/(n-1)
        assert np.all((low < variance) & (variance < high)), (variance, low, high)
        assert np.all(np.abs(error.mean(axis=0)) < z * sigma / np.sqrt(n)), error.mean(axis=0)
    # the same seed, the same noise
    again = robot(position_noise=sigma_q, velocity_noise=sigma_qd, seed=7)
    other = robot(position_noise=sigma_q, velocity_noise=sigma_qd, seed=8)
    assert np.array_equal(again.measure().position, robot(
        position_noise=sigma_q, velocity_noise=sigma_qd, seed=7).measure().position)
    assert not np.array_equal(again.measure().position, other.measure().position)


def test_the_model_error_is_applied_before_anything_runs():
    r = robot(model_error='mass_scale=1.3,frictionloss=0.05,damping=0.3')
    nominal = ArmModel(load_task(TASK)).model
    m = r.arm.model
    for name in ('link1', 'link2', 'link3'):            # the arm's bodies
        assert m.body(name).mass[0] == pytest.approx(1.3 * nominal.body(name).mass[0])
        np.testing.assert_allclose(m.body(name).inertia, 1.3 * nominal.body(name).inertia)
    for name in ('world', 'obstacle'):                   # the world's, unchanged
        assert m.body(name).mass[0] == nominal.body(name).mass[0]
    for name in r.arm.joint_names:
        dof = m.joint(name).dofadr[0]
        assert m.dof_damping[dof] == pytest.approx(nominal.dof_damping[dof] + 0.3)
        assert m.dof_frictionloss[dof] == pytest.approx(nominal.dof_frictionloss[dof] + 0.05)
    # and the dynamics with it: the same pull moves the heavier arm less
    plain = robot()
    target = load_task(TASK).start_posture + 0.3
    for each in (r, plain):
        hold(each, target)
        for _ in range(10):
            each.step()
    assert np.all(np.abs(r.measure().velocity) < np.abs(plain.measure().velocity))


def test_its_joint_order_and_extra_joints_and_the_applied_torque_as_effort():
    r = robot(joint_order=['joint3', 'joint1', 'joint2'], extra_joints=['gripper'])
    hold(r, load_task(TASK).start_posture + 0.2)
    r.step()
    applied = dict(zip(r.arm.joint_names, r.applied))
    assert by_name(r, 'ctrl') == pytest.approx(applied, abs=0.0)    # each actuator, by joint
    m = r.measure()
    assert m.name == ['joint3', 'joint1', 'joint2', 'gripper']
    assert m.effort.tolist() == [applied['joint3'], applied['joint1'], applied['joint2'], 0.0]
    assert (m.position[-1], m.velocity[-1]) == (0.0, 0.0)


def test_the_torque_is_clipped_to_the_limits():
    r = robot()
    hold(r, load_task(TASK).start_posture + [2.0, -2.0, 0.001])     # far: saturates
    r.step()
    assert r.applied[0] == 40.0 and r.applied[1] == -40.0 and abs(r.applied[2]) < 40.0


def test_a_task_instance_is_placed_without_moving_the_arm():
    r = robot(task='payload_transport', model_error='mass_scale=1.2', kp=[0.0, 0.0],
              kd=[0.0, 0.0])
    for _ in range(50):                                  # falling under gravity, no torque
        r.step()
    q, qd = by_name(r, 'qpos'), by_name(r, 'qvel')
    assert any(abs(v) > 1e-3 for v in qd.values())
    r.place([2.5])
    assert r.arm.model.body('payload').mass[0] == 2.5     # the instance's mass, as announced
    assert (by_name(r, 'qpos'), by_name(r, 'qvel')) == (q, qd)


def test_the_initial_posture_is_where_the_robot_starts():
    r = robot(initial_posture=[0.1, -0.2, 0.3], joint_order=['joint3', 'joint2', 'joint1'])
    assert r.measure().position.tolist() == [0.3, -0.2, 0.1]
    start = load_task(TASK).start_posture
    assert [by_name(robot(), 'qpos')[f'joint{k + 1}'] for k in range(3)] == start.tolist()
    with pytest.raises(ValueError, match='outside its range'):
        robot(initial_posture=[0.0, 0.0, 9.0])


@pytest.mark.parametrize('changes, message', [
    ({'joint_order': ['joint1', 'joint2']}, 'missing'),
    ({'joint_order': ['joint1', 'joint2', 'joint2']}, 'once'),
    ({'joint_order': ['joint1', 'joint2', 'finger']}, 'not driven'),
    ({'extra_joints': ['joint1']}, 'extra_joints'),
    ({'extra_joints': ['finger', 'finger']}, 'extra_joints'),
    ({'initial_posture': [0.0, 0.0]}, 'initial_posture'),
    ({'initial_posture': [0.0, float('nan'), 0.0]}, 'initial_posture'),
    ({'kp': [1.0, 2.0]}, 'kp'),
    ({'kd': [1.0, -2.0, 3.0]}, 'kd'),
    ({'kp': [1.0, float('nan'), 3.0]}, 'kp'),
    ({'position_noise': -0.1}, 'position_noise'),
    ({'velocity_noise': float('inf')}, 'velocity_noise'),
    ({'latency_periods': -1}, 'latency_periods'),
    ({'seed': -3}, 'seed'),
    ({'model_error': 'mass=2'}, 'model error'),
    ({'task': 'no_such_task', 'joint_order': ['a']}, 'no_such_task'),
])
def test_parameters_that_do_not_fit_are_refused(changes, message):
    with pytest.raises(ValueError, match=message):
        StandardRobotParameters(**{'task': TASK, **changes})


def test_the_defaults_are_valid_and_need_no_task():
    p = StandardRobotParameters(task='no_such_task')     # checked when the robot loads it
    assert dataclasses.replace(p, task=TASK).extras == ()
    r = robot()
    assert r.names == r.arm.joint_names
    task = load_task(TASK)
    assert r.controller.law.kp.tolist() == task.controller.kp.tolist()
