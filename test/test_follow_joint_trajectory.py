"""psl's ``pd_controller`` (a process of its own) driven as a JointTrajectoryController: an
action client that knows only control_msgs (with trajectory_msgs for its goals and action_msgs
for their status) sends it control_msgs/action/FollowJointTrajectory goals, and the test plays
the robot, publishing sensor_msgs/JointState on ``<ns>/joint_states`` stamped with times it
chooses (the controller's clock is the states' stamps). What the controller answers each state
with is read from ``<ns>/pd_controller/controller_state`` (the reference at that state's stamp,
the torque in ``output.effort``) and ``<ns>/effort_command``.

Each answer is held against an independent reference computed here: the quintic's closed form
q(s) = q0 + d (10 s^3 - 15 s^4 + 6 s^5), a quintic Hermite segment solved here from its end
conditions, the feed-forward chosen linear in time (so that linear interpolation between the
points is exact), and the PD law u = clip(kp (q_ref - q) + kd (qd_ref - qd) + u_ff) with the
task's gains; and against JTC's (ros2_controllers, Jazzy) results: error codes, the words it
uses for a preempted goal and a success, a cancel answered as canceled with error_code 0.

Synchronisation is on events only: a state is published and its answer (the controller_state
with its stamp) awaited; a goal counts as taken by the controller once the action's status
says EXECUTING (the server hands the goal to the controller before that, and after it answered
"accepted"); results, cancels and parameters are awaited as answers. Every wait has a deadline.
"""
from __future__ import annotations

import contextlib
import dataclasses
import threading
import time

import numpy as np
import pytest
from action_msgs.msg import GoalStatus, GoalStatusArray
from action_msgs.srv import CancelGoal
from builtin_interfaces.msg import Duration, Time
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointTolerance, JointTrajectoryControllerState
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_action_status_default
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from psl_ros.action_client import ActionClient
from psl_ros.client import RosClient
from psl_ros.graph import PD_CONTROLLER, Graph, pid_alive
from psl_task.arm_model import joint_names_of
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
NAMESPACE = 'fjt'                   # the controller with its watchdog off
WATCHDOG_NAMESPACE = 'fjt_watchdog'  # the controller with its watchdog at its default
Result = FollowJointTrajectory.Result
NS, MS = 1_000_000_000, 1_000_000
T0 = 100 * NS                       # the first state's stamp (the robot's clock)
PREEMPTED = 'Current goal preempted by new incoming action.'    # JTC's words
SUCCEEDED = 'Goal successfully reached!'                        # JTC's words
TORQUE_LIMIT = 40.0                 # N m, every joint of the task (its model's limits)
ANSWER_TIMEOUT = 30.0               # s for any answer: a state's, a goal's, a result
QOS = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)

# The reference between points against the closed form: the same polynomial, computed by the
# controller from the points (segment coefficients divided by up to T^5 of a 0.1-0.25 s
# segment: double rounding amplified ~1e3) and here from the closed form. Seen, by sampling
# these trajectories every 0.14 ms: 7e-15 rad, 1.2e-13 rad/s, 3.4e-12 rad/s^2, 4e-16 N m.
# A cubic instead of a quintic, a wrong start or segment, or the effort not interpolated is
# off by more than 1e-4. Relative for the accelerations (up to ~10 rad/s^2), absolute near 0.
REF_RTOL, REF_ATOL = 1e-9, 1e-9             # rad, rad/s, rad/s^2, N m (feed-forward)
# the torque: kp (up to 300 N m/rad) times the reference's tolerance, and the sum's rounding
EFFORT_ATOL = 1e-6                          # N m
TASK_DEF = load_task(TASK)
JOINTS = list(joint_names_of(TASK_DEF))     # the controller's joints (its order)
KP = np.asarray(TASK_DEF.controller.kp, dtype=float)
KD = np.asarray(TASK_DEF.controller.kd, dtype=float)
Q_START = np.asarray(TASK_DEF.start_posture, dtype=float)
N = len(JOINTS)
ZEROS = np.zeros(N)
# offsets of the measured state from the reference: a torque well inside the limits
DQ = np.array([0.02, -0.03, 0.05])          # rad
DQD = np.array([0.1, -0.2, 0.3])            # rad/s


def law(q, qd, q_ref, qd_ref, u_ff) -> np.ndarray:
    """The PD + feed-forward law with the task's gains and torque limits."""
    return np.clip(KP * (np.asarray(q_ref) - q) + KD * (np.asarray(qd_ref) - qd) + u_ff,
                   -TORQUE_LIMIT, TORQUE_LIMIT)


def quintic(q0, q1, duration_ns: int):
    """Rest to rest from q0 to q1 in duration_ns, closed form: tau_ns -> (q, qd, qdd), held
    at the ends."""
    q0 = np.asarray(q0, dtype=float)
    d = np.asarray(q1, dtype=float) - q0
    big_t = duration_ns * 1e-9

    def at(tau_ns: int):
        s = min(max(tau_ns / duration_ns, 0.0), 1.0)
        return (q0 + d * (10 * s**3 - 15 * s**4 + 6 * s**5),
                d * (30 * s**2 - 60 * s**3 + 30 * s**4) / big_t,
                d * (60 * s - 180 * s**2 + 120 * s**3) / big_t**2)
    return at


