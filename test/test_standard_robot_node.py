"""psl_sim's standard robot as a separate process over DDS, seen as a ros2_control robot is:
joint_states stamped with the wall clock at the control rate, in its own joint order with an
extra joint; torques on effort_command in the controller's order come back as effort; a bad
command leaves it serving; silence brings zero torque after the command timeout; a task
instance is placed in its world. The process is ended by its process group in a finally."""
import contextlib
import os
import signal
import statistics
import subprocess
import threading
import time

import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from psl_msgs.msg import TaskInstance
from psl_ros import names
from psl_ros.client import RosClient
from psl_ros.graph import find_executable
from psl_ros.qos import LATCHED, RELIABLE
from psl_task.task import load_task

TASK = 'reach_over_obstacle'                     # joint1..joint3 at 500 Hz
PERIOD = load_task(TASK).control_period
JOINT_ORDER = ['joint3', 'joint1', 'joint2']     # the robot's joint_states order
COMMAND_JOINTS = ['joint2', 'joint3', 'joint1']  # its forward_command_controller's
EXTRA = 'gripper'
TIMEOUT = 0.2                                    # s, command_timeout: 100 periods
START_TIMEOUT = 30.0      # s, for the process to start and its first states to arrive
EVENT_TIMEOUT = 10.0      # s, for anything that should happen within periods
LATE = 0.25               # s a loaded machine's robot loop may answer the timeout late
STAMP_SKEW = 0.5          # s, a stamp's distance from the receive time on a loaded machine


class Robot:
    """The node's process, a client node that records its joint_states (with their receive
    time) and publishes commands, and the node's log."""

    def __init__(self, log_path, namespace: str = '/'):
        self.log_path = log_path
        self.states: list[tuple[float, JointState]] = []
        self._log = open(log_path, 'wb')
        env = dict(os.environ, RCUTILS_LOGGING_BUFFERED_STREAM='0')
        self.process = subprocess.Popen(
            [str(find_executable('psl_sim', 'standard_robot')), '--ros-args',
             '-p', f'task:={TASK}', '-p', f'joint_order:=[{",".join(JOINT_ORDER)}]',
             '-p', f'extra_joints:=[{EXTRA}]',
             '-p', f'command_joints:=[{",".join(COMMAND_JOINTS)}]',
             '-p', f'command_timeout:={TIMEOUT}', '-r', f'__ns:={namespace}'],
            stdout=self._log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        self.client = RosClient(namespace, name='standard_robot_test')
        node = self.client.node
        self.sub = node.create_subscription(
            JointState, names.JOINT_STATES,
            lambda m: self.states.append((time.time(), m)),
            QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE))
        self.pub = node.create_publisher(Float64MultiArray, names.EFFORT_COMMAND, RELIABLE)
        self.pub_task = node.create_publisher(TaskInstance, names.TASK_INSTANCE, LATCHED)

    def log(self) -> str:
        return self.log_path.read_text(errors='replace')

    def command(self, values) -> float:
        """Publish one command; returns the wall time after the publish call."""
        self.pub.publish(Float64MultiArray(data=[float(v) for v in values]))
        return time.time()

    def after(self, t: float) -> list[JointState]:
        """The states received after wall time t."""
        return [m for received, m in list(self.states) if received > t]

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


def stamp_s(msg: JointState) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


class Streamer:
    """Publishes one command every 5 ms from a thread (a controller at 200 Hz) until stopped;
    `last` is the wall time after its last publish."""

    def __init__(self, robot: Robot, values):
        self.robot, self.values, self.last = robot, values, 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            self.last = self.robot.command(self.values)
            self._stop.wait(0.005)

    def stop(self) -> float:
        self._stop.set()
        self._thread.join(timeout=5.0)
        return self.last


@contextlib.contextmanager
def running_robot(log_path, wait_until, namespace: str = '/'):
    """A standard robot process that has published its first states; ended in the end."""
    r = None
    try:
        r = Robot(log_path, namespace)
        assert wait_until(lambda: len(r.states) >= 10 and r.pub.get_subscription_count() > 0,
                          START_TIMEOUT), \
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


def wait_for_silence(robot: Robot, wait_until) -> float:
    """Wait until the robot applies zero torque (an earlier test's commands timed out);
    returns the wall time from which its states carry zero effort."""
    def zero_since():
        states = robot.after(time.time() - 1.0)
        return bool(states) and all(list(m.effort) == [0.0] * 4 for m in states[-10:])
    assert wait_until(zero_since, EVENT_TIMEOUT), 'the effort does not go back to zero'
    return time.time()


