"""Robots as published, through the graph: gymnasium's Pusher MJCF (read from the installed
package, passive object and goal joints) and the UR5 URDF of example-robot-data (package://
meshes, COLLADA visuals); each task YAML in examples/ completes the model (end effector,
obstacle) without touching it. The graph's rollouts equal batch mode's, also with a control
period of two physics steps."""
from pathlib import Path

import numpy as np
import pytest
import yaml

from psl_controller.policy import policy_for
from psl_task.arm_model import ArmModel
from psl_task.task import load_task

EXAMPLES = Path(__file__).resolve().parents[1] / 'examples'
PUSHER = EXAMPLES / 'pusher_reach_over_obstacle.yaml'


@pytest.fixture(scope='module')
def graph_task():
    return str(PUSHER)


@pytest.fixture(scope='module')
def task():
    return load_task(str(PUSHER))


def perturbed(task, seed):
    rng = np.random.default_rng(seed)
    theta = policy_for(task).default_theta
    return theta + rng.normal(0.0, 0.05 * np.abs(theta).max(), theta.size), rng


def test_the_pusher_loads_as_gymnasium_ships_it(task):
    arm = ArmModel(task)
    assert task.model_path.parts[-5:] == ('gymnasium', 'envs', 'mujoco', 'assets',
                                          'pusher_v5.xml')
    assert arm.joint_names[0] == 'r_shoulder_pan_joint' and len(arm.joint_names) == 7
    assert arm.passive_joints == ['obj_slidey', 'obj_slidex', 'goal_slidey', 'goal_slidex']
    np.testing.assert_array_equal(arm.torque_high, [2.0] * 7)     # the model's ctrlrange


def test_graph_and_batch_agree_on_the_pusher(graph_matches_batch, task):
    theta, rng = perturbed(task, 5)
    evaluation, batch = graph_matches_batch(task, task.sample_tau(rng), theta)
    assert evaluation.num_steps == task.num_steps
    assert np.ptp(batch.q[:, 0]) > 0.5          # the arm sweeps


def test_graph_and_batch_agree_with_two_physics_steps_per_command(graph_matches_batch, task,
                                                                  tmp_path):
    """The same robot at 50 Hz on its 100 Hz physics: the simulator holds each command over
    two physics steps, as batch mode does."""
    data = yaml.safe_load(PUSHER.read_text())
    data.update(name='pusher_50hz', control_rate=50.0)
    path = tmp_path / 'pusher_50hz.yaml'
    path.write_text(yaml.safe_dump(data))
    slow = load_task(str(path))
    assert ArmModel(slow).n_substeps == 2 and slow.num_steps == task.num_steps // 2
    theta, rng = perturbed(slow, 6)
    evaluation, _ = graph_matches_batch(slow, slow.sample_tau(rng), theta)
    assert evaluation.num_steps == slow.num_steps
