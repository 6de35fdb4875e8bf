"""Gains per task: two tasks of the same robot with different PD gains share one running
controller; the executor gives the controller each rollout's task's gains (its parameter
service validates them), so every rollout equals batch mode's with that task's law."""
import numpy as np
import yaml

from psl_controller.pd_law import law_for
from psl_controller.policy import policy_for
from psl_task.task import load_task

TASK = 'reach_over_obstacle'


def test_two_tasks_with_different_gains_on_one_controller(graph_matches_batch, client,
                                                          tmp_path):
    default = load_task(TASK)
    data = yaml.safe_load(default.path.read_text())
    data.update(name='soft_reach', model=str(default.model_path))
    data['controller'] = {'kp': [120.0, 80.0, 40.0], 'kd': [8.0, 5.0, 2.0]}
    path = tmp_path / 'soft_reach.yaml'
    path.write_text(yaml.safe_dump(data))
    soft = load_task(str(path))
    assert not np.array_equal(law_for(soft).kp, law_for(default).kp)
    theta = policy_for(default).default_theta
    rewards = {}
    for task in (default, soft, default):         # back and forth on one controller
        evaluation, batch = graph_matches_batch(task, task.tau_default, theta)
        rewards.setdefault(task.name, []).append(evaluation.reward)
    # the softer gains track worse: the law really changed between the rollouts
    assert rewards['soft_reach'][0] != rewards[TASK][0]
    assert rewards[TASK][0] == rewards[TASK][1]
    # a bad gain is refused by the controller's parameter service, and it keeps its gains
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    parameters = AsyncParameterClient(client.node, 'pd_controller')
    assert parameters.wait_for_services(timeout_sec=10.0)
    future = parameters.set_parameters([Parameter('kp', value=[1.0, -1.0, 1.0])])
    from psl_ros.futures import wait_for
    (result,) = wait_for(future, 10.0, 'set_parameters').results
    assert not result.successful and 'finite values >= 0' in result.reason
    evaluation, _ = graph_matches_batch(default, default.tau_default, theta)
    assert evaluation.reward == rewards[TASK][0]
