"""The skill_memory node as a separate process: services, bad requests, concurrency, restart.

The tests share one node (module scope) and are independent of their order: each uses skills
of its own name or the `curve` fixture's (made once if it is missing), and the test that
kills a node kills one of its own."""
import json
import math
import os
import signal
import threading
from pathlib import Path

import numpy as np
import pytest

from psl_ros.graph import Graph, pid_alive
from psl_ros.client import RosClient

MEMORY_NODE = (('skill_memory', 'psl_memory', 'skill_memory'),)
TASK_SKILL = 'reach_over_obstacle'


KILLED_NS = 'killed_memory'     # the killed node's namespace: apart from the module's node


def start_memory(log_dir, autosave, namespace: str = ''):
    graph = Graph(nodes=MEMORY_NODE, log_dir=log_dir, namespace=namespace,
                  extra_params={'skill_memory': {'autosave_path': str(autosave)}})
    try:
        graph.start()
    except BaseException:
        graph.stop()
        raise
    return graph


def stop(graph):
    graph.stop()
    assert not [p.name for p in graph.processes if pid_alive(p.pid)]


@pytest.fixture(scope='module')
def autosave(tmp_path_factory):
    return tmp_path_factory.mktemp('memory') / 'autosave.npz'


@pytest.fixture(scope='module')
def memory_node(tmp_path_factory, autosave):
    graph = start_memory(tmp_path_factory.mktemp('memory_logs'), autosave)
    try:
        yield graph
    finally:
        stop(graph)


@pytest.fixture(scope='module')
def client(memory_node):
    with RosClient() as c:
        assert c.memory('info', timeout=30).success
        yield c


def add_curve(client, skill: str) -> None:
    """12 samples of theta = [sin 2 tau, tau^2, cos tau] on tau in [0, 1] into a new skill."""
    for i, tau in enumerate(np.linspace(0.0, 1.0, 12)):
        theta = [math.sin(2 * tau), tau ** 2, math.cos(tau)]
        response = client.memory('add_sample', skill=skill, tau=[float(tau)], theta=theta)
        assert response.success, response.message
        assert response.num_samples == i + 1


@pytest.fixture
def curve(client) -> str:
    """The skill `curve` (1 task parameter, 3 policy parameters), made if it is missing."""
    if 'curve' not in info(client):
        add_curve(client, 'curve')
    return 'curve'


def info(client) -> dict:
    response = client.memory('info')
    assert response.success
    return json.loads(response.message)


def create_task_skill(client, **override):
    """create_skill with the ranges and default policy of the embedded task."""
    from psl_controller.policy import policy_for
    from psl_task.task import load_task
    task = load_task(TASK_SKILL)
    fields = dict(skill=TASK_SKILL, tau_low=task.tau_low.tolist(),
                  tau_high=task.tau_high.tolist(),
                  theta_reference=policy_for(task).default_theta.tolist())
    return client.memory('create_skill', **{**fields, **override})


def test_a_task_skill_is_created_by_whoever_knows_the_task(client):
    assert TASK_SKILL not in info(client)          # the memory knows no tasks
    response = create_task_skill(client)
    assert response.success and response.created, response.message
    skills = info(client)
    assert skills[TASK_SKILL]['tau_dim'] == 2 and skills[TASK_SKILL]['theta_dim'] == 24
    response = client.memory('query', skill=TASK_SKILL, tau=[0.6, 0.2])
    assert response.success and len(response.theta) == 24 and len(response.variance) == 24
    again = create_task_skill(client)              # a second call keeps it
    assert again.success and not again.created and 'kept' in again.message
    assert info(client) == skills


def test_add_query_complete_round_trip(client):
    rng = np.random.default_rng(1)
    add_curve(client, 'round_trip')
    tau = 4.5 / 11      # midway between two samples: the nearest sample is 0.059 off there
    response = client.memory('query', skill='round_trip', tau=[tau])
    assert response.success
    assert np.allclose(response.theta, [math.sin(2 * tau), tau ** 2, math.cos(tau)], atol=0.03)
    # theta -> tau through the associative memory
    theta = [math.sin(2 * tau), tau ** 2, math.cos(tau)]
    response = client.memory('complete', skill='round_trip',
                             pattern=[float(rng.uniform())] + theta,
                             known=[False, True, True, True])
    assert response.success, response.message
    assert list(response.pattern[1:]) == theta                # clamped entries untouched
    assert abs(response.pattern[0] - tau) < 0.05


