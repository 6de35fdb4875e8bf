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

from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_ros.client import RosClient
from psl_ros.graph import pid_alive
from psl_sim.task import load_task

PSL = [sys.executable, '-m', 'psl_cli.main']
TASK = 'reach_over_obstacle'
SETTINGS = LearnSettings(strategy='scratch', num_tasks=2, seed=5, num_test=20,
                         search=SearchSettings(max_rollouts=22))


def up_log(path) -> str:
    return path.read_text() if path.exists() else ''


def wait_for(path, pattern: str, timeout: float) -> re.Match:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = re.search(pattern, up_log(path))
        if found:
            return found
        time.sleep(0.1)
    raise AssertionError(f'{pattern!r} not printed; psl up printed:\n{up_log(path)}')


@pytest.mark.parametrize('policy', ['restart', 'drop'])
def test_a_killed_worker_simulator_does_not_end_the_session(tmp_path, policy):
    log_path = tmp_path / 'up.log'
    with open(log_path, 'w') as log:
        up = subprocess.Popen(PSL + ['up', '--workers', '2', '--worker-death', policy,
                                     '--memory-dir', str(tmp_path), '--log-dir',
                                     str(tmp_path / 'logs')],
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                              cwd=tmp_path, text=True)
    pids = []
    try:
        wait_for(log_path, 'graph ready', 90)
        pids = [int(p) for p in re.findall(r'pid (\d+)', up_log(log_path))]
        victim = int(wait_for(log_path, r'started worker1/sim\s+pid (\d+)', 5).group(1))
        killed = []

        def kill_once(feedback):
            # the first task is done: the second task's rollouts run on both workers
            if not killed and feedback.feedback.task_index >= 1:
                os.kill(victim, signal.SIGKILL)
                killed.append(time.monotonic())
        with RosClient() as client:
            result = client.learn(timeout=600, feedback=kill_once, task=TASK,
                                  strategy=SETTINGS.strategy, num_tasks=SETTINGS.num_tasks,
                                  max_rollouts_per_task=SETTINGS.search.max_rollouts,
                                  seed=SETTINGS.seed, mode='graph',
                                  output_dir=str(tmp_path / 'graph'))
        assert killed, 'the session ended before the kill'
        assert result.success, result.message
        metrics = json.loads(open(result.metrics_path).read())
        text = wait_for(log_path, r'worker1/sim \(pid \d+\) ended with signal SIGKILL', 10)
        assert text
        if policy == 'restart':
            wait_for(log_path, r'restarted worker /worker1: worker1/sim pid \d+', 10)
        else:
            wait_for(log_path, r'dropped worker /worker1; 1 left', 10)
        assert up.poll() is None, up_log(log_path)            # the graph goes on
        pids += [int(p) for p in re.findall(r'pid (\d+)', up_log(log_path))]
    finally:
        if up.poll() is None:
            os.kill(up.pid, signal.SIGINT)
            try:
                up.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.kill(up.pid, signal.SIGKILL)
                up.wait()
        for pid in pids:
            if pid_alive(pid):
                os.kill(pid, signal.SIGKILL)
    assert not [pid for pid in pids if pid_alive(pid)]
    reference = Learner(load_task(TASK), SETTINGS, tmp_path / 'batch').run().to_dict()
    got, want = metrics['tasks'], reference['tasks']
    assert [r['rollouts'] for r in got] == [r['rollouts'] for r in want]
    assert [r['fulfilled'] for r in got] == [r['fulfilled'] for r in want]
    np.testing.assert_allclose([r['best_reward'] for r in got], [r['best_reward'] for r in want],
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(metrics['summary']['test_rewards'],
                               reference['summary']['test_rewards'], rtol=0, atol=1e-9)