def hermite_quintic(length_ns: int, start, end):
    """The quintic on [0, length] with (position, velocity, acceleration) `start` at 0 and
    `end` at length, solved here from its six conditions: tau_ns -> (q, qd, qdd)."""
    big_t = length_ns * 1e-9
    powers = np.array([[1, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0], [0, 0, 2, 0, 0, 0],
                       [1, big_t, big_t**2, big_t**3, big_t**4, big_t**5],
                       [0, 1, 2 * big_t, 3 * big_t**2, 4 * big_t**3, 5 * big_t**4],
                       [0, 0, 2, 6 * big_t, 12 * big_t**2, 20 * big_t**3]])
    c = np.linalg.solve(powers, np.vstack([*start, *end]))     # (6, n)

    def at(tau_ns: int):
        t = tau_ns * 1e-9
        k = np.arange(6)
        return (np.power(t, k) @ c,
                (k[1:] * np.power(t, k[1:] - 1)) @ c[1:],
                (k[2:] * (k[2:] - 1) * np.power(t, k[2:] - 2)) @ c[2:])
    return at


def linear(e0, e1, duration_ns: int):
    """tau_ns -> e0 + (e1 - e0) tau / duration (the feed-forward: linear, as interpolated)."""
    e0, e1 = np.asarray(e0, dtype=float), np.asarray(e1, dtype=float)
    return lambda tau_ns: e0 + (e1 - e0) * (tau_ns / duration_ns)


