"""Dynamics learning in graph mode: the rollout's evaluation carries the measured episode
(joint angles, applied torques, the controller's reference), so the learner runs ILC of the
feed-forward through the graph as in batch mode. A graph-mode payload_transport session (sim,
controller, executor, evaluator, memory and learner as processes) equals the in-process
session: the same rollouts per task, the same rewards to the graph's tolerance."""
import json

import numpy as np

from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_ros.client import RosClient
from psl_ros.graph import Graph, pid_alive
from psl_task.task import load_task

TASK = 'payload_transport'
NUM_TEST = 2
SKILL = LearnSettings().skill
MEMORY_PARAMS = {'readout': SKILL.readout, 'n_hidden': SKILL.n_hidden,
                 'regularization': SKILL.regularization, 'seed': SKILL.seed}
SETTINGS = LearnSettings(strategy='bootstrap', num_tasks=2, seed=1, num_test=NUM_TEST,
                         search=SearchSettings(max_rollouts=40))


def test_a_graph_mode_payload_session_runs_ilc_as_batch_mode_does(tmp_path):
    reference = Learner(load_task(TASK), SETTINGS, tmp_path / 'batch',
                        BatchRollouts(load_task(TASK))).run().to_dict()
    # ILC did the work in batch mode: few rollouts, every task fulfilled
    assert all(r['fulfilled'] for r in reference['tasks'])
    assert sum(r['rollouts'] for r in reference['tasks']) <= 2 * 30
    g = Graph(task=TASK, log_dir=tmp_path / 'logs', extra_params={
        'skill_memory': MEMORY_PARAMS,
        'learner': {'test_tasks': NUM_TEST, 'output_root': str(tmp_path / 'runs')}})
    try:
        g.start()
        g.wait_ready(timeout=60)
        with RosClient() as client:
            result = client.learn(timeout=300, task=TASK, strategy=SETTINGS.strategy,
                                  num_tasks=SETTINGS.num_tasks,
                                  max_rollouts_per_task=SETTINGS.search.max_rollouts,
                                  seed=SETTINGS.seed, mode='graph',
                                  output_dir=str(tmp_path / 'graph'))
        assert result.success, result.message
        metrics = json.loads(open(result.metrics_path).read())
    finally:
        g.stop()
        assert not [p.name for p in g.processes if pid_alive(p.pid)]
    graph_tasks, batch_tasks = metrics['tasks'], reference['tasks']
    assert [r['rollouts'] for r in graph_tasks] == [r['rollouts'] for r in batch_tasks]
    assert [r['fulfilled'] for r in graph_tasks] == [r['fulfilled'] for r in batch_tasks]
    np.testing.assert_allclose([r['best_reward'] for r in graph_tasks],
                               [r['best_reward'] for r in batch_tasks], rtol=0, atol=1e-6)
    for key in ('test_rewards', 'tracking_rmse_learned'):
        np.testing.assert_allclose(metrics['summary'][key], reference['summary'][key], rtol=0,
                                   atol=1e-6)
    # the learned feed-forward tracks better than PD alone, in both modes alike
    assert metrics['summary']['tracking_rmse_learned_mean'] < \
        metrics['summary']['tracking_rmse_pd_only_mean']
