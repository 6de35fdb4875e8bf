"""safety.max_tracking_error in the graph: the executor gives it to the controller as every
joint's path tolerance; the controller aborts a goal whose tracking error passes it
(PATH_TOLERANCE_VIOLATED, it holds where the arm is) and the rollout counts as the penalty,
with the reason, in the graph as in batch mode; a learning session goes on past it; a bound the
episode stays within changes nothing. Batch mode's rollout of the same candidate (the graph
equals it within 1e-9 rad in lockstep) says where the error first passes it."""
import json

import numpy as np
import pytest
import yaml

from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_task.arm_model import joint_names_of
from psl_task.task import load_task

BASE = 'reach_over_obstacle'


@pytest.fixture(scope='module')
def bound_and_first(tmp_path_factory):
    """(a bound the default candidate's tracking error passes, batch mode's first step and
    joint beyond it, the episode's largest error)."""
    task = load_task(BASE)
    theta = policy_for(task).default_theta
    batch = BatchRollouts(task).run(theta[None], task.tau_default)[0]
    error = np.abs(batch.q - batch.q_ref)
    bound = 0.5 * error.max()
    k = int(np.argmax(error.max(axis=1) > bound))
    return bound, k, int(np.argmax(error[k])), error.max()


@pytest.fixture(scope='module')
def graph_task(tmp_path_factory, bound_and_first):
    default = load_task(BASE)
    data = yaml.safe_load(default.path.read_text())
    data.update(name='bounded_reach', model=str(default.model_path))
    data.setdefault('safety', {})['max_tracking_error'] = float(bound_and_first[0])
    path = tmp_path_factory.mktemp('task') / 'bounded_reach.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_an_episode_beyond_the_bound_is_aborted_with_the_reason(client, graph_task,
                                                                bound_and_first):
    """The controller aborts the goal at the first state past the bound (the task's
    max_tracking_error is the goal's path tolerance: PATH_TOLERANCE_VIOLATED, its reason in
    the result) and holds; the rollout counts as the penalty minus the excess error, the
    same check replayed on the measured episode as batch mode replays it on its own (the
    graph equals batch mode within 1e-9 rad in lockstep up to the abort)."""
    bound, k, joint, _ = bound_and_first
    task = load_task(graph_task)
    theta = policy_for(task).default_theta
    result = client.rollout(graph_task, task.tau_default, theta, timeout=60)
    assert result.success, result.message
    assert result.aborted.startswith('path tolerance violated'), result.aborted
    assert result.aborted in result.message
    assert f'joint {joint_names_of(task)[joint]!r}' in result.aborted, result.aborted
    assert f'violated at {k * task.control_period:.3f} s' in result.aborted, result.aborted
    evaluation = result.evaluation
    assert not evaluation.fulfilled
    assert list(evaluation.component_names) == ['tracking_abort']
    violation = evaluation.component_values[0]
    assert 0.0 < violation
    assert evaluation.reward == pytest.approx(task.safety.penalty - violation, abs=1e-12)
    batch = BatchRollouts(task).run(theta[None], task.tau_default)[0]
    assert batch.aborted, 'batch mode did not abort the same candidate'
    assert batch.evaluation.reward == pytest.approx(evaluation.reward, abs=1e-9)
    assert not batch.evaluation.fulfilled and not batch.has_trajectory
    # the measured episode: the arm followed the reference up to the abort, then held
    q = np.asarray(evaluation.position).reshape(-1, task.n_joints)
    q_ref = np.asarray(evaluation.reference_position).reshape(-1, task.n_joints)
    error = np.abs(q - q_ref).max(axis=1)
    assert error[:k].max() <= bound < error[k]
    assert np.abs(np.diff(q[k + 50:], axis=0)).max() < 1e-3     # at rest, held


def test_a_learning_session_goes_on_past_aborted_episodes(client, graph_task, tmp_path):
    """Candidates whose episodes the controller aborts are bad candidates, not a broken
    robot: a graph-mode session on the bounded task runs its budget and ends with the task
    not fulfilled, every rollout counted."""
    result = client.learn(timeout=300, task=graph_task, strategy='scratch', num_tasks=1,
                          max_rollouts_per_task=3, seed=0, mode='graph',
                          output_dir=str(tmp_path / 'session'))
    assert result.success, result.message
    metrics = json.loads(open(result.metrics_path).read())
    assert metrics['summary']['total_rollouts'] >= 3
    assert not metrics['tasks'][0]['fulfilled']


def test_the_bound_is_the_rollouts_tasks(client, graph_task):
    """The controller started with the bounded task; a rollout of the task without a bound
    (its gains and bound set by the executor) runs to its end, also after an abort."""
    task = load_task(BASE)
    result = client.rollout(BASE, task.tau_default, policy_for(task).default_theta,
                            timeout=60)
    assert result.success, result.message