BAD_REQUESTS = [
    ('query', {'skill': 'nope', 'tau': [0.5]}, 'unknown skill'),
    ('query', {'skill': 'curve', 'tau': [0.5, 0.1]}, 'tau with 1 entries, got 2'),
    ('query', {'skill': 'curve', 'tau': [float('nan')]}, 'NaN'),
    ('add_sample', {'skill': 'curve', 'tau': [0.5], 'theta': [1.0, 2.0]},
     'theta with 3 entries, got 2'),
    ('add_sample', {'skill': 'curve', 'tau': [float('inf')], 'theta': [1.0, 2.0, 3.0]},
     'NaN or inf'),
    ('add_sample', {'skill': 'fresh', 'tau': [], 'theta': [1.0]}, 'non-empty'),
    ('add_sample', {'skill': '', 'tau': [1.0], 'theta': [1.0]}, 'needs a name'),
    ('complete', {'skill': 'curve', 'pattern': [0.1, 0.2, 0.3, 0.4], 'known': [True, False]},
     'known needs 4 entries'),
    ('complete', {'skill': 'curve', 'pattern': [0.1, 0.2], 'known': [True, False]},
     'known needs 4 entries'),
    ('complete', {'skill': 'nope', 'pattern': [0.1], 'known': [True]}, 'unknown skill'),
    ('save', {'path': '/nonexistent_folder/memory.npz'}, 'outside the memory folder'),
    ('save', {'path': ''}, 'give a file name'),
    ('load', {'path': '/nonexistent_folder/memory.npz'}, 'outside the memory folder'),
    ('load', {'path': 'no_such_memory_file.npz'}, 'no such file'),
    ('query', {'skill': 'curve', 'tau': [-1e308]}, 'a units or scaling error'),
    ('add_sample', {'skill': 'curve', 'tau': [0.5], 'theta': [1e308, 2.0, 3.0]},
     'a units or scaling error'),
    ('create_skill', {'skill': 'curve', 'tau_low': [0.0, 0.0], 'tau_high': [1.0, 1.0],
                      'theta_reference': [0.0, 0.0, 0.0]}, 'exists with 1 task'),
    ('create_skill', {'skill': 'new', 'tau_low': [1.0], 'tau_high': [0.0],
                      'theta_reference': [0.0]}, 'high > low'),
    ('create_skill', {'skill': 'new', 'tau_low': [0.0], 'tau_high': [1.0],
                      'theta_reference': [float('nan')]}, 'finite'),
    ('create_skill', {'skill': 'new', 'tau_low': [0.0], 'tau_high': [1.0],
                      'theta_reference': []}, 'at least one'),
    ('create_skill', {'skill': '', 'tau_low': [0.0], 'tau_high': [1.0],
                      'theta_reference': [0.0]}, 'needs a name'),
]


@pytest.mark.parametrize('service, fields, words', BAD_REQUESTS)
def test_bad_requests_get_clear_errors_and_change_nothing(client, curve, service, fields,
                                                          words):
    before = info(client)
    query_before = client.memory('query', skill='curve', tau=[0.3]).theta
    response = client.memory(service, **fields)
    assert not response.success
    assert words in response.message, response.message
    assert info(client) == before
    assert list(client.memory("query", skill="curve", tau=[0.3]).theta) == list(query_before)


def test_memory_files_stay_inside_the_memory_folder(client, tmp_path, memory_folder):
    """The node's memory_dir is this test process's temporary folder here (conftest.py
    `memory_folder`): nothing outside it is written or read, no link is followed, no device,
    FIFO or folder replaced."""
    before = info(client)
    root = memory_folder
    outside = root.parent / f'psl-never-{os.getpid()}.npz'        # next to the folder
    victim = tmp_path / 'victim.txt'
    victim.write_text('keep me')
    link = tmp_path / 'link.npz'
    link.symlink_to(victim)
    fifo = tmp_path / 'pipe.npz'
    os.mkfifo(fifo)
    for path, words in ((str(outside), 'outside the memory folder'),
                        (f'../{outside.name}', 'outside the memory folder'),
                        (str(tmp_path / os.path.relpath(outside, tmp_path)), 'outside'),
                        (str(link), 'symbolic link'), (str(fifo), 'not a regular file'),
                        (str(tmp_path), 'is a directory')):
        for service in ('save', 'load'):
            response = client.memory(service, path=path)
            assert not response.success and words in response.message, (service, path,
                                                                          response.message)
    assert not outside.exists()
    assert victim.read_text() == 'keep me' and link.is_symlink()
    assert fifo.exists() and not fifo.is_file()
    assert info(client) == before
    inside = tmp_path / 'inside.npz'                               # a path inside works
    assert client.memory('save', path=str(inside)).success and inside.is_file()
    name = f'psl-memory-test-{os.getpid()}.npz'                    # so does a bare name
    try:
        assert client.memory('save', path=name).success and (root / name).is_file()
        assert client.memory('load', path=name, replace=True).success
    finally:
        (root / name).unlink(missing_ok=True)
    assert info(client) == before


