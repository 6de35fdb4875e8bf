"""The benchmarks' own readers and Ray's address (issue 46): a damaged run file is one
ValueError naming it; a Ray address with no cluster is refused at once, naming it; a sweep in
which no session finished raises with why instead of a table of nothing."""
import json
import socket

import pytest

from psl_bench import sessions
from psl_bench.learn import SESSION_FILE, _timing


@pytest.mark.parametrize('content, words', [
    (b'', 'damaged'), (b'{"session_seconds": 1', 'damaged'), (b'\xff\xfe\x00', 'damaged'),
    (b'[1, 2]', r'damaged \(not an object of numbers'),
    (b'{"session_seconds": "x"}', r'damaged \(not an object of numbers'),
])
def test_a_damaged_session_file_is_refused_naming_it(tmp_path, content, words):
    path = tmp_path / SESSION_FILE
    path.write_bytes(content)
    with pytest.raises(ValueError, match=f'^{path}: {words}'):
        _timing(path)


def test_a_session_file_is_read_absent_is_none_and_a_directory_is_refused(tmp_path):
    path = tmp_path / SESSION_FILE
    assert _timing(path) == {}
    path.write_text(json.dumps({'session_seconds': 2.5, 'simulation_share': 0.5}))
    assert _timing(path) == {'session_seconds': 2.5, 'simulation_share': 0.5}
    path.unlink()
    path.mkdir()
    with pytest.raises(ValueError, match=f'^{path}: damaged'):
        _timing(path)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def test_an_address_with_no_cluster_is_refused_naming_it():
    address = f'127.0.0.1:{free_port()}'
    with pytest.raises(RuntimeError, match=f'^no Ray cluster at {address}'):
        sessions.check_reachable(address)
    with pytest.raises(RuntimeError, match=f'^no Ray cluster at ray://{address}: '):
        sessions.check_reachable(f'ray://{address}')


def test_the_address_in_the_environment_is_checked_before_ray_joins(monkeypatch):
    """$RAY_ADDRESS to where no cluster is: refused naming it (before: ray.init retried for
    minutes); the sweep's cluster is not joined."""
    import ray
    address = f'127.0.0.1:{free_port()}'
    monkeypatch.setenv(sessions.ADDRESS_VARIABLE, address)
    with pytest.raises(RuntimeError, match=f'^no Ray cluster at {address}'):
        with sessions.cluster('ray'):
            pass
    assert not ray.is_initialized()


def test_an_address_that_answers_passes_and_local_and_auto_are_rays():
    with socket.socket() as server:
        server.bind(('0.0.0.0', 0))
        server.listen(1)
        sessions.check_reachable(f'127.0.0.1:{server.getsockname()[1]}')
    sessions.check_reachable('local')
    sessions.check_reachable('auto')


@pytest.mark.parametrize('address', ['nonsense', '127.0.0.1', 'host:port', ':6379',
                                     '127.0.0.1:0', '127.0.0.1:70000'])
def test_an_address_that_is_no_host_and_port_is_a_value_error(address):
    with pytest.raises(ValueError, match='give HOST:PORT'):
        sessions.check_reachable(address)


def failing(name: str) -> dict:
    raise ValueError(f'{name}: damaged')


def test_a_sweep_in_which_no_session_finished_raises_with_why():
    plan = [sessions.Session(key=(k,), label=f'session {k}', function=failing,
                             kwargs={'name': f'file{k}'}) for k in range(2)]
    with pytest.raises(RuntimeError, match=r'^no session of the sweep finished: \(0,\): '
                                           r'ValueError: file0: damaged; \(1,\): ValueError'):
        sessions.run(plan, 'serial')


def test_a_local_address_is_checked_where_ray_joins_it():
    """Ray joins 127.0.0.1:PORT at its node's address: a server on the loopback alone is no
    cluster Ray could join, and is refused naming both."""
    from ray._private.services import get_node_ip_address
    node = get_node_ip_address()
    if node.startswith('127.'):
        pytest.skip(f"this machine's node address is the loopback ({node})")
    with socket.socket() as server:
        server.bind(('127.0.0.1', 0))
        server.listen(1)
        address = f'127.0.0.1:{server.getsockname()[1]}'
        with pytest.raises(RuntimeError, match=f'^no Ray cluster at {address} \\(joined at '
                                               f'{node}:{server.getsockname()[1]}\\): '):
            sessions.check_reachable(address)
