"""Workers that fail alone: `psl up --workers 2` runs the robot loop twice; SIGKILL of one
worker's simulator in the middle of a graph-mode session. psl up reports the death and
restarts that worker (or drops it), the learner sends the unanswered rollout to the other
worker, and the session's result equals the uninterrupted one (lockstep rollouts do not depend
on the worker: the in-process batch session is the reference)."""
import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_ros.client import RosClient
from psl_ros.graph import NODES, NodeHandle
from psl_task.task import load_task

PSL = [sys.executable, '-m', 'psl_cli.main']
TASK = 'reach_over_obstacle'
SETTINGS = LearnSettings(strategy='scratch', num_tasks=2, seed=5, num_test=2,
                         search=SearchSettings(max_rollouts=12))


def hold_nodes(up: subprocess.Popen, text: str, nodes: dict[int, NodeHandle]) -> None:
    """Hold (NodeHandle) every node psl up has printed as started or restarted and that is
    not held yet; `nodes` is by PID."""
    for line in text[:text.rfind('\n') + 1].splitlines():     # whole lines only
        if line.startswith('started '):
            found = re.findall(r'^started (\S+)\s+pid (\d+)$', line)
        elif line.startswith('restarted worker '):
            found = re.findall(r'(\S+) pid (\d+)', line.split(': ', 1)[1])
        else:
            continue
        for label, pid in found:
            if int(pid) not in nodes:
                nodes[int(pid)] = NodeHandle(label, int(pid), up.pid)


def up_log(path) -> str:
    return path.read_text() if path.exists() else ''


def wait_for(path, pattern: str, timeout: float, up: subprocess.Popen) -> re.Match:
    """The first match of `pattern` in psl up's output, once printed; AssertionError after
    `timeout` s or when psl up has ended without printing it."""
    deadline = time.monotonic() + timeout
    while True:
        ended = up.poll() is not None          # then its output is complete: one last look
        found = re.search(pattern, up_log(path))
        if found:
            return found
        if ended or time.monotonic() > deadline:
            raise AssertionError(f'{pattern!r} not printed; psl up printed:\n{up_log(path)}')
        time.sleep(0.1)


@pytest.mark.parametrize('policy', ['restart', 'drop'])
def test_a_killed_worker_simulator_does_not_end_the_session(tmp_path, policy):
    log_path = tmp_path / 'up.log'
    with open(log_path, 'w') as log:
        up = subprocess.Popen(PSL + ['up', '--workers', '2', '--worker-death', policy,
                                     '--memory-dir', str(tmp_path), '--log-dir',
                                     str(tmp_path / 'logs')],
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                              cwd=tmp_path, text=True)
    nodes: dict[int, NodeHandle] = {}      # every node psl up started, by PID
    try:
        wait_for(log_path, 'graph ready', 90, up)
        hold_nodes(up, up_log(log_path), nodes)
        victim = next((n for n in nodes.values() if n.label == 'worker1/sim'), None)
        assert victim is not None, up_log(log_path)
        killed = []

        def kill_once(feedback):
            # the first task is done: the second task's rollouts run on both workers
            if not killed and feedback.feedback.task_index >= 1:
                killed.append(victim.kill())
        with RosClient() as client:
            result = client.learn(timeout=300, feedback=kill_once, task=TASK,
                                  strategy=SETTINGS.strategy, num_tasks=SETTINGS.num_tasks,
                                  max_rollouts_per_task=SETTINGS.search.max_rollouts,
                                  seed=SETTINGS.seed, num_test=SETTINGS.num_test, mode='graph',
                                  output_dir=str(tmp_path / 'graph'))
        assert killed, 'the session ended before the kill'
        assert killed == [True], 'worker1/sim had ended before the kill'
        assert result.success, result.message
        metrics = json.loads(open(result.metrics_path).read())
        wait_for(log_path, rf'worker1/sim \(pid {victim.pid}\) ended with signal SIGKILL',
                 10, up)
        if policy == 'restart':
            wait_for(log_path, r'restarted worker /worker1: worker1/sim pid \d+.*\n', 10, up)
        else:
            wait_for(log_path, r'dropped worker /worker1; 1 left', 10, up)
        assert up.poll() is None, up_log(log_path)            # the graph goes on
        hold_nodes(up, up_log(log_path), nodes)                # the restarted ones too
        assert len(nodes) == len(NODES) + 4 + (4 if policy == 'restart' else 0), \
            up_log(log_path)                # 2 workers of 4 nodes; 4 again after a restart
    finally:
        try:
            if up.poll() is None:
                up.send_signal(signal.SIGINT)
                try:
                    up.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    os.killpg(up.pid, signal.SIGKILL)      # not reaped: still its group
                    up.wait()
        finally:
            left = [n.label for n in nodes.values() if n.alive()]
            for node in nodes.values():
                node.kill()
                node.close()
    assert not left, f'psl up left {left} running'
    reference = Learner(load_task(TASK), SETTINGS, tmp_path / 'batch',
                        BatchRollouts(load_task(TASK))).run().to_dict()
    got, want = metrics['tasks'], reference['tasks']
    assert [r['rollouts'] for r in got] == [r['rollouts'] for r in want]
    assert [r['fulfilled'] for r in got] == [r['fulfilled'] for r in want]
    np.testing.assert_allclose([r['best_reward'] for r in got], [r['best_reward'] for r in want],
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(metrics['summary']['test_rewards'],
                               reference['summary']['test_rewards'], rtol=0, atol=1e-9)
