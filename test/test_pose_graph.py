"""The pose DMP in graph mode: pose_reach_3d (the hand's position and orientation DMPs, the
six-dimensional inverse kinematics, ILC turning the goal orientation) through the graph's
processes in lockstep; the same rollouts in batch mode agree."""
import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_task.task import EMBEDDED_TASKS, load_task


@pytest.fixture(scope='module')
def graph_task():
    return str(EMBEDDED_TASKS / 'pose_reach_3d.yaml')


@pytest.mark.parametrize('tau', [[0.44, 0.06, -0.08, 3.25], [0.37, -0.1, -0.18, 2.8]])
def test_a_pose_task_runs_in_the_graph_as_in_batch_mode(graph_matches_batch, graph_task, tau):
    """Instances with the yaw turned either way, a perturbed theta: the executor's reference
    and batch mode's are the same, so the rollouts and every reward component, the
    orientation error included, agree."""
    task = load_task(graph_task)
    policy = policy_for(task)
    rng = np.random.default_rng(int(100 * tau[0]))
    theta = policy.default_theta + rng.normal(0.0, 0.01, policy.num_parameters)
    evaluation, batch = graph_matches_batch(task, np.array(tau), theta)
    assert evaluation.num_steps == task.num_steps_of(np.array(tau))
    assert batch.evaluation.components['orientation_error'] > 0.05    # the yaw is not the default
