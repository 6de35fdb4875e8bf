"""A damaged checkpoint.json in the folder of a session of the learner node (issue 46): the
goal is refused with one message naming the file and what is wrong (before: 'stopped by an
error (Expecting value: line 1 column 1 (char 0))', no file named; a directory of that name was
taken for no checkpoint and the folder's memory.npz written over); nothing is written into the
folder, and the node answers the next goal. The skill memory and learner nodes run as
processes of their own under a namespace of this module, ended by PID."""
import os
import subprocess
import sys

import numpy as np
import pytest

from psl_ros.client import RosClient
from psl_ros.graph import NODES, Graph, pid_alive

TASK = 'reach_over_obstacle'
NAMESPACE = f'damaged_checkpoint_{os.getpid()}'
LEARN_NODES = tuple(n for n in NODES if n[0] in ('skill_memory', 'learner'))
GOAL = dict(task=TASK, strategy='bootstrap', num_tasks=1, max_rollouts_per_task=2, seed=0,
            mode='batch', num_test=1)


@pytest.fixture(scope='module')
def client(tmp_path_factory):
    graph = Graph(nodes=LEARN_NODES, namespace=NAMESPACE,
                  log_dir=tmp_path_factory.mktemp('damaged_checkpoint_logs'),
                  extra_params={'learner': {'output_root': str(
                      tmp_path_factory.mktemp('runs'))}})
    try:
        graph.start()
        with RosClient(NAMESPACE) as c:
            assert c.memory('info', timeout=60).success
            yield c
    finally:
        graph.stop()
        assert not [p.name for p in graph.processes if pid_alive(p.pid)]


def damaged(folder, how: str):
    """A session folder whose checkpoint.json is `how` damaged; a memory.npz beside it that
    must stay as it is."""
    folder.mkdir()
    path = folder / 'checkpoint.json'
    if how == 'directory':
        path.mkdir()
    else:
        path.write_bytes({'empty': b'', 'truncated': b'{"task": "reach_ov',
                          'random bytes': np.random.default_rng(46).bytes(300),
                          'wrong content': b'[1, 2]'}[how])
    (folder / 'memory.npz').write_bytes(b'the memory of the session before')
    return path


def test_psl_learn_through_the_learner_node_names_the_damaged_checkpoint(client, tmp_path):
    out = tmp_path.resolve() / 'run'
    path = damaged(out, 'truncated')
    done = subprocess.run([sys.executable, '-m', 'psl_cli.main', 'learn', '--learner', 'node',
                           '--mode', 'batch', '--namespace', NAMESPACE, '--tasks', '1',
                           '--test-tasks', '1', '--budget', '2', '-o', str(out),
                           '--timeout', '60'],
                          capture_output=True, text=True, timeout=180)
    lines = done.stderr.splitlines()
    assert done.returncode == 1, done.stderr
    assert 'Traceback' not in done.stderr and len(lines) == 1, done.stderr
    assert lines[0].startswith(f'psl learn: {path}: a damaged checkpoint (not JSON'), lines[0]
    assert (out / 'memory.npz').read_bytes() == b'the memory of the session before'


@pytest.mark.parametrize('how, words', [
    ('empty', 'not JSON'), ('random bytes', 'not text'), ('directory', 'not a regular file'),
    ('wrong content', 'a JSON list, not an object')])
def test_the_learner_node_refuses_a_damaged_checkpoint_and_serves_on(client, tmp_path, how,
                                                                     words):
    out = tmp_path / 'run'
    path = damaged(out, how)
    result = client.learn(timeout=120, output_dir=str(out), **GOAL)
    assert not result.success
    assert result.message.startswith(f'{path}: a damaged checkpoint ({words}'), result.message
    assert (out / 'memory.npz').read_bytes() == b'the memory of the session before'
    assert sorted(p.name for p in out.iterdir()) == ['checkpoint.json', 'memory.npz']
    assert client.memory('info', timeout=30).success
