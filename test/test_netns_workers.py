"""Workers on other hosts, for real: two rollout workers in network namespaces of their own,
joined by a veth pair; discovery over that subnet only (ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET
inside the namespaces, whose only link is the pair: nothing beyond them). The skill memory,
the learner and worker0 run in namespace A, worker1 in namespace B; a graph-mode session
across them equals the in-process batch session. Needs root (ip netns); skipped otherwise."""
import json
import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest

from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_ros.bag_recorder import read_bag_summary
from psl_ros.graph import Graph, pid_alive
from psl_sim.task import load_task

TASK = 'reach_over_obstacle'
SETTINGS = LearnSettings(strategy='scratch', num_tasks=2, seed=7, num_test=20,
                         search=SearchSettings(max_rollouts=22))


def ip(*args: str) -> None:
    subprocess.run(['ip', *args], check=True, capture_output=True, timeout=10)


@pytest.fixture
def namespaces():
    """Two network namespaces joined by a veth pair on a /24 of their own; removed after."""
    if os.geteuid() != 0 or shutil.which('ip') is None:
        pytest.skip('network namespaces need root and iproute2 (ip netns): not available')
    tag = f'{os.getpid() % 100000}'
    a, b = f'psl_a{tag}', f'psl_b{tag}'
    subnet = f'10.231.{os.getpid() % 200 + 20}'
    try:
        ip('netns', 'add', a)
        ip('netns', 'add', b)
        ip('link', 'add', f'pa{tag}', 'type', 'veth', 'peer', 'name', f'pb{tag}')
        for ns, dev, host in ((a, f'pa{tag}', 1), (b, f'pb{tag}', 2)):
            ip('link', 'set', dev, 'netns', ns)
            ip('-n', ns, 'addr', 'add', f'{subnet}.{host}/24', 'dev', dev)
            ip('-n', ns, 'link', 'set', 'lo', 'up')
            ip('-n', ns, 'link', 'set', dev, 'up', 'multicast', 'on')
            ip('-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', dev)     # DDS discovery
    except (subprocess.CalledProcessError, OSError) as exc:
        for ns in (a, b):
            subprocess.run(['ip', 'netns', 'del', ns], capture_output=True)
        pytest.skip(f'cannot make network namespaces here: {exc}')
    yield a, b
    for ns in (a, b):
        subprocess.run(['ip', 'netns', 'del', ns], capture_output=True, timeout=10)


def inside(ns: str) -> list[str]:
    """Run a command in namespace ns with discovery over its subnet."""
    return ['ip', 'netns', 'exec', ns, 'env', 'ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET']


def test_a_session_across_two_network_namespaces_equals_batch_mode(namespaces, tmp_path,
                                                                   monkeypatch):
    a, b = namespaces
    monkeypatch.setenv('PSL_MEMORY_DIR', str(tmp_path))
    g = Graph(task=TASK, workers=2, log_dir=tmp_path / 'logs',
              launch_prefix={'': inside(a), 'worker0': inside(a), 'worker1': inside(b)})
    recorder = None
    try:
        g.start()
        # every evaluation of each worker, recorded from namespace A: worker1's come over the
        # veth pair from namespace B
        recorder = subprocess.Popen(
            inside(a) + [sys.executable, '-m', 'psl_cli.main', 'record', '-o',
                         str(tmp_path / 'bag'), '/worker0/rollout_evaluation',
                         '/worker1/rollout_evaluation'],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
            start_new_session=True)
        done = subprocess.run(
            inside(a) + [sys.executable, '-m', 'psl_cli.main', 'learn', '--mode', 'graph',
                         '--task', TASK, '--strategy', SETTINGS.strategy, '--tasks',
                         str(SETTINGS.num_tasks), '--budget', str(SETTINGS.search.max_rollouts),
                         '--seed', str(SETTINGS.seed), '--timeout', '90', '-o',
                         str(tmp_path / 'graph')],
            capture_output=True, text=True, timeout=600, cwd=tmp_path)
        assert done.returncode == 0, done.stderr + '\n'.join(
            f'--- {p.name}\n{p.tail()}' for p in g.processes)
        recorder.send_signal(signal.SIGINT)
        assert recorder.wait(timeout=30) == 0, recorder.stderr.read()
    finally:
        if recorder is not None and recorder.poll() is None:
            recorder.kill()
            recorder.wait()
        g.stop()
        assert not [p.name for p in g.processes if pid_alive(p.pid)]
    metrics = json.loads((tmp_path / 'graph' / 'metrics.json').read_text())
    reference = Learner(load_task(TASK), SETTINGS, tmp_path / 'batch').run().to_dict()
    got, want = metrics['tasks'], reference['tasks']
    assert [r['rollouts'] for r in got] == [r['rollouts'] for r in want]
    np.testing.assert_allclose([r['best_reward'] for r in got], [r['best_reward'] for r in want],
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(metrics['summary']['test_rewards'],
                               reference['summary']['test_rewards'], rtol=0, atol=1e-9)
    # both workers ran rollouts (the one in namespace B too), none twice
    counts = {topic: count for topic, (_, count) in read_bag_summary(tmp_path / 'bag').items()}
    assert counts.get('/worker0/rollout_evaluation', 0) > 0, counts
    assert counts.get('/worker1/rollout_evaluation', 0) > 0, counts
    assert sum(counts.values()) <= metrics['summary']['total_rollouts'] + SETTINGS.num_test
