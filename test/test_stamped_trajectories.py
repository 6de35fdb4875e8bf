"""The controller (a process of its own) and stamped trajectories, driven by joint states this
test stamps itself: a trajectory stamped in the future is acknowledged on /diagnostics
(``trajectory taken``) and, until its start, the trajectory that ran before goes on (its last
point's feed-forward: a homing's hold is not replaced early by the next trajectory's first
torque); one stamped in the past is refused and reported (``late trajectory``)."""
import threading

import numpy as np
import pytest
from builtin_interfaces.msg import Duration
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from psl_ros import names
from psl_ros.client import RosClient
from psl_ros.graph import NODES, Graph, pid_alive
from psl_ros.matching import PUBLISHER, SUBSCRIPTION, MatchedEndpoints
from psl_ros.qos import RELIABLE
from psl_ros.stamps import time_msg, to_ns
from psl_task.arm_model import joint_names_of
from psl_task.task import load_task

NAMESPACE = 'stamped'
TASK = 'reach_over_obstacle'
MS = 1_000_000          # ns


@pytest.fixture(scope='module')
def controller(tmp_path_factory):
    g = Graph(task=TASK, namespace=NAMESPACE,
              nodes=tuple(n for n in NODES if n[0] == 'pd_controller'),
              log_dir=tmp_path_factory.mktemp('stamped_logs'))
    try:
        g.start()
        yield g
    finally:
        g.stop()
        assert not [p.name for p in g.processes if pid_alive(p.pid)]


class Bench:
    """Joint states and trajectories in, references and the controller's reports out."""

    def __init__(self, node, wait_until):
        self.node, self.wait_until = node, wait_until
        self.task = load_task(TASK)
        self.joints = joint_names_of(self.task)
        self.lock = threading.Lock()
        self.references: dict[int, JointState] = {}
        self.reports: dict[tuple[str, int], str] = {}
        topic = f'/{NAMESPACE}/'
        self.states = node.create_publisher(JointState, topic + names.JOINT_STATES, RELIABLE)
        self.trajectories = node.create_publisher(JointTrajectory,
                                                  topic + names.JOINT_TRAJECTORY, RELIABLE)
        node.create_subscription(JointState, topic + names.REFERENCE, self._on_reference,
                                 RELIABLE)
        node.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self._on_diagnostics, 100)
        self.matched = MatchedEndpoints(node)          # this node is in NAMESPACE
        controller = f'/{NAMESPACE}/pd_controller'
        for kind, name in ((SUBSCRIPTION, names.JOINT_STATES),
                           (SUBSCRIPTION, names.JOINT_TRAJECTORY),
                           (PUBLISHER, names.REFERENCE)):
            resolved = topic + name
            assert wait_until(lambda: self.matched.counts(kind, resolved).get(controller, 0)
                              >= 1, 30.0), f'the controller did not match {resolved}'

    def _on_reference(self, msg):
        with self.lock:
            self.references[to_ns(msg.header.stamp)] = msg

    def _on_diagnostics(self, msg):
        prefix = f'/{NAMESPACE}/pd_controller: '
        with self.lock:
            for status in msg.status:
                if status.name.startswith(prefix):
                    values = {kv.key: kv.value for kv in status.values}
                    self.reports[(status.name[len(prefix):],
                                  int(values['trajectory_start_ns']))] = status.message

    def state(self, t_ns: int, q) -> JointState:
        """Publish a state stamped t_ns; the reference the controller answered it with."""
        self.states.publish(JointState(header=dict_header(t_ns), name=self.joints,
                                       position=list(map(float, q)),
                                       velocity=[0.0] * len(self.joints)))
        assert self.wait_until(lambda: t_ns in self.references, 15.0), \
            f'no reference for the state at {t_ns * 1e-9:.3f} s'
        return self.references[t_ns]

    def trajectory(self, start_ns: int, q, effort, points: int = 3) -> None:
        msg = JointTrajectory(joint_names=self.joints)
        msg.header.stamp = time_msg(start_ns)
        for k in range(points):
            msg.points.append(JointTrajectoryPoint(
                positions=list(map(float, q)), velocities=[0.0] * len(q),
                effort=list(map(float, effort)),
                time_from_start=Duration(sec=0, nanosec=2 * MS * k)))
        self.trajectories.publish(msg)

    def report(self, what: str, start_ns: int) -> str:
        assert self.wait_until(lambda: (what, start_ns) in self.reports, 15.0), \
            f'no {what!r} report for the trajectory at {start_ns * 1e-9:.3f} s'
        return self.reports[(what, start_ns)]


def dict_header(t_ns: int):
    from std_msgs.msg import Header
    return Header(stamp=time_msg(t_ns), frame_id='')


def test_a_future_trajectory_waits_for_its_start_and_a_past_one_is_refused(controller,
                                                                           wait_until):
    with RosClient(NAMESPACE) as client:
        bench = Bench(client.node, wait_until)
        q = bench.task.start_posture
        n = len(q)
        t = 1_000 * MS
        bench.state(t, q)                           # the controller holds this posture
        held, first = np.full(n, 1.5), np.full(n, -2.5)
        bench.trajectory(t + 10 * MS, q, held)      # a "homing hold": its torque held
        bench.report('trajectory taken', t + 10 * MS)
        for k in range(1, 11):                      # through it and past its end
            reference = bench.state(t + k * 2 * MS, q)
        np.testing.assert_array_equal(reference.effort, held)
        # the next trajectory, stamped 0.2 s ahead, with another first torque
        start = t + 220 * MS
        bench.trajectory(start, q, first)
        bench.report('trajectory taken', start)
        before = bench.state(start - 100 * MS, q)
        np.testing.assert_array_equal(before.effort, held)   # not `first` before its start
        at = bench.state(start, q)
        np.testing.assert_array_equal(at.effort, first)
        # stamped before the newest state: refused, and the controller goes on
        late = start - 50 * MS
        bench.trajectory(late, q, np.zeros(n))
        assert 'after its start' in bench.report('late trajectory', late)
        assert ('trajectory taken', late) not in bench.reports
        np.testing.assert_array_equal(bench.state(start + 2 * MS, q).effort, first)