def test_a_file_declaring_gigabytes_is_refused_before_it_is_read(client, tmp_path):
    """A small zip whose array inflates to more than the node's limit (256 MB): refused from
    the archive's declared sizes, nothing inflated, the memory kept."""
    import zipfile
    before = info(client)
    bomb = tmp_path / 'bomb.npz'
    header = np.lib.format.header_data_from_array_1_0(np.zeros(1))
    header['shape'] = (300 * 2**20 // 8,)
    with zipfile.ZipFile(bomb, 'w', zipfile.ZIP_DEFLATED) as archive:
        with archive.open('__meta__.npy', 'w', force_zip64=True) as member:
            np.lib.format.write_array_header_1_0(member, header)
            zeros = bytes(2**20)
            for _ in range(300):
                member.write(zeros)
    assert bomb.stat().st_size < 2**20 * 2                        # small on disk
    response = client.memory('load', path=str(bomb))
    assert not response.success and 'more than the limit' in response.message, response.message
    assert info(client) == before


def test_corrupt_file_is_refused_and_memory_kept(client, tmp_path):
    before = info(client)
    good = tmp_path / 'good.npz'
    assert client.memory('save', path=str(good)).success
    data = good.read_bytes()
    truncated = tmp_path / 'truncated.npz'
    truncated.write_bytes(data[: len(data) // 2])
    garbage = tmp_path / 'garbage.npz'
    garbage.write_bytes(os.urandom(4096))
    for path in (truncated, garbage):
        response = client.memory('load', path=str(path))
        assert not response.success and 'unchanged' in response.message
        assert info(client) == before
    assert client.memory('load', path=str(good), replace=True).success
    assert info(client) == before


def test_four_concurrent_clients_lose_no_sample(client):
    assert 'concurrent' not in info(client)
    per_client, errors = 15, []

    def work(k: int):
        try:
            with RosClient(name=f'worker{k}') as c:
                for i in range(per_client):
                    tau = [k + i / per_client]
                    r = c.memory('add_sample', skill='concurrent', tau=tau,
                                 theta=[float(k), float(i)], timeout=30)
                    if not r.success:
                        errors.append(r.message)
                    q = c.memory('query', skill='concurrent', tau=tau, timeout=30)
                    if not q.success:
                        errors.append(q.message)
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(repr(exc))

    threads = [threading.Thread(target=work, args=(k,), daemon=True) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not any(t.is_alive() for t in threads), 'a client did not end within 120 s'
    assert not errors
    assert info(client)['concurrent']['num_samples'] == 4 * per_client


def test_ten_new_clients_under_load_lose_no_answer():
    """8 querying and 2 adding client processes at once, each new to the server: before
    psl_ros.service (a deep service history; answers resent to a client the server has not
    matched yet) about 1 in 140 answers never came."""
    from psl_bench.memory_load import measure
    # lost = never answered: the deadline is far beyond any answer time (p99 below 0.4 s
    # with a core busy, docs/benchmarks.md), so a slow machine is not mistaken for a loss;
    # the answer times are the benchmark's (psl bench memory-load); 1,260 calls: about 9
    # lost at the old rate, none lost by chance in e^-9
    report = measure(clients=8, adders=2, calls=150, timeout=60.0)
    assert report['query']['lost'] == 0 and report['add']['lost'] == 0, report
    assert report['unavailable'] == 0, report
    assert report['query']['calls'] == 8 * 150
    assert report['samples_held'] == report['samples_expected'] == 1 + 2 * 30


def test_killed_node_restarts_with_what_it_learned(tmp_path):
    """A node of its own (its own namespace and autosave file), killed with SIGKILL and started
    again: it answers as before."""
    autosave = tmp_path / 'autosave.npz'
    first = start_memory(tmp_path / 'logs', autosave, namespace=KILLED_NS)
    try:
        with RosClient(KILLED_NS) as c:
            add_curve(c, 'curve')
            before = info(c)
            answer = c.memory('query', skill='curve', tau=[0.37])
        assert autosave.is_file()
        node = first.processes[0]
        os.kill(node.pid, signal.SIGKILL)       # a child of this test, not yet reaped: its own
        node.process.wait(timeout=10)
    finally:
        stop(first)
    restarted = start_memory(tmp_path / 'logs_again', autosave, namespace=KILLED_NS)
    try:
        with RosClient(KILLED_NS) as fresh:
            assert fresh.memory('info', timeout=30).success
            assert info(fresh) == before
            again = fresh.memory('query', skill='curve', tau=[0.37])
            assert list(again.theta) == list(answer.theta)
            assert list(again.variance) == list(answer.variance)
    finally:
        stop(restarted)
