"""Workers on other hosts, for real: two rollout workers in network namespaces of their own,
joined by a veth pair; discovery over that subnet only (ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET
inside the namespaces, whose only link is the pair: nothing beyond them). The skill memory,
the learner and worker0 run in namespace A, worker1 in namespace B; a graph-mode session
across them equals the in-process batch session. Needs root with CAP_NET_ADMIN and
CAP_SYS_ADMIN and iproute2 (ip netns); skipped without them, failed if they are there but
the namespaces cannot be made."""
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_ros.bag_recorder import read_bag_summary
from psl_ros.graph import Graph
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
EVALUATIONS = ('/worker0/rollout_evaluation', '/worker1/rollout_evaluation')
SETTINGS = LearnSettings(strategy='scratch', num_tasks=2, seed=7, num_test=2,
                         search=SearchSettings(max_rollouts=12))


SERIAL = itertools.count()
CAP_NET_ADMIN, CAP_SYS_ADMIN = 12, 21    # linux/capability.h: links, addresses; unshare, mount


def ip(*args: str) -> None:
    """Run `ip args`; AssertionError with what ip said if it fails."""
    done = subprocess.run(['ip', *args], capture_output=True, text=True, timeout=10)
    assert done.returncode == 0, f'ip {" ".join(args)}: {done.stderr.strip()}'


def effective_capabilities() -> int:
    with open('/proc/self/status') as f:
        return int(next(line for line in f if line.startswith('CapEff:')).split()[1], 16)


def why_no_namespaces() -> str:
    """Why this machine cannot make network namespaces at all ('' if it can)."""
    if shutil.which('ip') is None:
        return 'no ip command (iproute2)'
    if os.geteuid() != 0:
        return 'not root'
    missing = [name for name, bit in (('CAP_NET_ADMIN', CAP_NET_ADMIN),
                                      ('CAP_SYS_ADMIN', CAP_SYS_ADMIN))
               if not effective_capabilities() >> bit & 1]
    return f'without {" and ".join(missing)}' if missing else ''


@pytest.fixture
def namespaces():
    """Two network namespaces joined by a veth pair on a /24 of their own; removed after.
    Skipped only where network namespaces cannot be made at all; an ip command that fails
    where they can fails the test."""
    why = why_no_namespaces()
    if why:
        pytest.skip(f'network namespaces need root, CAP_NET_ADMIN, CAP_SYS_ADMIN and iproute2 '
                    f'(ip netns): {why}')
    # names of this process and this fixture: the kernel removes a deleted namespace's links
    # in the background, so a name is not used twice
    tag = f'{os.getpid() % 100000}{next(SERIAL)}'
    a, b = f'psl_a{tag}', f'psl_b{tag}'
    subnet = f'10.231.{os.getpid() % 200 + 20}'
    pair_in_root = False    # the veth pair, made and not in namespace A yet
    try:
        ip('netns', 'add', a)
        ip('netns', 'add', b)
        ip('link', 'add', f'pa{tag}', 'type', 'veth', 'peer', 'name', f'pb{tag}')
        pair_in_root = True
        for ns, dev, host in ((a, f'pa{tag}', 1), (b, f'pb{tag}', 2)):
            ip('link', 'set', dev, 'netns', ns)
            pair_in_root = False
            ip('-n', ns, 'addr', 'add', f'{subnet}.{host}/24', 'dev', dev)
            ip('-n', ns, 'link', 'set', 'lo', 'up')
            ip('-n', ns, 'link', 'set', dev, 'up', 'multicast', 'on')
            ip('-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', dev)     # DDS discovery
        yield a, b
    finally:
        # namespace A takes the pair with it (one end deleted, both go); a pair still in the
        # root namespace goes here
        for ns in (a, b):
            subprocess.run(['ip', 'netns', 'del', ns], capture_output=True, timeout=10)
        if pair_in_root:
            subprocess.run(['ip', 'link', 'del', f'pa{tag}'], capture_output=True, timeout=10)


def inside(ns: str) -> list[str]:
    """Run a command in namespace ns with discovery over its subnet."""
    return ['ip', 'netns', 'exec', ns, 'env', 'ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET']


def test_a_session_across_two_network_namespaces_equals_batch_mode(namespaces, tmp_path,
                                                                   monkeypatch):
    a, b = namespaces
    monkeypatch.setenv('PSL_MEMORY_DIR', str(tmp_path))
    g = Graph(task=TASK, workers=2, log_dir=tmp_path / 'logs',
              launch_prefix={'': inside(a), 'worker0': inside(a), 'worker1': inside(b)})
    recorder, recorder_log = None, tmp_path / 'recorder.log'
    try:
        g.start()
        # every evaluation of each worker, recorded from namespace A: worker1's come over the
        # veth pair from namespace B
        with open(recorder_log, 'w') as log:
            recorder = subprocess.Popen(
                inside(a) + [sys.executable, '-m', 'psl_cli.main', 'record', '-o',
                             str(tmp_path / 'bag'), *EVALUATIONS],
                stdout=subprocess.DEVNULL, stderr=log, start_new_session=True)
        # the session starts once the recorder has subscribed to both workers' evaluations
        # (it says so, with the type, when it has): none of them is missed
        deadline = time.monotonic() + 60
        while not all(f'recording {topic} [' in recorder_log.read_text()
                      for topic in EVALUATIONS):
            assert recorder.poll() is None, recorder_log.read_text()
            dead = g.dead()
            assert not dead, g.describe_death(dead[0])
            assert time.monotonic() < deadline, \
                f'the recorder did not subscribe to {EVALUATIONS}:\n{recorder_log.read_text()}'
            time.sleep(0.05)
        done = subprocess.run(
            inside(a) + [sys.executable, '-m', 'psl_cli.main', 'learn', '--mode', 'graph',
                         '--task', TASK, '--strategy', SETTINGS.strategy, '--tasks',
                         str(SETTINGS.num_tasks), '--budget', str(SETTINGS.search.max_rollouts),
                         '--seed', str(SETTINGS.seed), '--test-tasks', str(SETTINGS.num_test),
                         '--timeout', '90', '-o',
                         str(tmp_path / 'graph')],
            capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert done.returncode == 0, done.stderr + '\n'.join(
            f'--- {p.name}\n{p.tail()}' for p in g.processes)
        recorder.send_signal(signal.SIGINT)
        assert recorder.wait(timeout=30) == 0, recorder_log.read_text()
    finally:
        if recorder is not None and recorder.poll() is None:
            os.killpg(recorder.pid, signal.SIGKILL)
            recorder.wait(timeout=10)
        g.stop()
        assert not [p.name for p in g.processes if p.process.poll() is None]
    metrics = json.loads((tmp_path / 'graph' / 'metrics.json').read_text())
    reference = Learner(load_task(TASK), SETTINGS, tmp_path / 'batch',
                        BatchRollouts(load_task(TASK))).run().to_dict()
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
    refused = sum(r.get('refused', 0) for r in got)
    assert sum(counts.values()) == (metrics['summary']['total_rollouts'] - refused
                                    + SETTINGS.num_test), counts
