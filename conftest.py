"""The whole suite: ROS domains that no two processes of any test run share, discovery on this
machine only, and a memory folder of the run's own.

A ROS domain is claimed by an exclusive lock (``fcntl.flock``) on a file of its own in the
system's temporary folder, ``psl-ros-domain-<id>.lock``, held for the life of the process that
claimed it: the kernel releases it when that process ends, however it ends (SIGKILL included),
so a domain is never left claimed and never claimed twice, whichever runs, workers and
checkouts share the machine. The files are made once and never written or removed (removing
one would let two processes lock two different files of one name).

- Each process that runs tests (the only one, or each pytest-xdist worker) claims the run's
  domain at start (`pytest_configure`), before anything starts: every process a test starts
  inherits it (``ROS_DOMAIN_ID``).
- A test that needs a domain where nothing else runs, not even its own worker's graphs (a node
  in the test's process: test_sim_commands.py, test_bag_recorder.py, test_watchdog.py), takes
  `private_ros_domain`: one more domain claimed the same way, once per process.

The run's domains are the first free ids of `DOMAINS` from ``PSL_TEST_DOMAIN_ID`` upward
(default: the first), the private ones the first free from the last id downward: a run given
``PSL_TEST_DOMAIN_ID=51`` on two workers runs its graphs on 51 and 52, its private nodes on
100 and 99.
"""
from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path

import pytest

# the ids whose DDS ports lie below Linux's ephemeral port range (Fast DDS: 7400 + 250 x id):
# 1..100; 0 (ROS's default) and 42 (scripts/env.sh's) are where a user's own graph runs
DOMAINS = tuple(i for i in range(1, 101) if i != 42)
LOCK_FILE = 'psl-ros-domain-{}.lock'
# the system's temporary folder, where every run finds the lock files (read before this
# process's TMPDIR becomes its own: `memory_folder`)
SYSTEM_TMP = Path(tempfile.gettempdir())
_claimed: dict[int, int] = {}       # domain -> the locked file's descriptor, open for life


def claim_domain(private: bool = False) -> int:
    """A domain no other process holds, held by this process until it ends: the run's, or
    with `private` one of the top (module docstring). Raises RuntimeError when every id of
    `DOMAINS` is held."""
    first = int(os.environ.get('PSL_TEST_DOMAIN_ID', DOMAINS[0]))
    order = [d for d in DOMAINS if d >= first] + [d for d in DOMAINS if d < first]
    if private:
        order = list(reversed(DOMAINS))
    folder = SYSTEM_TMP
    for domain in order:
        if domain in _claimed:
            continue
        fd = os.open(folder / LOCK_FILE.format(domain), os.O_RDONLY | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:             # held by another process
            os.close(fd)
            continue
        _claimed[domain] = fd
        return domain
    raise RuntimeError(f'every ROS domain of {DOMAINS[0]}..{DOMAINS[-1]} is held by another '
                       f'test process (lock files {folder / LOCK_FILE.format("*")})')


def pytest_configure(config):
    """The run's domain for a process that runs tests (not xdist's controller, which runs
    none)."""
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    controller = (getattr(config.option, 'numprocesses', None)
                  and not hasattr(config, 'workerinput'))
    if not controller:
        os.environ['ROS_DOMAIN_ID'] = str(claim_domain())


@pytest.fixture(scope='session')
def private_ros_domain() -> int:
    """A domain of this process's own, where none of the run's graphs runs (module
    docstring); a test sets it as ``ROS_DOMAIN_ID`` before rclpy.init."""
    return claim_domain(private=True)


@pytest.fixture(scope='session', autouse=True)
def memory_folder(tmp_path_factory) -> Path:
    """This process's own temporary folder (pytest's base folder: every tmp_path lies in it)
    for what the tests and the processes they start keep: the memory nodes' files
    (``PSL_MEMORY_DIR``: a memory node refuses paths outside its memory_dir, and a bare name
    lands here) and every temporary file (``TMPDIR``: its ``tmp``), never the system's
    temporary folder; Ray's session folders stay where Ray keeps them (``RAY_TMPDIR``: its
    sockets' paths must stay short)."""
    folder = tmp_path_factory.getbasetemp()
    os.environ['PSL_MEMORY_DIR'] = str(folder)
    (folder / 'tmp').mkdir(exist_ok=True)
    os.environ.setdefault('RAY_TMPDIR', str(SYSTEM_TMP))
    os.environ['TMPDIR'] = str(folder / 'tmp')
    return folder


@pytest.fixture(scope='session')
def ray_cluster():
    """One local Ray cluster for the tests of this process that run sweeps on Ray (the sweeps
    join it: `psl_bench.sessions.cluster`), started at the first of them and ended with the
    process's tests: a cluster's start and its workers' imports once, not per test (its
    workers are this process's descendants, through its raylet)."""
    from psl_bench import sessions
    with sessions.cluster('ray'):
        yield
