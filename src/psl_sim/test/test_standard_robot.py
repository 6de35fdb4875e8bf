"""The standard robot's physics without ROS (`psl_sim.standard_robot`): latency, noise, command
timeout, model error, joint and command orders, clipping, refusals, placing a task instance,
and the parameters' checks. References are computed here from the MuJoCo model by joint name,
not through the robot's own index tables."""
import dataclasses

import numpy as np
import pytest
from scipy import stats

from psl_sim.standard_robot import CommandRefused, StandardRobot
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


@pytest.mark.parametrize('latency', [0, 1, 3])
def test_a_torque_step_is_applied_exactly_latency_periods_later(latency):
    r = robot(latency_periods=latency, command_timeout=1.0)
    step = np.array([1.0, -2.0, 3.0])
    applied = [r.advance() for _ in range(4)]       # zero before any command
    r.receive(step)                                 # arrives in the period after 4 advances
    applied += [r.advance() for _ in range(latency + 5)]
    for k, torque in enumerate(applied):
        expected = step if k >= 4 + latency else np.zeros(3)
        np.testing.assert_array_equal(torque, expected, err_msg=f'advance {k}')


def test_zero_torque_after_the_command_timeout():
    r = robot(command_timeout=0.006)                # 3 periods of 2 ms (on robot time)
    r.advance()
    r.receive([5.0, 5.0, 5.0])
    applied = [r.advance().copy() for _ in range(6)]
    assert [bool(np.any(t)) for t in applied] == [True, True, True, False, False, False]
    # a new command is in force again, for as long
    r.receive([1.0, 1.0, 1.0])
    assert [bool(np.any(r.advance())) for _ in range(4)] == [True, True, True, False]
    # the default: 5 control periods
    d = robot()
    d.receive([1.0, 1.0, 1.0])
    assert [bool(np.any(d.advance())) for _ in range(7)] == [True] * 5 + [False] * 2


def test_the_timeout_counts_on_the_clock_given():
    now = [100.0]                                   # a wall clock that the test moves
    r = StandardRobot(StandardRobotParameters(task=TASK, command_timeout=0.05),
                      clock=lambda: now[0])
    r.receive([1.0, 1.0, 1.0])
    for _ in range(100):                            # robot time runs, the clock stands
        assert np.any(r.advance())
    now[0] += 0.049
    assert np.any(r.advance())
    now[0] += 0.001                                 # 0.05 s since the command
    assert not np.any(r.advance())


def test_the_timeout_counts_from_the_arrival_not_from_the_application():
    r = robot(latency_periods=2, command_timeout=0.006)
    r.receive([1.0, 1.0, 1.0])
    # sampled at advances 0, 1, 2 (in force), applied two later: 2, 3, 4
    assert [bool(np.any(r.advance())) for _ in range(7)] == [False, False, True, True, True,
                                                            False, False]


def test_zero_noise_gives_the_exact_state():
    r = robot(joint_order=['joint2', 'joint3', 'joint1'])
    r.receive([3.0, -1.0, 2.0])
    for _ in range(20):
        r.advance()
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
        r.advance()
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
    # and the dynamics with it: the same torque moves the heavier arm less
    plain = robot()
    for each in (r, plain):
        for _ in range(10):
            each.receive([2.0, 2.0, 2.0])
            each.advance()
    assert np.all(np.abs(r.measure().velocity) < np.abs(plain.measure().velocity))


def test_commands_in_their_order_drive_the_right_joints_and_come_back_as_effort():
    r = robot(joint_order=['joint3', 'joint1', 'joint2'], extra_joints=['gripper'],
              command_joints=['joint2', 'joint3', 'joint1'])
    command = {'joint2': 1.0, 'joint3': 2.0, 'joint1': 3.0}
    r.receive([command[j] for j in ('joint2', 'joint3', 'joint1')])
    r.advance()
    assert by_name(r, 'ctrl') == command                 # each actuator, found by its joint
    m = r.measure()
    assert m.name == ['joint3', 'joint1', 'joint2', 'gripper']
    assert m.effort.tolist() == [2.0, 3.0, 1.0, 0.0]
    assert (m.position[-1], m.velocity[-1]) == (0.0, 0.0)


def test_commands_are_clipped_and_bad_ones_refused_without_changing_the_torque():
    r = robot(command_timeout=1.0)
    r.receive([100.0, -100.0, 1.0])
    np.testing.assert_array_equal(r.advance(), [40.0, -40.0, 1.0])
    for bad in ([1.0, 2.0], [1.0, 2.0, 3.0, 4.0], [np.nan, 0.0, 0.0], [0.0, np.inf, 0.0], []):
        with pytest.raises(CommandRefused):
            r.receive(bad)
        np.testing.assert_array_equal(r.advance(), [40.0, -40.0, 1.0])


def test_a_task_instance_is_placed_without_moving_the_arm():
    r = robot(task='payload_transport', model_error='mass_scale=1.2')
    for _ in range(50):                                  # falling under gravity, no torque
        r.advance()
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
    ({'command_joints': ['joint1', 'joint2', 'finger']}, 'not driven'),
    ({'extra_joints': ['joint1']}, 'extra_joints'),
    ({'extra_joints': ['finger', 'finger']}, 'extra_joints'),
    ({'initial_posture': [0.0, 0.0]}, 'initial_posture'),
    ({'initial_posture': [0.0, float('nan'), 0.0]}, 'initial_posture'),
    ({'position_noise': -0.1}, 'position_noise'),
    ({'velocity_noise': float('inf')}, 'velocity_noise'),
    ({'latency_periods': -1}, 'latency_periods'),
    ({'command_timeout': -1.0}, 'command_timeout'),
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
    assert r.names == r.arm.joint_names == r.command_joints
