"""Realtime mode under a namespace: a whole rollout worker runs in /worker1 and paces itself
on the wall clock."""
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray

from psl_ros.graph import Graph, pid_alive
from psl_ros.client import RosClient
from psl_controller.policy import policy_for
from psl_sim.task import load_task

NAMESPACE = 'worker1'


@pytest.fixture(scope='module')
def worker(tmp_path_factory):
    g = Graph(mode='realtime', namespace=NAMESPACE, log_dir=tmp_path_factory.mktemp('rt'))
    try:
        g.start()
        g.wait_ready(timeout=60)
        yield g
    finally:
        g.stop()
        assert not [p.name for p in g.processes if pid_alive(p.pid)]


def test_realtime_rollout_in_a_namespace(worker):
    task = load_task('reach_over_obstacle')
    theta = policy_for(task).default_theta
    statuses = []
    with RosClient(NAMESPACE) as client:
        client.node.create_subscription(DiagnosticArray, '/diagnostics',
                                        lambda m: statuses.extend(m.status), 100)
        with RosClient() as outside:          # the root namespace has no worker
            assert not outside.rollout_client.wait_for_server(timeout_sec=1.0)
        start = time.monotonic()
        result = client.rollout(task.name, task.tau_default, theta, timeout=60)
        wall = time.monotonic() - start
        time.sleep(0.5)
    assert result.success, result.message
    evaluation = result.evaluation
    goal_error = dict(zip(evaluation.component_names, evaluation.component_values))['goal_error']
    assert goal_error < 0.01
    episode_seconds = task.num_steps * task.control_period
    assert wall >= episode_seconds         # paced by the wall clock, not as fast as possible
    final = [s for s in statuses if dict((kv.key, kv.value) for kv in s.values).get(
        'steps_done') == str(task.num_steps)]
    assert final and f'/{NAMESPACE}/sim' in final[-1].name
    values = {kv.key: kv.value for kv in final[-1].values}
    assert values['mode'] == 'realtime'
    assert 0 <= int(values['deadline_misses']) < task.num_steps
