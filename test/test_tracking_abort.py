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
from rclpy.qos import QoSProfile, ReliabilityPolicy

from psl_controller.policy import policy_for
from psl_msgs.msg import RolloutEvaluation
from psl_ros import names
from psl_optimizer.batch_rollout import BatchRollouts
from psl_task.arm_model import joint_names_of
from psl_task.task import load_task

BASE = 'reach_over_obstacle'
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


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
    # the measured episode: the arm followed the reference up to the abort, then held
    q = np.asarray(evaluation.position).reshape(-1, task.n_joints)
    q_ref = np.asarray(evaluation.reference_position).reshape(-1, task.n_joints)
    error = np.abs(q - q_ref)
    assert error[:k].max() <= bound < error[k].max()
    assert np.abs(np.diff(q[k + 50:], axis=0)).max() < 1e-3     # at rest, held
    # the violation is the error beyond the bound at that state and joint
    assert violation == pytest.approx(error[k, joint] - bound, rel=1e-9, abs=1e-12)
    assert evaluation.reward == pytest.approx(task.safety.penalty - violation, abs=1e-12)
    batch = BatchRollouts(task).run(theta[None], task.tau_default)[0]
    assert batch.aborted, 'batch mode did not abort the same candidate'
    assert f'joint {joint_names_of(task)[joint]!r}' in batch.aborted, batch.aborted
    assert f'at {k * task.control_period:.3f} s' in batch.aborted, batch.aborted
    assert batch.evaluation.reward == pytest.approx(evaluation.reward, abs=1e-9)
    assert not batch.evaluation.fulfilled and not batch.has_trajectory


def test_a_learning_session_goes_on_past_aborted_episodes(client, graph_task, tmp_path):
    """Candidates whose episodes the controller aborts are bad candidates, not a broken
    robot: a graph-mode session on the bounded task runs its whole budget, each rollout an
    executed episode (none refused), aborted ones among them scored as the tracking abort,
    and ends with the task not fulfilled."""
    budget = 3
    evaluations = []
    sub = client.node.create_subscription(RolloutEvaluation, names.ROLLOUT_EVALUATION,
                                          evaluations.append, RELIABLE)
    try:
        client.wait_for_subscribers([names.ROLLOUT_EVALUATION], subscriptions=[sub])
        result = client.learn(timeout=300, task=graph_task, strategy='scratch', num_tasks=1,
                              max_rollouts_per_task=budget, seed=0, mode='graph', num_test=1,
                              output_dir=str(tmp_path / 'session'))
    finally:
        client.node.destroy_subscription(sub)
    assert result.success, result.message
    metrics = json.loads(open(result.metrics_path).read())
    record = metrics['tasks'][0]
    assert metrics['summary']['total_rollouts'] == record['rollouts'] == budget
    assert record.get('refused', 0) == 0
    assert not record['fulfilled']
    aborted = [e for e in evaluations if list(e.component_names) == ['tracking_abort']]
    assert aborted, f'no aborted episode among {len(evaluations)} evaluations'
    assert all(not e.fulfilled for e in aborted)


def test_the_bound_is_the_rollouts_tasks(client, graph_task, bound_and_first):
    """The controller runs each rollout's task's bound: right after an episode of the
    bounded task that it aborts, the same candidate on the task without a bound runs to its
    end and is scored by the task's reward."""
    bounded = load_task(graph_task)
    theta = policy_for(bounded).default_theta
    first = client.rollout(graph_task, bounded.tau_default, theta, timeout=60)
    assert first.success and first.aborted.startswith('path tolerance violated'), \
        first.message
    task = load_task(BASE)
    result = client.rollout(BASE, task.tau_default, theta, timeout=60)
    assert result.success, result.message
    assert not result.aborted, result.aborted
    evaluation = result.evaluation
    assert 'tracking_abort' not in evaluation.component_names
    assert evaluation.num_steps == task.num_steps
    # the whole episode measured, beyond the state where the bounded one was aborted
    _, k, _, largest = bound_and_first
    q = np.asarray(evaluation.position).reshape(-1, task.n_joints)
    q_ref = np.asarray(evaluation.reference_position).reshape(-1, task.n_joints)
    assert len(q) > k and np.abs(q - q_ref).max() == pytest.approx(largest, rel=1e-6)
