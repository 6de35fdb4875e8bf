"""Integration tests: the nodes run as separate processes over real DDS.

Every test session gets its own ROS_DOMAIN_ID (set before anything starts, inherited by
every process a test starts) so concurrent runs on one machine do not see each other, and
discovery stays on this machine.
"""
import os

os.environ['ROS_DOMAIN_ID'] = os.environ.get('PSL_TEST_DOMAIN_ID', str(1 + os.getpid() % 100))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

import pytest  # noqa: E402

from psl_cli.graph import Graph, pid_alive  # noqa: E402
from psl_cli.ros_client import RosClient  # noqa: E402


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    """The robot loop in lockstep, one process per node; ended by PID whatever happens."""
    g = Graph(log_dir=tmp_path_factory.mktemp('graph_logs'))
    try:
        g.start()
        g.wait_ready(timeout=60)
        yield g
    finally:
        g.stop()
        left = [p.name for p in g.processes if pid_alive(p.pid)]
        assert not left, f'processes left behind: {left}'


@pytest.fixture(scope='module')
def client(graph):
    with RosClient() as c:
        yield c
