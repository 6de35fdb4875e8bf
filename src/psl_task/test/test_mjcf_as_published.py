"""MJCF robots as their authors publish them: a humanoid's arm taken from gymnasium's
humanoid.xml (its legs coupled by fixed tendons, its motors geared 25:1). Locking every joint
of a fixed tendon removes the tendon with its actuators (its length is then a constant);
locking only some is refused naming the tendon; a geared joint motor becomes one whose ctrl
is the joint torque with the same limits, the torque it applies equal to the geared one's
(MuJoCo's own model of the file as the reference)."""
import textwrap
from pathlib import Path

import mujoco
import numpy as np
import pytest

import gymnasium
from psl_task.arm_model import ArmModel
from psl_task.model_spec import task_model
from psl_task.task import TaskError, task_from_data

HUMANOID = Path(gymnasium.__file__).parent / 'envs' / 'mujoco' / 'assets' / 'humanoid.xml'
ARM = ['left_shoulder1', 'left_shoulder2', 'left_elbow']


def humanoid_task(folder: Path, locked: dict[str, float]):
    data = {'name': 'humanoid_arm', 'model': str(HUMANOID),
            'robot': {'end_effector': {'body': 'left_lower_arm', 'offset': [0.18, 0.18, 0.18]},
                      'joints': ARM, 'locked_joints': locked},
            'control_rate': 1.0 / 0.003, 'duration': 1.0,
            'start_posture': [0.0, 0.0, 0.0], 'goal_posture': [0.2, 0.2, -0.5],
            'task_parameters': [{'name': 'x', 'low': 0.0, 'high': 1.0,
                                 'binds': {'kind': 'target_position', 'axis': 0}}],
            'target': {'position': [0.0, 0.0, 0.0]},
            'controller': {'kp': [10.0] * 3, 'kd': [1.0] * 3}, 'policy': {'n_basis': 3},
            'demonstration': {'times': [0.0, 1.0],
                              'positions': [[0.0, 0.0, 0.0], [0.2, 0.2, -0.5]]},
            'reward': {'weights': {'goal_error': 1.0}, 'success_threshold': -1.0}}
    return task_from_data(folder / 'task.yaml', data)


def off_the_arm() -> dict[str, float]:
    """Every joint off the arm, at 0 or the nearest end of its range."""
    model = mujoco.MjModel.from_xml_path(str(HUMANOID))
    return {model.joint(j).name: float(np.clip(0.0, *model.jnt_range[j]))
            if model.jnt_limited[j] else 0.0
            for j in range(model.njnt) if model.joint(j).name not in ARM}


def test_the_humanoids_arm_locks_with_its_tendons_and_holds(tmp_path):
    task = humanoid_task(tmp_path, off_the_arm())
    model = task_model(task)
    assert model.ntendon == 0 and model.nu == 3 and model.nq == 3
    arm = ArmModel(task)
    assert arm.joint_names == ARM and arm.passive_joints == []
    data = mujoco.MjData(arm.model)       # no torque: only the arm can move, the body holds
    mujoco.mj_forward(arm.model, data)
    torso = data.xpos[arm.model.body('torso').id].copy()
    for _ in range(200):
        mujoco.mj_step(arm.model, data)
    np.testing.assert_array_equal(data.xpos[arm.model.body('torso').id], torso)


def test_a_tendon_half_locked_is_refused_naming_it(tmp_path):
    locked = {j: v for j, v in off_the_arm().items() if j != 'left_knee'}
    with pytest.raises(TaskError, match="the tendon 'left_hipknee' couples left_hip_y "
                                        r'\(locked\) with left_knee') as error:
        task_model(humanoid_task(tmp_path, locked))
    assert '\n' not in str(error.value)


def test_a_geared_motor_applies_the_torque_its_ctrl_now_names(tmp_path):
    arm = ArmModel(humanoid_task(tmp_path, off_the_arm()))
    raw = mujoco.MjModel.from_xml_path(str(HUMANOID))
    act = [raw.actuator(name).id for name in ARM]
    gear = raw.actuator_gear[act, 0]
    np.testing.assert_allclose(arm.torque_low, gear * raw.actuator_ctrlrange[act, 0], rtol=1e-15)
    np.testing.assert_allclose(arm.torque_high, gear * raw.actuator_ctrlrange[act, 1],
                               rtol=1e-15)
    assert np.all(arm.model.actuator_gear[:, 0] == 1.0)
    # the same joint torque through both: ctrl = torque here, torque / gear in the file
    torque = np.array([3.0, -7.5, 9.0])
    ours, theirs = mujoco.MjData(arm.model), mujoco.MjData(raw)
    ours.ctrl[arm.actuator_ids] = torque
    theirs.ctrl[act] = torque / gear
    mujoco.mj_forward(arm.model, ours)
    mujoco.mj_forward(raw, theirs)
    got = ours.qfrc_actuator[arm.dof_adr]
    want = theirs.qfrc_actuator[[raw.jnt_dofadr[raw.joint(n).id] for n in ARM]]
    np.testing.assert_allclose(got, want, rtol=1e-12)
