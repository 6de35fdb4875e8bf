"""psl_sim's standard robot as a separate process over DDS, seen as a ros2_control robot with
its own JointTrajectoryController is: joint_states in its own joint order with an extra joint,
stamped with the robot's time (its start plus the periods run: consecutive stamps a whole
number of control periods apart); FollowJointTrajectory served on the effort interface by the
controller inside its loop (the torque it applies, reported as effort, is the law on the state
it reported, with the robot's own gains, JTC's parameters say what it drives); a task instance
placed in its world; its loop's timing reported on /diagnostics; Ctrl-C ends it quietly. Every
wait is on an event with a deadline; the process is ended by its process group in a
finally."""
import contextlib
import os
import signal
import subprocess
import threading
import time

import numpy as np
import pytest
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointTolerance
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from psl_msgs.msg import TaskInstance
from psl_ros import names
from psl_ros.action_client import ActionClient
from psl_ros.client import RosClient, send_goal, wait_for_result
from psl_ros.futures import ask
from psl_ros.graph import find_executable
from psl_ros.qos import LATCHED
from psl_ros.stamps import duration_msg, time_msg, to_ns
from psl_task.task import load_task

TASK = 'reach_over_obstacle'                     # joint1..joint3 at 500 Hz
PERIOD_NS = load_task(TASK).control_period_ns
JOINT_ORDER = ['joint3', 'joint1', 'joint2']     # the robot's joint_states order
EXTRA = 'gripper'
KP, KD = [150.0, 100.0, 50.0], [10.0, 6.0, 2.5]  # its controller's gains (not the task's)
START_TIMEOUT = 30.0      # s, for the process to start and its first states to arrive
EVENT_TIMEOUT = 20.0      # s, for anything that should happen within a second of robot time
TORQUE_LIMIT = 40.0       # N m, reach_over_obstacle's motors
STALL = 0.2               # s the robot's process is stopped for (its loop skips after 0.05 s)