def test_joint_states_are_stamped_with_the_wall_clock_at_the_control_rate(robot, wait_until):
    start = time.time()
    assert wait_until(lambda: len(robot.after(start)) >= 300, EVENT_TIMEOUT), \
        f'{len(robot.after(start))} joint_states in {EVENT_TIMEOUT} s'
    received = [(t, m) for t, m in list(robot.states) if t > start]
    for t, m in received:
        # stamped before it was received, and not long before (system time, not sim time)
        assert -0.01 < t - stamp_s(m) < STAMP_SKEW, (t, stamp_s(m))
    stamps = [stamp_s(m) for _, m in received]
    steps = [b - a for a, b in zip(stamps, stamps[1:])]
    assert all(step > 0 for step in steps)
    assert statistics.median(steps) == pytest.approx(PERIOD, rel=0.2), \
        statistics.median(steps)
    m = received[-1][1]
    assert list(m.name) == JOINT_ORDER + [EXTRA]
    assert (m.position[-1], m.velocity[-1], m.effort[-1]) == (0.0, 0.0, 0.0)
    assert len(m.position) == len(m.velocity) == len(m.effort) == 4


def test_a_bad_command_is_refused_and_the_robot_serves_on(robot, wait_until):
    start = wait_for_silence(robot, wait_until)
    bad = [[1.0], [1.0, 2.0, 3.0, 4.0], [float('nan'), 0.0, 0.0]]
    # DDS may still be matching the command publisher: send until the node says it refused
    assert wait_until(lambda: [robot.command(b) for b in bad]
                      and 'refused effort_command' in robot.log(), EVENT_TIMEOUT, 0.05), \
        robot.log()
    after = time.time()
    assert wait_until(lambda: len(robot.after(after)) >= 50, EVENT_TIMEOUT), \
        'the robot stopped publishing after a bad command'
    assert robot.process.poll() is None
    # none of them changed the torque
    assert all(list(m.effort) == [0.0] * 4 for m in robot.after(start))


def test_constant_torques_come_back_as_effort_and_stop_after_the_timeout(robot, wait_until):
    command = {'joint2': 1.0, 'joint3': 2.0, 'joint1': 3.0}
    expected = [command[j] for j in JOINT_ORDER] + [0.0]       # the robot's order
    streamer = Streamer(robot, [command[j] for j in COMMAND_JOINTS])
    try:
        start = time.time()
        assert wait_until(lambda: sum(list(m.effort) == expected
                                      for m in robot.after(start)) >= 50, EVENT_TIMEOUT), \
            [list(m.effort) for m in robot.after(start)[-5:]]
    finally:
        last = streamer.stop()
    # silence: zero torque after the timeout, never before it (the robot's clock never runs
    # ahead of the wall clock), and soon after: within LATE s more, the time a Python loop at
    # 500 Hz beside the other test worker may answer late (seen: 47 ms past 10 periods); how
    # late it is under load is a benchmark's business (psl bench graph), not this test's

    def first_zero():
        zero = [m for m in robot.after(last) if list(m.effort) == [0.0] * 4]
        return zero[0] if zero else None
    assert wait_until(lambda: first_zero() is not None, EVENT_TIMEOUT), \
        [list(m.effort) for m in robot.after(last)[-5:]]
    silent = stamp_s(first_zero()) - last
    assert TIMEOUT - PERIOD < silent < TIMEOUT + LATE, silent
    assert all(list(m.effort) == expected for m in robot.after(last)
               if stamp_s(m) < last + TIMEOUT - PERIOD)


def test_a_task_instance_is_placed_in_its_world(robot, wait_until):
    robot.pub_task.publish(TaskInstance(task=TASK, tau=[0.6, 0.2], control_period=PERIOD))
    assert wait_until(lambda: 'task instance placed: tau = [0.6, 0.2]' in robot.log(),
                      EVENT_TIMEOUT), robot.log()
    robot.pub_task.publish(TaskInstance(task='payload_transport', tau=[1.0]))
    assert wait_until(lambda: 'task instance not placed' in robot.log(), EVENT_TIMEOUT), \
        robot.log()
    after = time.time()
    assert wait_until(lambda: len(robot.after(after)) >= 50, EVENT_TIMEOUT)


def test_ctrl_c_ends_it_quietly(tmp_path, wait_until):
    # a robot of its own (in a namespace of its own), stopped while its loop publishes
    with running_robot(tmp_path / 'robot.log', wait_until, '/ctrl_c') as robot:
        assert robot.stop() == 0, robot.log()
        assert 'Traceback' not in robot.log(), robot.log()
