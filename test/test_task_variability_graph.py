"""The task variability in graph mode: a target (position and orientation), a duration, a
learned goal and an end-effector-space DMP with inverse kinematics, on the 10-joint arm,
through the graph's processes in lockstep; the same rollouts in batch mode agree."""
import shutil

import numpy as np
import pytest
import yaml

from psl_controller.policy import policy_for
from psl_task.task import EMBEDDED_TASKS, load_task


@pytest.fixture(scope='module')
def graph_task(tmp_path_factory):
    """planar_10dof_reach with every new kind at once: the target's x, y and yaw, the
    duration; the DMP over the hand position with its goal learned."""
    folder = tmp_path_factory.mktemp('variability_task')
    data = yaml.safe_load((EMBEDDED_TASKS / 'planar_10dof_reach.yaml').read_text())
    data['name'] = 'every_variability'
    data['task_parameters'] += [
        {'name': 'target_yaw', 'unit': 'rad', 'low': -0.5, 'high': 0.5,
         'binds': {'kind': 'target_orientation', 'axis': 2}},
        {'name': 'duration', 'unit': 's', 'low': 0.8, 'high': 1.4, 'default': 1.0,
         'binds': {'kind': 'duration'}}]
    data['policy'].update(space='end_effector', learn_goal=True)
    data['reward']['weights']['orientation_error'] = 0.1
    shutil.copy(EMBEDDED_TASKS / data['model'], folder / data['model'])
    path = folder / 'every_variability.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.fixture(scope='module')
def task(graph_task):
    return load_task(graph_task)


def test_the_task_has_every_new_kind(task):
    policy = policy_for(task)
    assert policy.ik is not None
    assert policy.num_parameters == 3 * task.policy.n_basis + 3      # weights and goal point
    assert {p.binds.kind for p in task.parameters} == {
        'target_position', 'target_orientation', 'duration'}


@pytest.mark.parametrize('tau', [[0.45, 0.1, 0.3, 0.8], [0.65, 0.4, -0.2, 1.4]])
def test_graph_and_batch_mode_agree(graph_matches_batch, task, tau):
    """Episodes of two lengths, a perturbed path and goal: the graph's measured joints, reward
    and components equal batch mode's."""
    rng = np.random.default_rng(int(10 * tau[0]))
    policy = policy_for(task)
    theta = policy.default_theta.copy()
    theta[policy.kinematics] += rng.normal(0.0, 5.0, policy.kinematics.stop)
    theta[policy.goal] = [tau[0] - 0.02, tau[1] + 0.01, 0.0]          # a hand goal near it
    evaluation, batch = graph_matches_batch(task, np.array(tau), theta)
    assert evaluation.num_steps == task.num_steps_of(np.array(tau))
    assert batch.evaluation.components['goal_error'] < 0.1
    assert batch.evaluation.components['orientation_error'] > 0.0
