"""safety.max_tracking_error in the graph: the controller aborts an episode whose tracking
error passes the bound (it holds where the arm is) and the rollout fails with the reason; a
bound the episode stays within changes nothing. Batch mode's rollout of the same candidate
(the graph equals it within 1e-9 rad in lockstep) says where the error first passes it."""
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
    bound, k, joint, _ = bound_and_first
    task = load_task(graph_task)
    result = client.rollout(graph_task, task.tau_default, policy_for(task).default_theta,
                            timeout=60)
    assert not result.success and 'episode aborted' in result.message, result.message
    assert f'joint {joint_names_of(task)[joint]!r}' in result.message, result.message
    at = float(result.message.split(' rad from its reference at ')[1].split(' s')[0])
    assert at == pytest.approx(k * task.control_period, abs=1e-9), result.message


def test_the_bound_is_the_rollouts_tasks(client, graph_task):
    """The controller started with the bounded task; a rollout of the task without a bound
    (its gains and bound set by the executor) runs to its end, also after an abort."""
    task = load_task(BASE)
    result = client.rollout(BASE, task.tau_default, policy_for(task).default_theta,
                            timeout=60)
    assert result.success, result.message
