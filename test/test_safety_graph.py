"""The safety check in the graph: the executor checks every candidate's reference before it
sends anything (`psl_task.safety_check`); a refused one gets the penalty and the reason, and the
simulator starts no episode for it (its episode count on /diagnostics)."""
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray

from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_ros import names
from psl_ros.qos import RELIABLE
from psl_ros.stamps import to_ns
from psl_task.task import load_task

TASK = 'reach_over_obstacle'


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


@pytest.fixture
def episode_count(client, wait_until):
    """episode_count(result): the simulator's count of started episodes, as its report at
    the end of that rollout's episode says."""
    reports = {}

    def on_diagnostics(msg):
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if 'episodes' in values and values['steps_done'] == values['steps']:
                reports[int(values['episode_start_ns'])] = int(values['episodes'])
    sub = client.node.create_subscription(DiagnosticArray, names.DIAGNOSTICS, on_diagnostics,
                                          RELIABLE)
    assert wait_until(lambda: sub.get_publisher_count() >= 1, 10.0)

    def count(result):
        t0 = to_ns(result.evaluation.stamp)
        assert wait_until(lambda: t0 in reports, 10.0), sorted(reports)
        return reports[t0]
    yield count
    client.node.destroy_subscription(sub)


def test_refused_candidates_start_no_episode(client, task, episode_count):
    default = policy_for(task).default_theta
    # a first episode while the report subscription matches the simulator's writer (its report
    # may be missed); the second's report is the count before
    assert client.rollout(TASK, task.tau_default, default, timeout=60).success
    before = client.rollout(TASK, task.tau_default, default, timeout=60)
    assert before.success and not before.refused, before.message
    wild = 6.0 * default                     # joint2 beyond its range [-3, 3]
    refused = client.rollout(TASK, task.tau_default, wild, timeout=30)
    assert refused.success and refused.refused, refused.message
    assert 'its limit' in refused.refused and 'joint' in refused.refused
    assert refused.evaluation.reward < task.safety.penalty
    assert not refused.evaluation.fulfilled
    # the same verdict and penalty as batch mode (one check, both modes)
    batch = BatchRollouts(task).run(wild[None], task.tau_default)[0]
    assert batch.refused == refused.refused
    assert batch.evaluation.reward == refused.evaluation.reward
    # theta = 1e308: the range policy refuses it before the safety check, with the range
    absurd = client.rollout(TASK, task.tau_default, np.full_like(default, 1e308), timeout=30)
    assert not absurd.success and 'a units or scaling error' in absurd.message
    # neither started an episode: the next good rollout is the very next one
    after = client.rollout(TASK, task.tau_default, default, timeout=60)
    assert after.success and not after.refused, after.message
    assert episode_count(after) == episode_count(before) + 1
