"""Integration tests: the nodes run as separate processes over real DDS, on the ROS domain
of this test run (the root conftest.py)."""
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from psl_ros.graph import Graph, pid_alive
from psl_ros.client import RosClient, evaluation_dict

# graph mode against batch mode: the same law on the same states, only the order of the
# floating-point additions differs
Q_TOLERANCE = 1e-9          # rad, joint angles at every control period
REWARD_TOLERANCE = 1e-9     # reward, absolute
COMPONENT_RTOL, COMPONENT_ATOL = 1e-9, 1e-12
DELIVERY_TIMEOUT = 10.0     # s, for messages already published to reach a test's subscription

# the helper modules of this folder (docs_commands.py) importable by its test files, which
# pytest imports by path (--import-mode=importlib)
sys.path.insert(0, str(Path(__file__).resolve().parent))


def poll_until(condition, timeout: float, period: float = 0.01) -> bool:
    """Call `condition` until it is true (True) or `timeout` s have passed (False); what a
    test waits on instead of a sleep of a guessed length."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(period)
    return True


@pytest.fixture(scope='session')
def wait_until():
    """`poll_until` for the tests of this folder."""
    return poll_until


def check_watchdog_silence(reason: str) -> float:
    """The silence the controller's watchdog measured on its own clock when it fired, read
    from its abort reason ('joint states stopped: none for X s (state_timeout T s)'), held to
    X >= T: it did not fire before its timeout. No upper bound: X is measured on a Python
    process's clock, late by whatever the machine's load keeps it from running; that the
    watchdog looks every control period and fires at the first look past T is held on its
    own ticks (src/psl_controller/test/test_watchdog.py). Returns X."""
    import re
    found = re.search(r'none for ([0-9.]+) s \(state_timeout ([0-9.eE+-]+) s\)', reason)
    assert found, f'no measured silence in the reason: {reason!r}'
    silence, timeout = float(found[1]), float(found[2])
    # X is printed to the millisecond: above T within that rounding
    assert silence >= timeout - 5e-4, (
        f'the watchdog fired after {silence} s of silence, before its timeout {timeout} s')
    return silence


@pytest.fixture(scope='session')
def watchdog_silence():
    """`check_watchdog_silence` for the tests of this folder."""
    return check_watchdog_silence


@pytest.fixture(scope='module')
def graph_task():
    """The task (name or YAML path) the module's graph starts with; a module overrides this
    fixture to run the graph on another task or robot."""
    return 'reach_over_obstacle'


@pytest.fixture(scope='module')
def graph_options(tmp_path_factory):
    """More keyword arguments of the module's `Graph` (none); a module overrides this fixture
    to start the graph with them (e.g. the view node)."""
    return {}


@pytest.fixture(scope='module')
def graph(tmp_path_factory, graph_task, graph_options):
    """The robot loop in lockstep, one process per node; ended by PID whatever happens."""
    g = Graph(task=graph_task, log_dir=tmp_path_factory.mktemp('graph_logs'), **graph_options)
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


@pytest.fixture(scope='module')
def graph_matches_batch(client):
    """A check: roll out theta on (task, tau) through the graph (recording its joint_states)
    and in batch mode (with `law`, default the task's: what the graph's controller runs);
    assert that the joint trajectories, the rewards and every reward
    component agree; return (graph evaluation, batch result)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_task.task import task_id

    def check(task, tau, theta, law=None):
        states = {}
        sub = client.node.create_subscription(
            JointState, 'joint_states',
            lambda m: states.__setitem__(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m),
            QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE))
        try:
            client.wait_for_subscribers(['joint_states'], subscriptions=[sub])
            result = client.rollout(task_id(task), tau, theta)
            assert result.success, result.message
            stamp = result.evaluation.stamp
            t0 = stamp.sec * 10**9 + stamp.nanosec
            steps = task.num_steps_of(tau)
            episode = [t0 + k * task.control_period_ns for k in range(steps + 1)]
            # the evaluator has scored every state; this subscription may still be receiving
            assert poll_until(lambda: all(t in states for t in episode), DELIVERY_TIMEOUT), \
                f'{sum(t in states for t in episode)} of {len(episode)} joint_states recorded'
        finally:
            client.node.destroy_subscription(sub)
        q_graph = np.array([states[t].position for t in episode])
        batch = BatchRollouts(task, law=law).run(np.asarray(theta)[None], tau)[0]
        assert q_graph.shape == batch.q.shape == (steps + 1, task.n_joints)
        assert np.abs(q_graph - batch.q).max() < Q_TOLERANCE
        assert result.evaluation.reward == pytest.approx(batch.evaluation.reward,
                                                         abs=REWARD_TOLERANCE)
        graph_components = evaluation_dict(result.evaluation)['components']
        for name, value in batch.evaluation.components.items():
            assert graph_components[name] == pytest.approx(value, rel=COMPONENT_RTOL,
                                                           abs=COMPONENT_ATOL)
        return result.evaluation, batch
    return check
