"""The learner node as a separate process, with the skill memory node behind its services.

A session through the nodes must give what the same session in-process gives (the nodes are
adapters, not a second algorithm); a SIGKILLed learner, restarted, resumes from its checkpoint
to the same result; bad goals get a reason and the node keeps serving. (Graph mode over two
workers: the test with a whole graph in the root namespace; over one, through psl learn:
test_cli.py. The other tests run their nodes under namespaces of their own so no two learners
answer the same goal; no test depends on another's state or order.)
"""
import dataclasses
import json
import os
import signal
import time

import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy

from psl_ros.graph import NODES, Graph, pid_alive
from psl_ros import names
from psl_ros.client import RolloutClient, RosClient
from psl_controller.policy import policy_for
from psl_memory.skill_memory import SkillMemory
from psl_msgs.msg import RolloutEvaluation
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import CORRECTION_SUFFIX, Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
NUM_TEST = 2
SKILL = LearnSettings().skill      # the memory node gets the in-process default's readout
MEMORY_PARAMS = {'readout': SKILL.readout, 'n_hidden': SKILL.n_hidden,
                 'regularization': SKILL.regularization, 'seed': SKILL.seed}
LEARN_NODES = tuple(n for n in NODES if n[0] in ('skill_memory', 'learner'))
RELIABLE = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
LEARNER_ONLY = tuple(n for n in NODES if n[0] == 'learner')
NAMESPACE = 'batch_learning'
KILLED_NS = 'killed_learner'     # the killed learner's own nodes


def settings(strategy: str, num_tasks: int, budget: int, seed: int) -> LearnSettings:
    return LearnSettings(strategy=strategy, num_tasks=num_tasks, seed=seed, num_test=NUM_TEST,
                         search=SearchSettings(max_rollouts=budget))


def in_process(s: LearnSettings, out) -> dict:
    task = load_task(TASK)
    return Learner(task, s, out, BatchRollouts(task)).run().to_dict()


def without_time(records):
    return [{k: v for k, v in r.items() if k != 'seconds'} for r in records]