class Robot:
    """The node's process, a client node that records its joint_states and its reports, and
    the node's log."""

    def __init__(self, log_path, namespace: str = '/'):
        self.log_path = log_path
        self.lock = threading.Lock()
        self.states: list[JointState] = []
        self.reports: list[dict] = []
        self._log = open(log_path, 'wb')
        env = dict(os.environ, RCUTILS_LOGGING_BUFFERED_STREAM='0')
        self.process = subprocess.Popen(
            [str(find_executable('psl_sim', 'standard_robot')), '--ros-args',
             '-p', f'task:={TASK}', '-p', f'joint_order:=[{",".join(JOINT_ORDER)}]',
             '-p', f'extra_joints:=[{EXTRA}]', '-p', f'kp:={KP}', '-p', f'kd:={KD}',
             '-r', f'__ns:={namespace}'],
            stdout=self._log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        try:
            self._connect(namespace)
        except BaseException:           # the process ends with the test that made it
            self.stop()
            self._log.close()
            raise

    def _connect(self, namespace: str) -> None:
        self.client = RosClient(namespace, name='standard_robot_test')
        node = self.client.node
        node.create_subscription(JointState, names.JOINT_STATES, self._on_state,
                                 QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE))
        node.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self._on_report, 100)
        self.pub_task = node.create_publisher(TaskInstance, names.TASK_INSTANCE, LATCHED)
        self.action = ActionClient(node, FollowJointTrajectory,
                                   'standard_robot/follow_joint_trajectory')

    def _on_state(self, msg: JointState) -> None:
        with self.lock:
            self.states.append(msg)

    def _on_report(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.endswith('standard_robot: loop'):
                with self.lock:
                    self.reports.append({kv.key: kv.value for kv in status.values})

    def count(self) -> int:
        with self.lock:
            return len(self.states)

    def since(self, k: int) -> list[JointState]:
        with self.lock:
            return list(self.states[k:])

    def log(self) -> str:
        return self.log_path.read_text(errors='replace')

    def stop(self) -> int | None:
        """SIGINT to the process group, then SIGKILL; returns the exit code."""
        for sig, wait in ((signal.SIGINT, 10.0), (signal.SIGKILL, 5.0)):
            if self.process.poll() is not None:
                break
            try:
                os.killpg(self.process.pid, sig)
            except ProcessLookupError:
                break
            try:
                self.process.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                pass
        return self.process.poll()

    def close(self) -> None:
        try:
            self.stop()
        finally:
            self.client.close()
            self._log.close()


@contextlib.contextmanager
def running_robot(log_path, wait_until, namespace: str = '/'):
    """A standard robot process that has published its first states; ended in the end."""
    r = None
    try:
        r = Robot(log_path, namespace)
        assert wait_until(lambda: r.count() >= 10, START_TIMEOUT), \
            f'no joint_states from the standard robot within {START_TIMEOUT} s:\n{r.log()}'
        yield r
    finally:
        if r is not None:
            r.close()
            assert r.process.poll() is not None, 'the standard robot process is left running'


@pytest.fixture(scope='module')
def robot(tmp_path_factory, wait_until):
    """One robot for the module's tests (they run in any order: pytest-randomly)."""
    with running_robot(tmp_path_factory.mktemp('standard_robot') / 'robot.log',
                       wait_until) as r:
        yield r


def positions(msg: JointState) -> dict[str, float]:
    return dict(zip(msg.name, msg.position))


def test_joint_states_are_stamped_with_the_robots_time_in_its_own_order(robot, wait_until):
    """Consecutive stamps are a whole number of control periods apart (one unless its loop
    stalled and skipped periods, which its reports count), in its joint order with the extra
    joint at 0."""
    k = robot.count()
    assert wait_until(lambda: robot.count() >= k + 300, EVENT_TIMEOUT)
    states = robot.since(k)
    stamps = np.array([to_ns(m.header.stamp) for m in states])
    steps = np.diff(stamps)
    assert np.all(steps > 0) and np.all(steps % PERIOD_NS == 0), set(steps.tolist())
    assert all(list(m.name) == JOINT_ORDER + [EXTRA] for m in states)
    assert all((m.position[-1], m.velocity[-1], m.effort[-1]) == (0.0, 0.0, 0.0)
               for m in states)


def test_its_controller_says_what_it_drives(robot):
    parameters = AsyncParameterClient(robot.client.node, 'standard_robot')
    assert parameters.wait_for_services(timeout_sec=EVENT_TIMEOUT)
    values = ask(lambda: parameters.get_parameters(['joints', 'command_interfaces', 'kp']),
                 10.0, 'standard_robot/get_parameters').values
    assert list(values[0].string_array_value) == ['joint1', 'joint2', 'joint3']
    assert list(values[1].string_array_value) == ['effort']
    assert list(values[2].double_array_value) == KP


def test_a_goal_moves_the_arm_by_the_law_on_the_reported_state(robot, wait_until):
    """A one-point goal a second long, a second ahead: the arm comes to it (SUCCESSFUL at its
    end: the goal tolerance erased), and every effort the robot reports is the compliant law,
    with its own gains, on the state it reported one period earlier and the goal's reference
    (the trajectory's segment from the state at the goal's first sample to the point: between
    the two, the reference is known only to the controller, so the law is checked where it is
    the point itself: from the point's time on)."""
    task = load_task(TASK)
    target = {j: float(q) + 0.15 for j, q in zip(['joint1', 'joint2', 'joint3'],
                                                  task.start_posture)}
    newest = robot.since(robot.count() - 1)[-1]
    start = to_ns(newest.header.stamp) + 10**9                    # a second ahead
    goal = FollowJointTrajectory.Goal(trajectory=JointTrajectory(
        joint_names=list(target), points=[JointTrajectoryPoint(
            positions=list(target.values()), velocities=[0.0] * 3,
            time_from_start=duration_msg(10**9))]))
    goal.trajectory.header.stamp = time_msg(start)
    goal.goal_tolerance = [JointTolerance(name=j, position=-1.0, velocity=-1.0)
                           for j in target]
    k = robot.count()
    handle = send_goal(robot.action, goal, EVENT_TIMEOUT, 'standard_robot')
    result = wait_for_result(robot.action, handle, EVENT_TIMEOUT, 'standard_robot')
    assert result.error_code == FollowJointTrajectory.Result.SUCCESSFUL, result.error_string
    end = start + 10**9
    assert wait_until(lambda: sum(to_ns(m.header.stamp) >= end for m in robot.since(k))
                      > 200, EVENT_TIMEOUT)
    states = robot.since(k)
    kp, kd = dict(zip(['joint1', 'joint2', 'joint3'], KP)), dict(zip(['joint1', 'joint2',
                                                                      'joint3'], KD))
    checked = 0
    for before, after in zip(states, states[1:]):
        t = to_ns(before.header.stamp)
        if t < end or to_ns(after.header.stamp) - t != PERIOD_NS:
            continue
        q, qd = positions(before), dict(zip(before.name, before.velocity))
        applied = dict(zip(after.name, after.effort))       # in the period after `before`
        for j in target:
            law = np.clip(kp[j] * (target[j] - q[j]) - kd[j] * qd[j], -TORQUE_LIMIT,
                          TORQUE_LIMIT)
            assert applied[j] == pytest.approx(law, rel=1e-9, abs=1e-9), (j, t)
        checked += 1
    assert checked > 100
    final = positions(robot.since(robot.count() - 1)[-1])
    assert max(abs(final[j] - target[j]) for j in target) < 0.01


def test_a_task_instance_is_placed_in_its_world(robot, wait_until):
    mark = len(robot.log())
    robot.pub_task.publish(TaskInstance(task=TASK, tau=[0.7, 0.2]))
    assert wait_until(lambda: 'task instance placed: tau = [0.7, 0.2]' in robot.log()[mark:],
                      EVENT_TIMEOUT), robot.log()[mark:]
    robot.pub_task.publish(TaskInstance(task='payload_transport', tau=[1.0]))
    assert wait_until(lambda: 'task instance not placed' in robot.log()[mark:],
                      EVENT_TIMEOUT)


def test_its_loop_reports_its_timing_as_its_stamps_show_it(robot, wait_until):
    """Its reports on /diagnostics count what its joint states show: stopped for a while
    (SIGSTOP, longer than the stall it catches up from), the loop skips periods; between two
    reports (each as of a state's stamp) the periods it counts are the states it published
    plus the periods it skipped, and those are the gaps in its stamps."""
    with robot.lock:
        seen = len(robot.reports)
    assert wait_until(lambda: len(robot.reports) > seen, EVENT_TIMEOUT)
    with robot.lock:
        first = robot.reports[-1]
        seen = len(robot.reports)
    os.kill(robot.process.pid, signal.SIGSTOP)
    try:
        time.sleep(STALL)       # the stimulus' length, not a wait for anything
    finally:
        os.kill(robot.process.pid, signal.SIGCONT)
    assert wait_until(lambda: len(robot.reports) >= seen + 2, EVENT_TIMEOUT)
    second = robot.reports[seen + 1]
    s1, s2 = int(first['stamp_ns']), int(second['stamp_ns'])
    assert wait_until(lambda: to_ns(robot.since(robot.count() - 1)[-1].header.stamp) > s2,
                      EVENT_TIMEOUT)
    stamps = np.array(sorted({to_ns(m.header.stamp) for m in robot.since(0)}))
    assert s1 in stamps and s2 in stamps, 'a report names a state this test did not get'
    inside = (stamps > s1) & (stamps <= s2)
    # each state's gap to the next: the periods skipped after it
    gaps = (np.diff(stamps) // PERIOD_NS - 1)[inside[:-1]]
    skipped = int(second['skipped']) - int(first['skipped'])
    assert skipped > 0, f'stopped {STALL} s and no period skipped: {first} {second}'
    assert skipped == int(gaps.sum()), (skipped, int(gaps.sum()))
    assert int(second['periods']) - int(first['periods']) == int(inside.sum()) + skipped
    assert int(second['deadline_misses']) > int(first['deadline_misses'])
    assert float(second['late_max_us']) >= float(second['late_p99_us'])


def test_ctrl_c_ends_it_quietly(tmp_path, wait_until):
    with running_robot(tmp_path / 'robot.log', wait_until, '/quiet') as r:
        code = r.stop()
    assert code == 0, r.log()
    assert 'Traceback' not in r.log()
