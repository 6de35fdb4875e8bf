"""The UR5 URDF of example-robot-data as published (package:// meshes, COLLADA visuals,
Gazebo and transmission tags, motors and limits from its <limit> tags) through the graph:
its rollouts equal batch mode's. The task YAML (examples/) adds the tool site, the obstacle
and gravity compensation; the URDF is read where pip installed it."""
from pathlib import Path

import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_task.arm_model import ArmModel
from psl_task.task import load_task

UR5 = Path(__file__).resolve().parents[1] / 'examples' / 'ur5_reach_over_obstacle.yaml'


@pytest.fixture(scope='module')
def graph_task():
    return str(UR5)


@pytest.fixture(scope='module')
def task():
    return load_task(str(UR5))


def test_the_ur5_loads_from_its_package(task):
    arm = ArmModel(task)
    assert task.model_path.parts[-4:] == ('robots', 'ur_description', 'urdf', 'ur5_robot.urdf')
    assert 'example-robot-data' in task.model_path.parts
    assert arm.joint_names == ['shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint',
                               'wrist_1_joint', 'wrist_2_joint', 'wrist_3_joint']
    np.testing.assert_array_equal(arm.torque_high, [150, 150, 150, 28, 28, 28])  # <limit effort>
    assert arm.passive_joints == []


def test_graph_and_batch_agree_on_the_ur5(graph_matches_batch, task):
    rng = np.random.default_rng(8)
    theta = policy_for(task).default_theta
    theta = theta + rng.normal(0.0, 0.05 * np.abs(theta).max(), theta.size)
    evaluation, batch = graph_matches_batch(task, task.sample_tau(rng), theta)
    assert evaluation.num_steps == task.num_steps
    assert np.ptp(batch.q[:, 0]) > 1.0          # the sweep of shoulder_pan


def test_the_ur5_pose_example_reaches_a_turned_pose_by_ilc():
    """examples/ur5_pose_reach.yaml (the pose DMP on the URDF as published, batch mode): the
    demonstration's tool ends on the default target; ILC alone (goal point, goal orientation,
    feed-forward) fulfils an instance 6 cm and 0.4 rad away in a few rollouts."""
    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_optimizer.ilc import ILCSettings, ilc_search
    task = load_task(str(UR5.parent / 'ur5_pose_reach.yaml'))
    batch = BatchRollouts(task, n_threads=1)
    assert batch.policy.controls_orientation
    default = batch.run(batch.policy.default_theta[None], task.tau_default)[0].evaluation
    assert default.fulfilled and default.components['orientation_error'] < 2e-3
    tau = task.tau_default + [0.04, -0.03, 0.03, 0.4]
    start = batch.run(batch.policy.default_theta[None], tau)[0].evaluation
    assert not start.fulfilled and start.components['orientation_error'] > 0.35
    found = ilc_search(batch, tau, batch.policy.default_theta, ILCSettings(iterations=10))
    assert found.fulfilled and found.rollouts <= 6