def assert_same_session(node_metrics: dict, reference: dict) -> None:
    a, b = without_time(node_metrics['tasks']), without_time(reference['tasks'])
    assert [r['rollouts'] for r in a] == [r['rollouts'] for r in b]
    assert [r['fulfilled'] for r in a] == [r['fulfilled'] for r in b]
    np.testing.assert_allclose([r['tau'] for r in a], [r['tau'] for r in b], atol=0)
    np.testing.assert_allclose([r['best_reward'] for r in a], [r['best_reward'] for r in b],
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(node_metrics['summary']['test_rewards'],
                               reference['summary']['test_rewards'], rtol=0, atol=1e-9)


def stop(graph: Graph) -> None:
    graph.stop()
    assert not [p.name for p in graph.processes if pid_alive(p.pid)]


def learner_params(out_root) -> dict:
    return {'test_tasks': NUM_TEST, 'output_root': str(out_root)}


@pytest.fixture(scope='module')
def nodes(tmp_path_factory):
    g = Graph(nodes=LEARN_NODES, namespace=NAMESPACE,
              log_dir=tmp_path_factory.mktemp('learner_logs'),
              extra_params={'skill_memory': MEMORY_PARAMS,
                            'learner': learner_params(tmp_path_factory.mktemp('runs'))})
    try:
        g.start()
        yield g
    finally:
        stop(g)


@pytest.fixture(scope='module')
def client(nodes):
    with RosClient(NAMESPACE) as c:
        assert c.memory('info', timeout=30).success
        yield c


def fresh_memory(client, tmp_path) -> None:
    """Load an empty skill for the task into the memory node (its public load service)."""
    task = load_task(TASK)
    memory = SkillMemory(SKILL)
    memory.create(task.name, task.tau_low, task.tau_high, policy_for(task).default_theta)
    path = tmp_path / 'empty.npz'
    memory.save(path)
    assert client.memory('load', path=str(path), replace=True).success


def num_samples(client, skill: str = TASK) -> int:
    return json.loads(client.memory('info').message)[skill]['num_samples']


def goal(s: LearnSettings, out, mode: str = 'batch') -> dict:
    return dict(task=TASK, strategy=s.strategy, num_tasks=s.num_tasks,
                max_rollouts_per_task=s.search.max_rollouts, seed=s.seed, mode=mode,
                output_dir=str(out))


def test_a_session_through_the_nodes_equals_the_in_process_session(client, tmp_path,
                                                                   wait_until):
    fresh_memory(client, tmp_path)
    s = settings('bootstrap', num_tasks=3, budget=30, seed=5)
    feedback = []
    result = client.learn(feedback=lambda m: feedback.append(m.feedback), timeout=300,
                          **goal(s, tmp_path / 'node'))
    assert result.success, result.message
    metrics = json.loads(open(result.metrics_path).read())
    reference = in_process(s, tmp_path / 'reference')
    assert_same_session(metrics, reference)
    # the skill lives in the memory node: one sample per fulfilled task
    assert num_samples(client) == sum(r['fulfilled'] for r in metrics['tasks'])
    # feedback: task index and rollout count never go back, and it reached the last task
    # (feedback and result travel on topics of their own: the last feedback may come after
    # the result)
    total = metrics['summary']['total_rollouts']
    assert wait_until(lambda: feedback and feedback[-1].rollouts >= total, 10.0), \
        [f.rollouts for f in feedback]
    feedback = list(feedback)
    indices = [f.task_index for f in feedback]
    rollouts = [f.rollouts for f in feedback]
    assert indices == sorted(indices) and rollouts == sorted(rollouts)
    assert indices[-1] == s.num_tasks - 1
    assert rollouts[-1] >= total


@pytest.mark.parametrize('fields, reason', [
    ({'task': 'no_such_task'}, 'no_such_task'),
    ({'strategy': 'gradient_descent'}, 'unknown strategy'),
    ({'num_tasks': 0}, 'num_tasks'),
    ({'mode': 'warp'}, 'unknown mode'),
])
def test_a_bad_goal_gets_a_reason_and_the_node_keeps_serving(client, tmp_path, fields, reason):
    fields = {**goal(settings('bootstrap', 1, 5, 0), tmp_path / 'bad'), **fields}
    result = client.learn(timeout=60, **fields)
    assert not result.success and reason in result.message
    assert not (tmp_path / 'bad' / 'checkpoint.json').exists()
    fresh_memory(client, tmp_path)
    result = client.learn(timeout=120, **goal(settings('bootstrap', 1, 5, 0), tmp_path / 'ok'))
    assert result.success, result.message


def test_a_missing_skill_is_created_from_the_task(client, tmp_path):
    """The memory knows no tasks: the learner creates the task's skill (create_skill), here
    of a task (a copy of TASK under a new name) the memory has never seen."""
    import shutil

    import yaml
    from psl_task.task import EMBEDDED_TASKS
    data = yaml.safe_load((EMBEDDED_TASKS / f'{TASK}.yaml').read_text())
    data['name'] = name = f'never_seen_{os.getpid()}'
    shutil.copy(EMBEDDED_TASKS / data['model'], tmp_path / data['model'])
    (tmp_path / 'never_seen.yaml').write_text(yaml.safe_dump(data))
    assert name not in json.loads(client.memory('info').message)
    result = client.learn(timeout=120, **{**goal(settings('bootstrap', 2, 5, 0), tmp_path / 'x'),
                                          'task': str(tmp_path / 'never_seen.yaml')})
    assert result.success, result.message
    metrics = json.loads(open(result.metrics_path).read())
    skill = json.loads(client.memory('info').message)[name]
    assert (skill['tau_dim'], skill['theta_dim']) == (2, policy_for(load_task(TASK)).num_parameters)
    assert skill['num_samples'] == sum(r['fulfilled'] for r in metrics['tasks'])


def test_continuing_from_a_skill_of_other_sizes_aborts_with_the_reason(client, tmp_path):
    other = SkillMemory(SKILL)
    other.add(TASK, [0.5], [1.0, 2.0, 3.0])          # the task's name, but 1 tau and 3 theta
    other.save(tmp_path / 'other.npz')
    result = client.learn(timeout=60, continue_from=str(tmp_path / 'other.npz'),
                          **goal(settings('bootstrap', 2, 5, 0), tmp_path / 'x'))
    assert not result.success and 'exists with 1 task and 3 policy parameters' in result.message
    assert not (tmp_path / 'x' / 'checkpoint.json').exists()


def test_a_new_session_starts_from_an_empty_skill_unless_told_to_continue(client, tmp_path):
    """The memory node still holds the skill of an earlier session: a new session does not
    start from it (it equals the in-process session), unless continue_from names a memory."""
    first = settings('bootstrap', num_tasks=3, budget=40, seed=6)
    assert client.learn(timeout=300, **goal(first, tmp_path / 'first')).success
    assert num_samples(client) > 0
    again = settings('bootstrap', num_tasks=2, budget=40, seed=7)
    result = client.learn(timeout=300, **goal(again, tmp_path / 'again'))
    assert result.success, result.message
    metrics = json.loads(open(result.metrics_path).read())
    assert_same_session(metrics, in_process(again, tmp_path / 'reference'))
    # continuing from the first session's memory, the residual way (the node's only way, the
    # in-process default): the loaded skill keeps its samples, a correction takes the new
    # solutions, and the session equals the same continuation in-process
    first_memory = tmp_path / 'first' / 'memory.npz'
    kept = SkillMemory.read(first_memory).get(TASK).num_samples
    goes_on = client.learn(timeout=300, continue_from=str(first_memory),
                           **goal(again, tmp_path / 'goes_on'))
    assert goes_on.success, goes_on.message
    done = json.loads(open(goes_on.metrics_path).read())
    assert num_samples(client) == kept
    assert num_samples(client, TASK + CORRECTION_SUFFIX) == sum(r['fulfilled']
                                                                for r in done['tasks'])
    assert_same_session(done, in_process(dataclasses.replace(
        again, continue_from=str(first_memory)), tmp_path / 'goes_on_reference'))
    # a new session after it starts from an empty skill again (the correction emptied too)
    result = client.learn(timeout=300, **goal(again, tmp_path / 'fresh_again'))
    assert result.success, result.message
    assert_same_session(json.loads(open(result.metrics_path).read()), in_process(
        again, tmp_path / 'reference_again'))
    assert num_samples(client, TASK + CORRECTION_SUFFIX) == 0


def test_goals_beyond_the_limits_are_refused_and_a_long_one_ends_on_cancel(client, tmp_path,
                                                                           wait_until):
    fields = goal(settings('bootstrap', 1, 5, 0), tmp_path / 'huge')
    for change, words in (({'num_tasks': 4_000_000_000}, 'num_tasks must be between 1 and'),
                          ({'max_rollouts_per_task': 1_000_000}, 'max_rollouts_per_task must')):
        result = client.learn(timeout=30, **{**fields, **change})
        assert not result.success and words in result.message, result.message
    # the largest session the learner takes: its task sequence is lazy, a cancel ends it
    out = tmp_path / 'long'
    handle = client.send_learn_goal(**{**goal(settings('bootstrap', 10_000, 40, 0), out)})
    assert wait_until(lambda: (out / 'checkpoint.json').is_file(), 120)
    client.wait(handle.cancel_goal_async(), 30, 'cancel')
    result = client.learner.result(handle, timeout=60)
    assert not result.success and 'cancelled' in result.message
    assert len(json.loads((out / 'checkpoint.json').read_text())['tasks']) < 10_000


def test_a_cancelled_session_resumes_when_the_goal_comes_again(client, tmp_path):
    fresh_memory(client, tmp_path)
    s = settings('scratch', num_tasks=8, budget=60, seed=4)
    out = tmp_path / 'session'
    handle = client.send_learn_goal(**goal(s, out))
    checkpoint = out / 'checkpoint.json'
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not checkpoint.is_file():
        time.sleep(0.005)
    client.wait(handle.cancel_goal_async(), 30, 'cancel')
    result = client.wait(handle.get_result_async(), 60, 'result').result
    kept = json.loads(checkpoint.read_text())['tasks']
    assert not result.success and 'cancelled' in result.message, result.message
    assert 1 <= len(kept) < s.num_tasks
    result = client.learn(timeout=300, **goal(s, out))
    assert result.success, result.message
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['tasks'][:len(kept)] == kept
    assert_same_session(metrics, in_process(s, tmp_path / 'reference'))


def test_a_killed_learner_resumes_from_its_checkpoint(tmp_path):
    """A memory and a learner of its own (its own namespace): the learner is SIGKILLed in a
    session and started again."""
    nodes = Graph(nodes=LEARN_NODES, namespace=KILLED_NS, log_dir=tmp_path / 'first_logs',
                  extra_params={'skill_memory': MEMORY_PARAMS,
                                'learner': learner_params(tmp_path / 'runs')})
    try:
        nodes.start()
        with RosClient(KILLED_NS) as client:
            assert client.memory('info', timeout=30).success
            before, s, out = kill_the_learner_in_a_session(nodes, client, tmp_path)
            restarted = Graph(nodes=LEARNER_ONLY, namespace=KILLED_NS,
                              log_dir=tmp_path / 'logs',
                              extra_params={'learner': learner_params(tmp_path / 'runs')})
            try:
                restarted.start()
                # a new participant: the old one may still see the killed server until its
                # lease ends
                with RosClient(KILLED_NS) as fresh:
                    result = fresh.learn(timeout=300, **goal(s, out))
            finally:
                stop(restarted)
            held = num_samples(client)
    finally:
        stop(nodes)
    assert result.success, result.message
    metrics = json.loads((out / 'metrics.json').read_text())
    # the tasks finished before the kill were kept, not redone
    assert without_time(metrics['tasks'][:len(before)]) == without_time(before)
    assert [r['seconds'] for r in metrics['tasks'][:len(before)]] == [r['seconds']
                                                                     for r in before]
    # and the whole session is the uninterrupted one
    assert_same_session(metrics, in_process(s, tmp_path / 'reference'))
    assert held == sum(r['fulfilled'] for r in metrics['tasks'])


def kill_the_learner_in_a_session(nodes: Graph, client, tmp_path):
    """Start a session on `nodes`' learner and SIGKILL it after two tasks; returns the tasks
    its checkpoint holds, the settings and the output folder."""
    fresh_memory(client, tmp_path)
    s = settings('scratch', num_tasks=8, budget=60, seed=2)
    out = tmp_path / 'session'
    learner = next(p for p in nodes.processes if p.name == 'learner')
    handle = client.send_learn_goal(**goal(s, out))
    checkpoint = out / 'checkpoint.json'
    deadline = time.monotonic() + 120
    done_at_kill = 0
    while time.monotonic() < deadline:
        if checkpoint.is_file():
            done_at_kill = len(json.loads(checkpoint.read_text())['tasks'])
            if done_at_kill >= 2:
                break
        time.sleep(0.005)
    # the learner is a child of this test, not yet reaped: the PID is still its own
    os.kill(learner.pid, signal.SIGKILL)
    learner.process.wait(timeout=10)
    before = json.loads(checkpoint.read_text())['tasks']
    assert 2 <= len(before) < s.num_tasks, 'the kill came too late to test a resume'
    del handle
    return before, s, out


def test_two_rollout_workers_learn_what_batch_mode_learns(tmp_path, wait_until):
    """Graph(workers=2): the loop runs twice, under worker0 and worker1; the learner spreads
    each CMA-ES population over both (lockstep rollouts do not depend on the worker)."""
    g = Graph(log_dir=tmp_path / 'logs', workers=2, extra_params={
        'skill_memory': MEMORY_PARAMS, 'learner': learner_params(tmp_path / 'runs')})
    try:
        g.start()
        labels = sorted(p.name for p in g.processes)
        assert 'worker0/sim' in labels and 'worker1/dmp_executor' in labels
        assert labels.count('learner') == 1 and 'sim' not in labels
        g.wait_ready(timeout=90)
        with RosClient() as c:
            evaluations = {'worker0': 0, 'worker1': 0}     # each worker's evaluator's output

            def counter(worker):
                def count(_):
                    evaluations[worker] += 1
                return count
            subscriptions = [c.node.create_subscription(
                RolloutEvaluation, f'/{worker}/rollout_evaluation', counter(worker), RELIABLE)
                for worker in evaluations]
            # every evaluator matched this client before the first rollout (both halves):
            # none is missed
            for worker, sub in zip(evaluations, subscriptions):
                RolloutClient(c.node, worker).wait_for_subscribers(
                    [names.ROLLOUT_EVALUATION], subscriptions=[sub], timeout=30.0)
            s = settings('scratch', num_tasks=2, budget=12, seed=5)
            result = c.learn(timeout=300, **goal(s, tmp_path / 'graph', mode='graph'))
            assert result.success, result.message
            metrics = json.loads(open(result.metrics_path).read())
            # one evaluation per training and per held-out rollout; the last ones may still
            # be on their way to this client
            expected = metrics['summary']['total_rollouts'] + NUM_TEST
            wait_until(lambda: sum(evaluations.values()) >= expected, 10.0)
    finally:
        stop(g)
    assert_same_session(metrics, in_process(s, tmp_path / 'batch'))
    # both workers rolled out, and every rollout ran once
    assert evaluations['worker0'] > 0 and evaluations['worker1'] > 0, evaluations
    assert sum(evaluations.values()) == expected, evaluations
