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


# Deadline misses per episode step below this share: more than half the periods are answered
# in time. A miss is a period whose command has not arrived when the next one starts (2 ms at
# 500 Hz). Measured: 0.3 % on a quiet machine (60 s, `psl bench graph`, whose < 1 % target that
# is); with this 1000-step episode 4-16 % at load average 3 on the 2 cores and up to 27 % at
# load average 5 (other graphs and a CPU burner running). Broken pacing misses nearly every
# period: a command applied one period late (the tick not waiting for the answer of its state),
# misses counted every period, the loop not answering; a simulator that does not wait for the
# wall clock fails the wall-time check as well.
MAX_MISS_SHARE = 0.5


def test_realtime_rollout_in_a_namespace(worker, wait_until):
    task = load_task('reach_over_obstacle')
    theta = policy_for(task).default_theta
    statuses = []
    with RosClient(NAMESPACE) as client:
        sub = client.node.create_subscription(DiagnosticArray, '/diagnostics',
                                              lambda m: statuses.extend(m.status), 100)
        with RosClient() as outside:          # the root namespace has no worker
            assert not outside.rollout_client.wait_for_server(timeout_sec=1.0)
        assert wait_until(lambda: sub.get_publisher_count() > 0, 15.0), 'no /diagnostics'
        start = time.monotonic()
        result = client.rollout(task.name, task.tau_default, theta, timeout=60)
        wall = time.monotonic() - start
        assert result.success, result.message
        t0 = result.evaluation.stamp.sec * 10**9 + result.evaluation.stamp.nanosec

        def final_status():
            """The simulator's status at the end of this rollout's episode, or None."""
            for status in list(statuses):
                values = {kv.key: kv.value for kv in status.values}
                if (values.get('episode_start_ns') == str(t0)
                        and values.get('steps_done') == str(task.num_steps)):
                    return status
            return None
        assert wait_until(lambda: final_status() is not None, 10.0), \
            f'no final /diagnostics status of the episode among {len(statuses)}'
    evaluation = result.evaluation
    goal_error = dict(zip(evaluation.component_names, evaluation.component_values))['goal_error']
    assert goal_error < 0.01
    episode_seconds = task.num_steps * task.control_period
    assert wall >= episode_seconds         # paced by the wall clock, not as fast as possible
    final = final_status()
    assert f'/{NAMESPACE}/sim' in final.name
    values = {kv.key: kv.value for kv in final.values}
    assert values['mode'] == 'realtime' and values['steps'] == str(task.num_steps)
    assert 0 <= int(values['deadline_misses']) < MAX_MISS_SHARE * task.num_steps, values