def time_msg(t_ns: int) -> Time:
    return Time(sec=t_ns // NS, nanosec=t_ns % NS)


def duration_msg(t_ns: int) -> Duration:
    return Duration(sec=t_ns // NS, nanosec=t_ns % NS)


def ns_of(stamp) -> int:
    return stamp.sec * NS + stamp.nanosec


@dataclasses.dataclass
class Points:
    """A trajectory's points in the controller's joint order: times (N,) ns, each field
    (N, n) or None."""

    times: list[int]
    q: np.ndarray
    qd: np.ndarray | None = None
    qdd: np.ndarray | None = None
    effort: np.ndarray | None = None

    @classmethod
    def sampled(cls, times, at, effort=None) -> 'Points':
        """Points at `times` of a closed form `at` (q, qd, qdd), and of `effort` (tau -> u)."""
        values = [at(t) for t in times]
        return cls(list(times), *(np.array([v[k] for v in values]) for k in range(3)),
                   None if effort is None else np.array([effort(t) for t in times]))

    @classmethod
    def rest(cls, times, q, effort=None) -> 'Points':
        """Points at `times`, all at q at rest (velocities and accelerations zero)."""
        k = len(times)
        q = np.tile(np.asarray(q, dtype=float), (k, 1))
        return cls(list(times), q, np.zeros_like(q), np.zeros_like(q),
                   None if effort is None else np.tile(np.asarray(effort, float), (k, 1)))

    def point(self, i: int) -> tuple:
        """Point i's (q, qd, qdd, effort) as sent (None: a field not sent)."""
        return tuple(None if f is None else f[i] for f in (self.q, self.qd, self.qdd,
                                                             self.effort))


def goal_msg(points: Points, start_ns: int = 0, order=None, **fields):
    """A FollowJointTrajectory goal of `points`, its joints in `order` (default: the
    controller's), stamped `start_ns` (0: start now); `fields`: the goal's other fields."""
    order = list(order or JOINTS)
    index = [JOINTS.index(j) for j in order]
    trajectory = JointTrajectory(joint_names=order)
    trajectory.header.stamp = time_msg(start_ns)
    for i, t in enumerate(points.times):
        point = JointTrajectoryPoint(time_from_start=duration_msg(t))
        for name, value in zip(('positions', 'velocities', 'accelerations', 'effort'),
                               points.point(i)):
            if value is not None:
                setattr(point, name, np.asarray(value, dtype=float)[index].tolist())
        trajectory.points.append(point)
    return FollowJointTrajectory.Goal(trajectory=trajectory, **fields)


def tolerances(position: dict[str, float]) -> list[JointTolerance]:
    return [JointTolerance(name=name, position=value) for name, value in position.items()]


@dataclasses.dataclass(frozen=True)
class Answer:
    """The controller's controller_state for one state, in the controller's joint order."""

    t_ns: int
    joint_names: list
    ref_q: np.ndarray
    ref_qd: np.ndarray
    ref_qdd: np.ndarray
    ref_effort: np.ndarray
    ref_time_ns: int            # reference.time_from_start
    q: np.ndarray               # feedback
    qd: np.ndarray
    error_q: np.ndarray
    torque: np.ndarray          # output.effort

    @classmethod
    def of(cls, msg: JointTrajectoryControllerState) -> 'Answer':
        ref, fb = msg.reference, msg.feedback
        return cls(ns_of(msg.header.stamp), list(msg.joint_names), *(
            np.array(v, dtype=float) for v in (ref.positions, ref.velocities,
                                               ref.accelerations, ref.effort)),
            ns_of(ref.time_from_start), np.array(fb.positions), np.array(fb.velocities),
            np.array(msg.error.positions), np.array(msg.output.effort))

    def reference(self) -> tuple:
        return self.ref_q, self.ref_qd, self.ref_qdd, self.ref_effort


class Robot:
    """The test's side: it plays the robot (joint states it stamps) and is the action client
    (psl's drop-in ActionClient, rclpy's without its lost-response race) of one controller."""

    def __init__(self, client: RosClient, graph: Graph, namespace: str, wait_until):
        self.node, self.graph, self.wait_until = client.node, graph, wait_until
        ns = f'/{namespace}'
        controller = f'{ns}/pd_controller'
        self.lock = threading.Lock()
        self.answers: dict[int, Answer] = {}
        self.commands: list[tuple[float, ...]] = []
        self.statuses: dict[bytes, int] = {}
        self.feedback: dict[bytes, list] = {}
        self.newest = 0                  # the newest state's stamp
        node = self.node
        self.states = node.create_publisher(JointState, f'{ns}/joint_states', QOS)
        self.subscriptions = [
            node.create_subscription(JointTrajectoryControllerState,
                                     f'{controller}/controller_state', self._on_answer, QOS),
            node.create_subscription(Float64MultiArray, f'{ns}/effort_command',
                                     self._on_command, QOS),
            node.create_subscription(GoalStatusArray,
                                     f'{controller}/follow_joint_trajectory/_action/status',
                                     self._on_status, qos_profile_action_status_default)]
        self.action = ActionClient(node, FollowJointTrajectory,
                                   f'{controller}/follow_joint_trajectory')
        self.parameters = AsyncParameterClient(node, controller)

    def close(self) -> None:
        self.action.destroy()
        for subscription in self.subscriptions:
            self.node.destroy_subscription(subscription)
        self.node.destroy_publisher(self.states)

    # -- what arrives ---------------------------------------------------------------------
    def _on_answer(self, msg):
        answer = Answer.of(msg)
        with self.lock:
            self.answers[answer.t_ns] = answer

    def _on_command(self, msg):
        with self.lock:
            self.commands.append(tuple(msg.data))

    def _on_status(self, msg):
        with self.lock:
            for status in msg.status_list:
                self.statuses[bytes(status.goal_info.goal_id.uuid)] = status.status

    def _on_feedback(self, msg):
        with self.lock:
            self.feedback.setdefault(bytes(msg.goal_id.uuid), []).append(msg.feedback)

    # -- waiting --------------------------------------------------------------------------
    def until(self, condition, what: str, timeout: float = ANSWER_TIMEOUT) -> None:
        """Wait for `condition`; fail naming `what` after `timeout` s or when the controller
        has died."""
        dead = self.graph.dead
        self.wait_until(lambda: condition() or bool(dead()), timeout, 0.0005)
        if condition():
            return
        if dead():
            pytest.fail(f'the controller died while waiting for {what}: '
                        f'{self.graph.describe_death(dead()[0])}')
        pytest.fail(f'{what}: nothing within {timeout:g} s (controller log '
                    f'{self.graph.processes[0].log_path})')

    def answer(self, future, what: str, timeout: float = ANSWER_TIMEOUT):
        self.until(future.done, what, timeout)
        return future.result()

    # -- the robot ------------------------------------------------------------------------
    def publish(self, t_ns: int, q, qd, order=None) -> None:
        """Publish the state (q, qd) (controller order) stamped t_ns, its joints in `order`."""
        order = list(order or JOINTS)
        index = [JOINTS.index(j) for j in order]
        msg = JointState(name=order, position=np.asarray(q, dtype=float)[index].tolist(),
                         velocity=np.asarray(qd, dtype=float)[index].tolist())
        msg.header.stamp = time_msg(t_ns)
        self.states.publish(msg)
        self.newest = max(self.newest, t_ns)

    def state(self, t_ns: int, q, qd=ZEROS, order=None) -> Answer:
        """Publish a state stamped t_ns (after the newest); the controller's answer to it."""
        assert t_ns > self.newest, 'the robot\'s clock runs forward'
        self.publish(t_ns, q, qd, order)
        self.until(lambda: t_ns in self.answers, f'the answer to the state at {t_ns} ns')
        answer = self.answers[t_ns]
        # what it was given, passed through: the measured state, and error = reference - it
        np.testing.assert_array_equal(answer.q, np.asarray(q, dtype=float))
        np.testing.assert_array_equal(answer.qd, np.asarray(qd, dtype=float))
        np.testing.assert_array_equal(answer.error_q, answer.ref_q - answer.q)
        assert answer.joint_names == JOINTS
        return answer

    def ready(self) -> None:
        """Publish states (holding the start posture) until the controller answers one on
        controller_state and effort_command reaches this node (both are matched then), and
        its action server and parameter services are there."""
        deadline = time.monotonic() + ANSWER_TIMEOUT
        while True:
            t = self.newest + 2 * MS if self.newest else T0
            self.publish(t, Q_START, ZEROS)
            if self.wait_until(lambda: t in self.answers and self.commands, 0.5, 0.001):
                break
            if time.monotonic() > deadline or self.graph.dead():
                pytest.fail('no answer on controller_state and effort_command within '
                            f'{ANSWER_TIMEOUT:g} s (controller log '
                            f'{self.graph.processes[0].log_path})')
        self.until(lambda: self.action.server_is_ready()
                   and self.parameters.services_are_ready(),
                   'the action server and the parameter services')

    # -- the action client ----------------------------------------------------------------
    def send(self, goal):
        """Send a goal; its handle. An accepted goal is returned once the action's status
        says it executes (the controller has taken it)."""
        handle = self.answer(self.action.send_goal_async(goal, self._on_feedback),
                             'the goal response')
        if handle.accepted:
            key = bytes(handle.goal_id.uuid)
            self.until(lambda: self.statuses.get(key, 0) >= GoalStatus.STATUS_EXECUTING,
                       'the status EXECUTING of an accepted goal')
        return handle

    def result(self, handle, timeout: float = ANSWER_TIMEOUT) -> tuple[int, int, str]:
        """(status, error_code, error_string) of a goal, once it has ended."""
        answer = self.answer(handle.get_result_async(), 'the result', timeout)
        return answer.status, answer.result.error_code, answer.result.error_string

    def ended(self, handle) -> bool:
        """Whether the action's status says the goal has ended."""
        return self.statuses.get(bytes(handle.goal_id.uuid), 0) >= GoalStatus.STATUS_SUCCEEDED

    def feedback_of(self, handle) -> list:
        with self.lock:
            return list(self.feedback.get(bytes(handle.goal_id.uuid), []))


def check_reference(answer: Answer, expected, rtol=REF_RTOL, atol=REF_ATOL) -> None:
    """The answer's reference (q, qd, qdd, effort) against `expected`."""
    for name, got, want in zip(('positions', 'velocities', 'accelerations', 'effort'),
                               answer.reference(), expected):
        np.testing.assert_allclose(got, want, rtol=rtol, atol=atol,
                                   err_msg=f'reference {name} at {answer.t_ns} ns')


def check_exact(answer: Answer, point: tuple) -> None:
    """The reference is `point` (q, qd, qdd, effort) bit for bit (None: zeros)."""
    for name, got, want in zip(('positions', 'velocities', 'accelerations', 'effort'),
                               answer.reference(), point):
        np.testing.assert_array_equal(got, ZEROS if want is None else want,
                                      err_msg=f'reference {name} at {answer.t_ns} ns')


def check_torque(answer: Answer, q_ref, qd_ref, u_ff) -> None:
    """The torque is the law on the answer's measured state and the given reference."""
    np.testing.assert_allclose(answer.torque, law(answer.q, answer.qd, q_ref, qd_ref, u_ff),
                               rtol=0, atol=EFFORT_ATOL, err_msg=f'torque at {answer.t_ns} ns')


def follow(robot: Robot, start_ns: int, taus, at, effort, end_ns: int, dq=DQ, dqd=DQD,
           order=None) -> list[Answer]:
    """States at start + tau (tau in `taus`) measured at the closed form `at` plus (dq, dqd);
    each answer's reference against `at` and `effort` (tau -> u_ff), its sample time (before
    the trajectory's end, `end_ns`: after it a success holds from its own start), its torque
    against the law. The answers."""
    answers = []
    for tau in taus:
        q, qd, qdd = at(tau)
        u_ff = effort(tau)
        answer = robot.state(start_ns + tau, q + dq, qd + dqd, order)
        check_reference(answer, (q, qd, qdd, u_ff))
        if tau < end_ns:
            assert answer.ref_time_ns == tau, f'sample time at {tau} ns'
        check_torque(answer, q, qd, u_ff)
        answers.append(answer)
    return answers


def grid(end_ns: int, step_ns: int = 10 * MS, also=()) -> list[int]:
    """Sample times 0..end_ns every step_ns, with an odd offset every other one (strictly
    between points), and `also`."""
    taus = {k * step_ns + (3 * MS if k % 2 else 0) for k in range(end_ns // step_ns + 1)}
    return sorted(t for t in taus | set(also) if t <= end_ns)


# -- the controllers ---------------------------------------------------------------------
@contextlib.contextmanager
def controller_process(namespace: str, log_dir, **params):
    """psl's pd_controller alone (no loop: no simulator, no executor; its parameters its
    defaults unless given), as a process; ended by PID whatever happens."""
    graph = Graph(task=TASK, namespace=namespace, nodes=(PD_CONTROLLER,),
                  extra_params={'pd_controller': params}, log_dir=log_dir)
    assert [p[0] for p in graph.nodes_spec] == ['pd_controller']
    try:
        graph.start()
        yield graph
    finally:
        graph.stop()
        left = [p.name for p in graph.processes if pid_alive(p.pid)]
        assert not left, f'processes left behind: {left}'


@contextlib.contextmanager
def robot_of(graph: Graph, namespace: str, wait_until):
    with RosClient(namespace) as client:
        robot = Robot(client, graph, namespace, wait_until)
        try:
            robot.ready()
            yield robot
        finally:
            robot.close()


@pytest.fixture(scope='module')
def robot(tmp_path_factory, wait_until):
    """The controller with its watchdog off (the test pauses between states while it
    waits for answers) and the test's robot side."""
    with controller_process(NAMESPACE, tmp_path_factory.mktemp('fjt_logs'),
                            state_timeout=0.0) as graph, \
            robot_of(graph, NAMESPACE, wait_until) as bench:
        yield bench


# -- the tests ---------------------------------------------------------------------------
def test_psl_result_codes_are_control_msgs_ones():
    """Catches: a result code of psl's controller renumbered against control_msgs'."""
    from psl_controller import trajectory_controller as tc
    for name in ('SUCCESSFUL', 'INVALID_GOAL', 'INVALID_JOINTS', 'OLD_HEADER_TIMESTAMP',
                 'PATH_TOLERANCE_VIOLATED', 'GOAL_TOLERANCE_VIOLATED'):
        assert getattr(tc, name) == getattr(Result, name), name


def test_parameters_say_what_the_controller_drives(robot):
    """Catches: `joints` not the controller's joints in order, or `command_interfaces` not effort.

    Also: either parameter writable."""
    answer = robot.answer(robot.parameters.get_parameters(['joints', 'command_interfaces']),
                          'the parameters')
    assert [list(v.string_array_value) for v in answer.values] == [JOINTS, ['effort']]
    answer = robot.answer(robot.parameters.set_parameters(
        [Parameter('joints', value=list(reversed(JOINTS)))]), 'the set_parameters answer')
    assert not answer.results[0].successful
    answer = robot.answer(robot.parameters.get_parameters(['joints']), 'the parameters')
    assert list(answer.values[0].string_array_value) == JOINTS


def test_a_quintic_is_followed_and_succeeds_within_its_goal_tolerance(robot):
    """Catches: the quintic sampled wrong (cubic, linear, shifted) or its torque not the PD law.

    Also: joints taken by position instead of by name (goal or state), the feed-forward not
    added or not interpolated, no torque clipping, success outside the goal tolerance, the
    success hold losing the last point's effort."""
    duration = 800 * MS
    times = [0, 200 * MS, 400 * MS, 600 * MS, duration]
    at = quintic(Q_START, Q_START + [0.3, -0.2, 0.25], duration)
    effort = linear([1.0, -2.0, 0.5], [3.0, -1.0, -0.5], duration)
    points = Points.sampled(times, at, effort)
    goal_order = list(reversed(JOINTS))             # not the controller's order
    state_order = goal_order[1:] + goal_order[:1]   # neither the controller's nor the goal's
    start = robot.newest + 100 * MS                 # in the future
    handle = robot.send(goal_msg(points, start, goal_order,
                                 goal_tolerance=tolerances({j: 0.01 for j in JOINTS})))
    assert handle.accepted
    taus = grid(duration, also=times)
    answers = follow(robot, start, [t for t in taus if t <= 400 * MS], at, effort, duration,
                     order=state_order)
    # far off the reference: the torque clipped to the limits (passed through: exact)
    tau = 405 * MS
    q, qd, _ = at(tau)
    big = robot.state(start + tau, q - [0.5, -0.5, 0.0], qd)
    assert big.torque[0] == TORQUE_LIMIT and big.torque[1] == -TORQUE_LIMIT
    check_torque(big, q, qd, effort(tau))
    answers += follow(robot, start, [t for t in taus if t > tau], at, effort, duration,
                      order=state_order)
    by_time = {a.t_ns - start: a for a in answers}
    for i, t in enumerate(times):                   # on a point: the point as sent
        check_exact(by_time[t], points.point(i))
    # past the end outside the goal tolerance (joint2 0.02 rad off, 0.01 allowed): still
    # active (its feedback stamped after the end); with goal_time_tolerance 0 it waits
    q_end, e_end = points.q[-1], points.effort[-1]
    end = start + duration
    deadline = time.monotonic() + ANSWER_TIMEOUT
    t = end
    while not any(ns_of(f.header.stamp) > end for f in robot.feedback_of(handle)):
        assert time.monotonic() < deadline, 'no feedback after the end: it did not wait'
        assert not robot.ended(handle), 'ended outside its goal tolerance'
        t += 10 * MS
        check_exact(robot.state(t, q_end + [0.0, 0.02, 0.0]), points.point(-1))
    robot.state(t + 10 * MS, q_end + 0.005)         # within: success
    assert robot.result(handle) == (GoalStatus.STATUS_SUCCEEDED, Result.SUCCESSFUL, SUCCEEDED)
    held = robot.state(t + 20 * MS, q_end + 0.1, [0.5, 0.0, -0.5])
    check_exact(held, (q_end, ZEROS, ZEROS, e_end))         # the last point, its effort too
    check_torque(held, q_end, ZEROS, e_end)
    # the feedback: the controller's joints, and what it served and measured at that state
    feedback = robot.feedback_of(handle)
    assert feedback and all(f.joint_names == JOINTS for f in feedback)
    for f in feedback:
        served = robot.answers[ns_of(f.header.stamp)]
        np.testing.assert_array_equal(f.desired.positions, served.ref_q)
        np.testing.assert_array_equal(f.actual.positions, served.q)


def test_the_goal_tolerance_not_met_within_goal_time_aborts_and_holds(robot):
    """Catches: goal_time_tolerance ignored (waiting for ever) or enforced early.

    Also: the abort not holding the measured position."""
    q_goal, e_goal = Q_START + [0.1, 0.1, -0.1], [2.0, 2.0, 2.0]
    points = Points.rest([0, 100 * MS], q_goal, e_goal)
    start = robot.newest + 5 * MS                   # stamped 0: from the next state on
    handle = robot.send(goal_msg(points, goal_tolerance=tolerances({j: 0.01 for j in JOINTS}),
                                 goal_time_tolerance=duration_msg(50 * MS)))
    assert handle.accepted
    off = q_goal + 0.05
    for tau in (0, 100 * MS, 120 * MS, 140 * MS):   # at most 40 ms late: it waits
        check_exact(robot.state(start + tau, off), points.point(-1))
    assert not robot.ended(handle)
    q_late = off + [0.001, 0.002, 0.003]
    aborted = robot.state(start + 160 * MS, q_late, [0.1, 0.1, 0.1])      # 60 ms late
    check_exact(aborted, (q_late, ZEROS, ZEROS, ZEROS))
    check_torque(aborted, q_late, ZEROS, ZEROS)
    status, code, _ = robot.result(handle)
    assert (status, code) == (GoalStatus.STATUS_ABORTED, Result.GOAL_TOLERANCE_VIOLATED)
    check_exact(robot.state(start + 200 * MS, off), (q_late, ZEROS, ZEROS, ZEROS))


def test_a_new_goal_preempts_the_running_one(robot):
    """Catches: a preempted goal left without its result (INVALID_GOAL, JTC's words).

    Also: the new goal queued behind the old one, or a goal stamped zero not started at the
    next state from the state measured there (JTC's segment to its first point)."""
    duration_a = 1000 * MS
    at_a = quintic(Q_START, Q_START + [-0.4, 0.3, 0.2], duration_a)
    start_a = robot.newest + 20 * MS
    first = robot.send(goal_msg(Points.sampled(range(0, duration_a + 1, 250 * MS), at_a),
                                start_a))
    assert first.accepted
    follow(robot, start_a, grid(300 * MS), at_a, lambda tau: ZEROS, duration_a)
    # the new goal, stamped 0: its first point 100 ms after its start, then a quintic
    q_b0, q_b1 = Q_START + [0.2, 0.2, 0.2], Q_START + [0.3, 0.0, 0.1]
    at_b_moving = quintic(q_b0, q_b1, 400 * MS)

    def at_b(tau):
        return at_b_moving(tau - 100 * MS)
    e_b = np.array([1.5, -1.5, 2.5])
    points_b = Points.sampled([100 * MS, 300 * MS, 500 * MS], at_b, lambda tau: e_b)
    second = robot.send(goal_msg(points_b))
    assert second.accepted
    assert robot.result(first) == (GoalStatus.STATUS_ABORTED, Result.INVALID_GOAL, PREEMPTED)
    # it starts at the next state: from the state measured there (acceleration 0, effort 0)
    # to its first point, a quintic (the trajectory has accelerations); the effort linear
    start_b = robot.newest + 10 * MS
    q_m, qd_m = at_a(310 * MS)[0] + DQ, at_a(310 * MS)[1] + DQD
    first_answer = robot.state(start_b, q_m, qd_m)
    assert first_answer.ref_time_ns == 0
    segment = hermite_quintic(100 * MS, (q_m, qd_m, ZEROS), points_b.point(0)[:3])

    def reference_b(tau):
        return segment(tau) if tau < 100 * MS else at_b(tau)

    def effort_b(tau):
        return e_b * min(tau / (100 * MS), 1.0)
    check_reference(first_answer, (*reference_b(0), ZEROS))
    follow(robot, start_b, grid(500 * MS, also=points_b.times)[1:], reference_b, effort_b,
           500 * MS)
    for i, t in enumerate(points_b.times):
        check_exact(robot.answers[start_b + t], points_b.point(i))
    assert robot.result(second) == (GoalStatus.STATUS_SUCCEEDED, Result.SUCCESSFUL,
                                    SUCCEEDED)


def test_a_goal_stamped_in_the_future_keeps_what_ran_before_until_its_start(robot):
    """Catches: a future goal served before its stamp instead of what ran before (with its effort).

    Either a hold, its first point, or JTC's move to it; for a hold that succeeded and for a
    goal that moves (preempted at once, served on until the new start)."""
    # a "homing": to q_h, held there with a torque; it succeeds, its last point held
    q_h, e_h = Q_START + [0.05, -0.05, 0.05], np.array([4.0, -3.0, 2.0])
    start = robot.newest + 2 * MS
    handle = robot.send(goal_msg(Points.rest([0, 20 * MS], q_h, e_h)))
    assert handle.accepted
    for tau in (0, 10 * MS, 20 * MS):
        robot.state(start + tau, q_h)
    assert robot.result(handle)[:2] == (GoalStatus.STATUS_SUCCEEDED, Result.SUCCESSFUL)
    # the next goal, stamped 200 ms ahead: a quintic with another feed-forward
    start_f = robot.newest + 200 * MS
    duration_f = 400 * MS
    at_f = quintic(Q_START + [0.3, 0.3, -0.3], Q_START, duration_f)
    effort_f = linear([-5.0, 5.0, -1.0], [-1.0, 1.0, 1.0], duration_f)
    points_f = Points.sampled([0, 200 * MS, duration_f], at_f, effort_f)
    handle_f = robot.send(goal_msg(points_f, start_f))
    assert handle_f.accepted
    for t in (start_f - 150 * MS, start_f - 50 * MS, start_f - 1):
        answer = robot.state(t, q_h + DQ, DQD)
        check_exact(answer, (q_h, ZEROS, ZEROS, e_h))      # the hold, its torque too
        check_torque(answer, q_h, ZEROS, e_h)
    check_exact(robot.state(start_f, Q_START), points_f.point(0))
    follow(robot, start_f, grid(200 * MS)[1:], at_f, effort_f, duration_f)
    # while it moves, a goal stamped 100 ms ahead: the moving one is preempted at once and
    # goes on (its reference, its feed-forward) until the new one's start
    start_g = robot.newest + 100 * MS
    q_g, e_g = Q_START + [-0.1, 0.1, 0.0], np.array([0.5, 0.5, 0.5])
    points_g = Points.rest([0, 50 * MS], q_g, e_g)
    handle_g = robot.send(goal_msg(points_g, start_g))
    assert handle_g.accepted
    assert robot.result(handle_f) == (GoalStatus.STATUS_ABORTED, Result.INVALID_GOAL,
                                      PREEMPTED)
    for t in (start_g - 90 * MS, start_g - 40 * MS, start_g - 1):
        tau = t - start_f
        q, qd, qdd = at_f(tau)
        answer = robot.state(t, q + DQ, qd + DQD)
        check_reference(answer, (q, qd, qdd, effort_f(tau)))
        check_torque(answer, q, qd, effort_f(tau))
    check_exact(robot.state(start_g, q_g), points_g.point(0))
    robot.state(start_g + 50 * MS, q_g)
    assert robot.result(handle_g)[:2] == (GoalStatus.STATUS_SUCCEEDED, Result.SUCCESSFUL)


def test_a_late_goal_ends_with_old_header_timestamp_and_changes_nothing(robot):
    """Catches: a goal whose start the states have passed run (jumped into) or preempting.

    The running goal goes on, as if the late one had not come, to its success."""
    duration = 600 * MS
    at = quintic(Q_START, Q_START + [0.2, -0.2, 0.2], duration)
    effort = linear([1.0, 1.0, 1.0], [-1.0, 0.0, 2.0], duration)
    start = robot.newest + 10 * MS
    running = robot.send(goal_msg(Points.sampled([0, 300 * MS, duration], at, effort), start))
    assert running.accepted
    taus = grid(duration)
    follow(robot, start, [t for t in taus if t <= 200 * MS], at, effort, duration)
    # stamped 50 ms before the newest state, ending 1 s after it: not in the past, but late
    late = robot.send(goal_msg(Points.rest([0, 1050 * MS], Q_START - 0.3, [9.0, 9.0, 9.0]),
                               robot.newest - 50 * MS))
    assert late.accepted
    status, code, _ = robot.result(late)
    assert (status, code) == (GoalStatus.STATUS_ABORTED, Result.OLD_HEADER_TIMESTAMP)
    follow(robot, start, [t for t in taus if t > 200 * MS], at, effort, duration)
    assert robot.result(running) == (GoalStatus.STATUS_SUCCEEDED, Result.SUCCESSFUL,
                                     SUCCEEDED)


def test_a_cancel_holds_the_measured_position(robot):
    """Catches: a cancel holding the reference (or running on) instead of the measured position.

    Also: not answered as canceled, or the hold keeping the feed-forward."""
    duration = 1000 * MS
    at = quintic(Q_START, Q_START + [0.4, 0.4, -0.4], duration)
    effort = linear([3.0, -3.0, 2.0], [3.0, -3.0, 2.0], duration)
    start = robot.newest + 10 * MS
    handle = robot.send(goal_msg(Points.sampled([0, 500 * MS, duration], at, effort), start))
    assert handle.accepted
    q_c = follow(robot, start, grid(300 * MS), at, effort, duration)[-1].q
    response = robot.answer(handle.cancel_goal_async(), 'the cancel response')
    assert response.return_code == CancelGoal.Response.ERROR_NONE
    assert [bytes(g.goal_id.uuid) for g in response.goals_canceling] == [
        bytes(handle.goal_id.uuid)]
    # JTC: canceled, with a default result (error_code 0)
    assert robot.result(handle)[:2] == (GoalStatus.STATUS_CANCELED, Result.SUCCESSFUL)
    for tau in (310 * MS, 600 * MS, duration + 100 * MS):
        q, qd, _ = at(tau)
        answer = robot.state(start + tau, q, qd)
        check_exact(answer, (q_c, ZEROS, ZEROS, ZEROS))     # where it was, no feed-forward
        check_torque(answer, q_c, ZEROS, ZEROS)


def test_a_path_tolerance_violation_aborts_and_holds(robot):
    """Catches: a path tolerance ignored or applied to another joint than the one it names.

    Also: the abort not at once, or not holding the measured position."""
    duration = 1000 * MS
    at = quintic(Q_START, Q_START + [-0.3, 0.3, 0.3], duration)
    effort = linear([2.0, 2.0, 2.0], [0.0, 0.0, 0.0], duration)
    start = robot.newest + 10 * MS
    handle = robot.send(goal_msg(Points.sampled([0, 500 * MS, duration], at, effort), start,
                                 path_tolerance=tolerances({JOINTS[1]: 0.05})))
    assert handle.accepted
    # joint2 0.03 rad off (within its 0.05), the others far off (no tolerance of theirs)
    follow(robot, start, grid(200 * MS), at, effort, duration,
           dq=np.array([0.2, -0.03, -0.2]))
    assert not robot.ended(handle)
    q, qd, _ = at(213 * MS)
    q_bad = q + [0.0, 0.06, 0.0]
    aborted = robot.state(start + 213 * MS, q_bad, qd)
    check_exact(aborted, (q_bad, ZEROS, ZEROS, ZEROS))      # held where it is, at once
    check_torque(aborted, q_bad, ZEROS, ZEROS)
    status, code, _ = robot.result(handle)
    assert (status, code) == (GoalStatus.STATUS_ABORTED, Result.PATH_TOLERANCE_VIOLATED)
    for tau in (300 * MS, duration + 50 * MS):
        check_exact(robot.state(start + tau, at(tau)[0]), (q_bad, ZEROS, ZEROS, ZEROS))


def test_goals_the_controller_cannot_run_are_rejected_and_change_nothing(robot):
    """Catches: a goal the controller cannot run accepted, or a rejected goal preempting.

    Not the controller's joints (one unknown, one missing, none), a last point that moves, a
    NaN, an end in the past, no points."""
    q_g = Q_START + [0.05, 0.05, 0.05]
    start = robot.newest + 2 * MS
    running = robot.send(goal_msg(Points.rest([0, 1000 * MS], q_g)))
    assert running.accepted
    check_exact(robot.state(start, q_g), (q_g, ZEROS, ZEROS, None))

    def good():
        return goal_msg(Points.sampled([0, 200 * MS], quintic(q_g, Q_START, 200 * MS)))
    bad = {name: good() for name in ('an unknown joint', 'a joint missing', 'no joints',
                                     'the last point moves', 'a NaN', 'no points')}
    bad['an unknown joint'].trajectory.joint_names[0] = 'elbow'
    bad['a joint missing'].trajectory.joint_names.pop()
    for point in bad['a joint missing'].trajectory.points:
        for field in ('positions', 'velocities', 'accelerations'):
            setattr(point, field, list(getattr(point, field))[:-1])
    bad['no joints'].trajectory.joint_names = []
    bad['the last point moves'].trajectory.points[-1].velocities[1] = 0.1
    bad['a NaN'].trajectory.points[0].positions[2] = float('nan')
    bad['no points'].trajectory.points = []
    bad['ending in the past'] = goal_msg(Points.rest([0, 1000 * MS], q_g),
                                         robot.newest - 2000 * MS)
    for what, goal in bad.items():
        assert not robot.send(goal).accepted, what
    # what ran goes on, to its success
    check_reference(robot.state(start + 500 * MS, q_g), (q_g, ZEROS, ZEROS, ZEROS))
    check_exact(robot.state(start + 1000 * MS, q_g), (q_g, ZEROS, ZEROS, None))
    assert robot.result(running)[:2] == (GoalStatus.STATUS_SUCCEEDED, Result.SUCCESSFUL)


def test_the_watchdog_aborts_the_goal_and_commands_zero_torque(tmp_path, wait_until,
                                                               watchdog_silence):
    """Catches: the watchdog off by default, not aborting / not zeroing the torque, or firing
    before its timeout or a whole timeout late (the silence it measured itself).

    When the states stop: the goal aborts with INVALID_GOAL and the reason, and only zero
    torque is commanded, every control period."""
    with controller_process(WATCHDOG_NAMESPACE, tmp_path) as graph, \
            robot_of(graph, WATCHDOG_NAMESPACE, wait_until) as bench:
        held = (5.0, -5.0, 3.0)             # the goal's torque (feed-forward at its position)
        zero = (0.0,) * N                   # the watchdog's: a constant, exact

        def holding(command) -> bool:
            return np.allclose(command, held, rtol=0, atol=EFFORT_ATOL)
        stop, errors = threading.Event(), []

        def states():
            """The robot at Q_START: the next state once the last one is answered."""
            while not stop.is_set():
                t = bench.newest + 2 * MS
                bench.publish(t, Q_START, ZEROS)
                if not wait_until(lambda: t in bench.answers or stop.is_set(), 10.0, 0.0005):
                    errors.append(f'no answer to the state at {t} ns')
                    return
        with bench.lock:
            seen = len(bench.commands)
        pump = threading.Thread(target=states, daemon=True)
        pump.start()
        try:
            handle = bench.send(goal_msg(Points.rest([0, 600 * NS], Q_START, held)))
            assert handle.accepted
            bench.until(lambda: any(map(holding, bench.commands[seen:])), "the goal's torque")
            assert not bench.ended(handle), 'the goal ended while the states came'
        finally:
            stop.set()
            pump.join(timeout=ANSWER_TIMEOUT)
        assert not errors and not pump.is_alive(), errors
        status, code, why = bench.result(handle)
        assert (status, code) == (GoalStatus.STATUS_ABORTED, Result.INVALID_GOAL)
        assert 'joint states stopped' in why
        watchdog_silence(why)
        with bench.lock:
            first = next(i for i in range(seen, len(bench.commands))
                         if holding(bench.commands[i]))

        def since_the_goal() -> list:
            with bench.lock:
                return bench.commands[first:]
        bench.until(lambda: since_the_goal()[-3:] == [zero] * 3,
                    'three zero torques on effort_command')
        commands = since_the_goal()
        k = commands.index(zero)
        # the goal's torque while the states came, then zero torque only, every period
        assert all(map(holding, commands[:k])) and set(commands[k:]) == {zero}
