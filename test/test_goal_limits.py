"""Goals that would move the arm past its limits, whoever sends them, against both of psl's
FollowJointTrajectory servers as processes of their own over DDS: ``pd_controller`` (the
controller of a robot that takes torques) and the standard robot's own controller (in its loop,
on the wall clock). The client here knows only control_msgs.

* the issue's goals (a point at 10 rad or 1e308 rad, a velocity of 1e6 rad/s, an effort of
  1e9 N m; reach_over_obstacle's joints range over [-3, 3] rad, 40 N m) and an interpolation
  that bulges past a limit between two points inside it are rejected, the reason on /rosout
  names the joint, the value and the bound, and the arm stays inside;
* a goal over the size bounds (``max_points``, ``max_duration``: set low here) is rejected
  saying the bound;
* an arm found outside its range is brought back by a goal whose points are inside, never
  sent further out; a goal with a point outside is rejected;
* a generated family of goals (seeded: positions, velocities, accelerations, efforts, point
  counts, times and stamps around the bounds): the reference the server serves never leaves the
  range, the arm passes it only by the give of its stop under an impact (``EXCESS_BOUND``; the
  most is printed), and a normal goal afterwards succeeds and leaves it at rest inside;
* 200 goals in 2 s right after a homing goal on the standard robot: every one answered, and
  every result.

The pd_controller's robot is played here, in lockstep: the task's MuJoCo model in this process,
stepped with the torque the controller answers each joint state with (read from
``controller_state``, keyed by the state's stamp). The standard robot is itself a MuJoCo model
on the wall clock; its joint_states are recorded. Every wait is on an event with a deadline;
the processes are ended by PID in a finally.
"""
from __future__ import annotations

import collections
import contextlib
import threading
import time

import numpy as np
import pytest
from action_msgs.msg import GoalStatus
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointTrajectoryControllerState
from rcl_interfaces.msg import Log
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from psl_ros.action_client import ActionClient
from psl_ros.client import RosClient
from psl_ros.graph import PD_CONTROLLER, STANDARD_ROBOT, Graph, pid_alive
from psl_ros.stamps import duration_msg, time_msg, to_ns
from psl_task.arm_model import ArmModel, joint_names_of
from psl_task.task import load_task

TASK = 'reach_over_obstacle'        # joint1..3 in [-3, 3] rad, 40 N m, 500 Hz
TASK_DEF = load_task(TASK)
JOINTS = list(joint_names_of(TASK_DEF))
N = len(JOINTS)
LOW, HIGH, TORQUE = -3.0, 3.0, 40.0
START = np.asarray(TASK_DEF.start_posture, dtype=float)
PERIOD_NS = TASK_DEF.control_period_ns
NS, MS = 1_000_000_000, 1_000_000
MAX_POINTS, MAX_DURATION = 200, 4.0     # the servers' size bounds here (their parameters)
SIZE = {'max_points': MAX_POINTS, 'max_duration': MAX_DURATION}
TIMEOUT = 30.0                          # s for any answer
# how far the measured arm may pass its range while goals run. The reference the controllers
# serve stays inside (held exactly); nothing pushes the arm through its stop any more (before: a
# reference at 10 rad held it 0.14-0.54 rad in). A goal inside the limits may still drive the
# arm into its stop at speed, which MuJoCo makes a soft constraint: a step of the reference
# across a joint's range takes this arm up to 0.095 rad in (simulated here, the task's gains);
# the family here on the standard robot on a loaded machine, where a step may come while the arm
# still moves from the one before: 0 to 0.19 rad (seeds 1-5, 46). At rest it is inside.
EXCESS_BOUND = 0.5                      # rad: impacts on the stop, not a push through it
REST_BOUND = 0.01                       # rad: the arm at rest after the issue's goals
FLOOD, FLOOD_SECONDS = 200, 2.0
QOS = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
PREEMPTED = 'Current goal preempted by new incoming action.'    # JTC's words
SUCCEEDED = 'Goal successfully reached!'


def goal_msg(times_s, positions, velocities=None, accelerations=None, effort=None,
             start_ns: int = 0) -> FollowJointTrajectory.Goal:
    """A goal of the controller's joints: points at times_s, each field (N_points, N)."""
    msg = JointTrajectory(joint_names=JOINTS)
    msg.header.stamp = time_msg(start_ns)
    for k, t in enumerate(times_s):
        point = JointTrajectoryPoint(time_from_start=duration_msg(int(round(t * NS))))
        for name, values in (('positions', positions), ('velocities', velocities),
                             ('accelerations', accelerations), ('effort', effort)):
            if values is not None:
                setattr(point, name, [float(v) for v in values[k]])
        msg.points.append(point)
    return FollowJointTrajectory.Goal(trajectory=msg)


def quintic(q0, q1, seconds: float, n_points: int):
    """Rest to rest: (times, q, qd, qdd) of n_points, closed form."""
    t = np.linspace(0.0, seconds, n_points)
    s = (t / seconds)[:, None]
    d = np.asarray(q1) - np.asarray(q0)
    return (t, q0 + d * (10 * s**3 - 15 * s**4 + 6 * s**5),
            d * (30 * s**2 - 60 * s**3 + 30 * s**4) / seconds,
            d * (60 * s - 180 * s**2 + 120 * s**3) / seconds**2)


class Client:
    """The action client of one server, and the server's log lines on /rosout."""

    def __init__(self, client: RosClient, graph: Graph, action: str, node_name: str):
        self.node, self.graph, self.node_name = client.node, graph, node_name
        self.lock = threading.Lock()
        self.logs: list[str] = []
        self.action = ActionClient(self.node, FollowJointTrajectory, action)
        self.node.create_subscription(Log, '/rosout', self._on_log, QOS)

    def _on_log(self, msg: Log) -> None:
        if msg.name.endswith(self.node_name):
            with self.lock:
                self.logs.append(msg.msg)

    def until(self, condition, what: str, timeout: float = TIMEOUT) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            if self.graph.dead():
                pytest.fail(f'{what}: the server died: '
                            f'{self.graph.describe_death(self.graph.dead()[0])}')
            if time.monotonic() > deadline:
                pytest.fail(f'{what}: nothing within {timeout:g} s (log '
                            f'{self.graph.processes[0].log_path})')
            time.sleep(0.001)

    def send(self, goal):
        future = self.action.send_goal_async(goal)
        self.until(future.done, 'the goal response')
        return future.result()

    def result(self, handle) -> tuple[int, int, str]:
        future = handle.get_result_async()
        self.until(future.done, 'the result')
        answer = future.result()
        return answer.status, answer.result.error_code, answer.result.error_string

    def cancel(self, handle) -> None:
        future = handle.cancel_goal_async()
        self.until(future.done, 'the cancel response')

    def rejected(self, goal) -> str:
        """Send a goal that must be rejected; the reason the server logged."""
        with self.lock:
            seen = len(self.logs)
        assert not self.send(goal).accepted, 'the goal was accepted'

        def reason() -> str | None:
            with self.lock:
                return next((line for line in self.logs[seen:] if 'goal rejected' in line),
                            None)
        self.until(lambda: reason() is not None, 'the reason on /rosout')
        return reason()


class LockstepArm(Client):
    """pd_controller's robot: the task's model here, one step per answered state."""

    def __init__(self, client: RosClient, graph: Graph, namespace: str):
        super().__init__(client, graph, f'/{namespace}/pd_controller/follow_joint_trajectory',
                         'pd_controller')
        self.arm = ArmModel(TASK_DEF)
        self.arm.reset(TASK_DEF.tau_default)
        self.place(START)
        self.answers: dict[int, JointTrajectoryControllerState] = {}
        self.newest = 10 * NS
        self.states = self.node.create_publisher(JointState, f'/{namespace}/joint_states', QOS)
        self.node.create_subscription(JointTrajectoryControllerState,
                                      f'/{namespace}/pd_controller/controller_state',
                                      self._on_answer, QOS)
        self.excess = 0.0               # the most the arm passed its range
        self.reference_excess = 0.0     # the most the served reference passed it

    def place(self, q) -> None:
        """The arm at q at rest (a test's own robot may start anywhere)."""
        import mujoco
        self.arm.data.qpos[self.arm.qpos_adr] = q
        self.arm.data.qvel[self.arm.dof_adr] = 0.0
        mujoco.mj_forward(self.arm.model, self.arm.data)

    def _on_answer(self, msg) -> None:
        with self.lock:
            self.answers[to_ns(msg.header.stamp)] = msg

    def step(self, count: int = 1) -> JointTrajectoryControllerState:
        """`count` control periods: the state published, its answer awaited, the torque
        applied; the last answer."""
        for _ in range(count):
            t = self.newest = self.newest + PERIOD_NS
            q, qd = self.arm.q.copy(), self.arm.qd.copy()
            msg = JointState(name=JOINTS, position=q.tolist(), velocity=qd.tolist())
            msg.header.stamp = time_msg(t)
            self.states.publish(msg)
            self.until(lambda: t in self.answers, f'the answer to the state at {t} ns')
            with self.lock:
                answer = self.answers.pop(t)
            self.arm.step(np.asarray(answer.output.effort))
            self.reference_excess = max(self.reference_excess,
                                        excess(np.asarray(answer.reference.positions)))
            self.excess = max(self.excess, excess(self.arm.q))
        return answer

    def ready(self) -> None:
        """States until the controller answers one (both ways matched) and the action server
        is there."""
        deadline = time.monotonic() + TIMEOUT
        while True:
            t = self.newest + PERIOD_NS
            msg = JointState(name=JOINTS, position=self.arm.q.tolist(),
                             velocity=[0.0] * N)
            msg.header.stamp = time_msg(t)
            self.states.publish(msg)
            got = time.monotonic() + 0.5
            while t not in self.answers and time.monotonic() < got:
                time.sleep(0.001)
            if t in self.answers:
                self.newest = t
                self.answers.clear()
                break
            assert time.monotonic() < deadline and not self.graph.dead(), \
                'pd_controller does not answer joint states'
        self.until(self.action.server_is_ready, 'the action server')

    def run(self, seconds: float) -> None:
        self.step(int(round(seconds * NS / PERIOD_NS)))

    def position(self) -> np.ndarray:
        return self.arm.q.copy()

    def newest_stamp(self) -> int:
        return self.newest


class WallClockArm(Client):
    """The standard robot: its joint_states recorded."""

    def __init__(self, client: RosClient, graph: Graph, namespace: str):
        super().__init__(client, graph, f'/{namespace}/standard_robot/follow_joint_trajectory',
                         'standard_robot')
        self.stamps: list[int] = []
        self.q = START.copy()           # the newest measured position
        self.excess = 0.0               # the most the arm passed its range
        self.reference_excess = 0.0     # the most the served reference passed it
        self.node.create_subscription(JointState, f'/{namespace}/joint_states', self._on_state,
                                      QOS)
        self.node.create_subscription(JointTrajectoryControllerState,
                                      f'/{namespace}/standard_robot/controller_state',
                                      self._on_reference, QOS)

    def _on_state(self, msg: JointState) -> None:
        q = np.array([dict(zip(msg.name, msg.position))[j] for j in JOINTS])
        with self.lock:
            self.stamps.append(to_ns(msg.header.stamp))
            self.excess = max(self.excess, excess(q))
            self.q = q

    def position(self) -> np.ndarray:
        with self.lock:
            return self.q.copy()

    def _on_reference(self, msg: JointTrajectoryControllerState) -> None:
        with self.lock:
            self.reference_excess = max(self.reference_excess,
                                        excess(np.asarray(msg.reference.positions)))

    def ready(self) -> None:
        self.until(lambda: len(self.stamps) > 10, 'the joint states')
        self.until(self.action.server_is_ready, 'the action server')

    def newest_stamp(self) -> int:
        with self.lock:
            return self.stamps[-1]

    def run(self, seconds: float) -> None:
        """Until the robot's states have passed `seconds` of its time from now."""
        end = self.newest_stamp() + int(seconds * NS)
        self.until(lambda: self.newest_stamp() >= end, f'{seconds} s of joint states')


def excess(q: np.ndarray) -> float:
    """How far q is outside [LOW, HIGH] (0 inside)."""
    return float(np.maximum(np.max(q - HIGH), np.max(LOW - q)).clip(0.0))


@contextlib.contextmanager
def server(kind: str, log_dir, namespace: str):
    """A pd_controller (its robot played here) or a standard robot, with the size bounds
    here, in its own namespace; its client; ended by PID."""
    node = PD_CONTROLLER if kind == 'pd' else STANDARD_ROBOT
    params = dict(SIZE, state_timeout=0.0) if kind == 'pd' else dict(SIZE)
    graph = Graph(task=TASK, namespace=namespace, nodes=(node,),
                  extra_params={node[0]: params}, log_dir=log_dir)
    try:
        graph.start()
        with RosClient(namespace, name='goal_limits_test') as client:
            arm = (LockstepArm if kind == 'pd' else WallClockArm)(client, graph, namespace)
            arm.ready()
            yield arm
    finally:
        graph.stop()
        left = [p.name for p in graph.processes if pid_alive(p.pid)]
        assert not left, f'processes left behind: {left}'


@pytest.fixture(scope='module', params=['pd', 'standard'])
def arm(request, tmp_path_factory):
    with server(request.param, tmp_path_factory.mktemp(f'limits_{request.param}'),
                f'limits_{request.param}') as a:
        yield a


@pytest.fixture(autouse=True)
def excess_of_this_test(request):
    """The arms' excess over the range counted from this test's start (the arms are the
    module's: a test run after the family must not inherit its impacts)."""
    for name in ('arm', 'standard'):
        if name in request.fixturenames:
            served = request.getfixturevalue(name)
            served.excess = served.reference_excess = 0.0


@pytest.fixture(scope='module')
def standard(tmp_path_factory):
    with server('standard', tmp_path_factory.mktemp('limits_flood'), 'limits_flood') as a:
        yield a


def here(arm) -> np.ndarray:
    """Where the arm is (pd: its model here; standard: its newest state's positions are not
    kept, so the start posture it holds between tests)."""
    return arm.arm.q.copy() if isinstance(arm, LockstepArm) else START.copy()


def home(arm) -> None:
    """Back to the start posture at rest: a quintic of 1 s, SUCCESSFUL."""
    t, q, qd, qdd = quintic(here(arm), START, 1.0, 51)
    handle = arm.send(goal_msg(t, q, qd, qdd))
    assert handle.accepted
    arm.run(1.2)
    status, code, why = arm.result(handle)
    assert code == FollowJointTrajectory.Result.SUCCESSFUL, why


# -- the issue's goals ----------------------------------------------------------------------
ISSUE_GOALS = {
    # (field, value) at joint2 of the second point (positions) or the first (the others)
    'a point at 10 rad': ('positions', 10.0, "joint 'joint2': position 10 at point 1 "
                                             "(t = 1 s) is above its limit 3 (the model's "
                                             'joint range)'),
    'a point at 1e308 rad': ('positions', 1e308, "joint 'joint2': position 1e+308 at point 1"),
    'a velocity of 1e6 rad/s': ('velocities', 1e6, "joint 'joint2': velocity 1e+06/s at "
                                                   'point 0 (t = 0.5 s) is above its limit '
                                                   '100/s'),
    'an effort of 1e9 N m': ('effort', 1e9, "joint 'joint2': effort 1e+09 N m at point 0 "
                                            '(t = 0.5 s) is above its limit 40 N m'),
}


@pytest.mark.parametrize('case', list(ISSUE_GOALS))
def test_the_issues_goals_are_rejected_with_the_reason_and_the_arm_stays_inside(arm, case):
    """Catches: a goal past the joint range, the velocity bound or the torque limit accepted
    (before: SUCCESSFUL, the arm at 3.14-3.54 rad against a limit of 3).

    The goal from where the arm is; rejected, the reason on /rosout naming the joint, the
    value and the bound; the arm, run on, stays inside."""
    field, value, words = ISSUE_GOALS[case]
    q = np.tile(here(arm), (2, 1))
    fields = {'positions': q, 'velocities': np.zeros((2, N)), 'effort': np.zeros((2, N))}
    fields[field][1 if field == 'positions' else 0, 1] = value
    reason = arm.rejected(goal_msg([0.5, 1.0], **fields))
    assert words in reason, reason
    arm.run(0.3)
    assert arm.excess <= REST_BOUND


def test_an_interpolation_bulging_past_the_limit_between_points_is_rejected(arm):
    """Catches: only the points held to the range. Two points at 2.95 rad, leaving upward and
    arriving downward at 3 rad/s 0.4 s apart: the cubic between them reaches 3.25 rad."""
    q = np.tile(here(arm), (3, 1))
    q[:2, 1] = 2.95
    qd = np.zeros((3, N))
    qd[0, 1], qd[1, 1] = 3.0, -3.0
    reason = arm.rejected(goal_msg([0.5, 0.9, 1.5], q, qd))
    assert ("joint 'joint2': the cubic interpolation between points 0 and 1 reaches position "
            '3.25 at t = 0.7 s, above its limit 3') in reason, reason


def test_a_goal_over_the_size_bounds_is_rejected_saying_the_bound(arm):
    """Catches: a goal of any size taken (before: pd_controller's memory 114 -> 217 MB after
    two goals of 100,000 points). max_points and max_duration are set low here."""
    q = np.tile(here(arm), (MAX_POINTS + 1, 1))
    times = np.arange(MAX_POINTS + 1) * 0.01
    assert 'the trajectory has 201 points, more than max_points 200' in arm.rejected(
        goal_msg(times, q))
    assert 'the trajectory lasts 4.001 s, longer than max_duration 4 s' in arm.rejected(
        goal_msg([0.0, MAX_DURATION + 0.001], q[:2]))
    assert 'later than max_duration 4 s' in arm.rejected(    # (the states seen here may lag)
        goal_msg([0.0], q[:1], start_ns=arm.newest_stamp() + int((MAX_DURATION + 10) * NS)))
    handle = arm.send(goal_msg(times[:-1], q[:-1]))         # 200 points: taken
    assert handle.accepted
    arm.run(0.05)
    arm.cancel(handle)


def test_an_arm_found_outside_is_brought_back_and_never_sent_further_out(tmp_path):
    """The arm at rest 0.03 rad past joint2's limit (3.03 rad): a goal whose first point is
    outside is rejected; one whose first point (inside, 2.9 rad) comes 1 s after its start is
    taken, and from where the arm is the reference served never goes past 3.03 rad and the arm
    comes inside. (How psl homes an arm found outside: its first point inside, later than its
    start.)"""
    with server('pd', tmp_path, 'limits_outside') as arm:
        outside = START.copy()
        outside[1] = 3.03
        arm.place(outside)
        q = np.tile(outside, (2, 1))
        assert "joint 'joint2': position 3.03 at point 0" in arm.rejected(
            goal_msg([1.0, 2.0], q, np.zeros((2, N))))
        q[:, 1] = 2.9
        handle = arm.send(goal_msg([1.0, 2.0], q, np.zeros((2, N))))
        assert handle.accepted
        served = []
        for _ in range(int(2.2 * NS / PERIOD_NS)):
            served.append(np.asarray(arm.step().reference.positions)[1])
        status, code, why = arm.result(handle)
        assert code == FollowJointTrajectory.Result.SUCCESSFUL, why
        assert max(served) <= 3.03
        assert np.all(np.diff(served) <= 1e-12), 'the reference went outward'
        assert abs(arm.arm.q[1] - 2.9) < 0.01


# -- a generated family -----------------------------------------------------------------------
FAMILY_GOALS = 24


ANOMALIES = {   # what a generated goal has wrong (at most one thing), and how often
    'nothing': .40, 'a point far outside': .05, 'a point just outside': .06,
    'a velocity near the bound': .06, 'a huge velocity': .04, 'points 1 ns apart': .05,
    'an effort near the limit': .06, 'a huge effort': .03, 'one point too many': .05,
    'too long': .05, 'starting too late': .05, 'stamped in the past': .1}


def random_goal(rng: np.random.Generator, q_now: np.ndarray, newest_ns: int):
    """A goal around the bounds (seeded), with at most one anomaly (ANOMALIES): its point
    count (up to max_points, or one more), times (3 ms to 0.3 s apart, 1 ns now and then; up
    to max_duration, or past it), stamp (now, ahead, in the past, past max_duration ahead),
    positions (near the arm, or touching a limit at rest; just or far outside), velocities and
    accelerations (none, small; near the bound or huge) and efforts (within the torque limit;
    near or far past it)."""
    anomaly = rng.choice(list(ANOMALIES), p=list(ANOMALIES.values()))
    n_points = int(rng.choice([1, 2, 3, 5, 12, MAX_POINTS - 1, MAX_POINTS]))
    if anomaly == 'one point too many':
        n_points = MAX_POINTS + 1
    low_gap = -9 if anomaly == 'points 1 ns apart' else -2.5
    gaps = 10.0 ** rng.uniform(low_gap, np.log10(0.3), n_points)
    first = float(rng.choice([0.0, 1e-9, 0.05, 0.5]))
    times = first + np.concatenate([[0.0], np.cumsum(gaps[1:])])
    longest = MAX_DURATION + rng.uniform(1e-3, 0.5) if anomaly == 'too long' else MAX_DURATION
    if times[-1] > longest or anomaly == 'too long':
        times = times * longest / times[-1]
    touching = rng.random() < 0.4
    velocities = accelerations = effort = None
    if touching:                    # at rest at a limit: exact, no bulge
        j, side = rng.integers(N), rng.choice([LOW, HIGH])
        q = np.tile(q_now, (n_points, 1))
        q[:, j] = side - np.sign(side) * rng.uniform(0.0, 0.05, n_points)
        q[rng.integers(n_points), j] = side
        if rng.random() < 0.5:
            velocities = np.zeros((n_points, N))
    else:
        q = q_now + rng.uniform(-0.1, 0.1, (n_points, N))
        if rng.random() < 0.6:
            velocities = rng.uniform(-0.2, 0.2, (n_points, N))
            velocities[-1] = 0.0
            if rng.random() < 0.4:
                accelerations = rng.uniform(-1, 1, (n_points, N))
    if velocities is None and anomaly in ('a velocity near the bound', 'a huge velocity'):
        velocities = np.zeros((n_points, N))
    k, j = rng.integers(n_points), rng.integers(N)
    if anomaly == 'a point far outside':
        q[k, j] = rng.choice([10.0, 1e308, -1e308])
    elif anomaly == 'a point just outside':
        q[k, j] = rng.choice([-1, 1]) * (3.0 + 10.0 ** rng.uniform(-5, -1))
    elif anomaly == 'a velocity near the bound':
        velocities[k, j] = rng.choice([-1, 1]) * rng.uniform(99.0, 101.0)
    elif anomaly == 'a huge velocity':
        velocities[k, j] = 1e6
    if rng.random() < 0.5 or anomaly in ('an effort near the limit', 'a huge effort'):
        effort = rng.uniform(-30.0, 30.0, (n_points, N))
        if anomaly == 'an effort near the limit':
            effort[k, j] = rng.choice([-1, 1]) * rng.uniform(39.0, 41.0)
        elif anomaly == 'a huge effort':
            effort[k, j] = 1e9
    stamp = 0 if rng.random() < 0.7 else newest_ns + 100 * MS
    if anomaly == 'starting too late':
        stamp = newest_ns + int((MAX_DURATION + rng.uniform(0.01, 1.0)) * NS)
    elif anomaly == 'stamped in the past':
        stamp = newest_ns - int(rng.choice([10 * MS, NS, 10 * NS]))
    return goal_msg(times, q, velocities, accelerations, effort, stamp)


def test_a_generated_family_of_goals_never_moves_the_arm_past_its_limits(arm):
    """Catches: any goal that moves the arm past its range (before: accepted goals of 10 rad
    and 1e308 rad drove it 0.14-0.54 rad past), or a server that stops serving.

    24 goals (seeded) one after another, each run a while (a later one preempts it): the
    reference the server served (its controller_state) never left the range; the most the
    measured arm passed it (reported) is an impact on its stop, at most EXCESS_BOUND; a normal
    goal afterwards succeeds and leaves the arm at rest inside."""
    rng = np.random.default_rng(46)
    taken = 0
    for _ in range(FAMILY_GOALS):
        handle = arm.send(random_goal(rng, here(arm), arm.newest_stamp()))
        if handle.accepted:
            taken += 1
            arm.run(float(rng.choice([0.02, 0.1, 0.3])))
    assert 0 < taken < FAMILY_GOALS, f'{taken} of {FAMILY_GOALS} taken: not a family'
    home(arm)
    print(f'max excess over the range: the measured arm {arm.excess:.3g} rad, the reference '
          f'served {arm.reference_excess:.3g} rad ({taken} of {FAMILY_GOALS} goals taken)')
    # a goal taken while the arm is outside (after an impact on its stop) starts from where
    # the arm is: its reference may begin outside, never further out than the arm has been
    assert arm.reference_excess <= arm.excess, \
        f'the reference served left the range by {arm.reference_excess:.4g} rad, the arm ' \
        f'by {arm.excess:.4g}'
    if isinstance(arm, LockstepArm):      # no impact: the reference held exactly
        assert arm.reference_excess == 0.0, arm.reference_excess
    assert excess(arm.position()) == 0.0, f'the arm rests outside: {arm.position()}'
    assert arm.excess <= EXCESS_BOUND, f'the arm passed its range by {arm.excess:.4g} rad'


# -- a flood ----------------------------------------------------------------------------------
def test_every_goal_of_a_flood_after_a_homing_goal_is_answered(standard):
    """Catches: goal requests or answers lost under a flood (before: 136-195 of 200 answered
    after a homing goal; the action's services kept rclpy's 10 requests and answers, on the
    server and on the client).

    A homing goal (2 s, 200 points), then 200 goals in 2 s from one client: every goal
    answered and, for the accepted ones, every result."""
    arm = standard
    t, q, qd, qdd = quintic(START, START + [0.2, -0.2, 0.2], 2.0, MAX_POINTS)
    assert arm.send(goal_msg(t, q, qd, qdd)).accepted
    futures = []
    began = time.monotonic()
    for i in range(FLOOD):
        t, q, qd, qdd = quintic(START, START + 0.01 * (i % 5), 0.2, 20)
        futures.append(arm.action.send_goal_async(goal_msg(t, q, qd, qdd)))
        time.sleep(max(0.0, began + (i + 1) * FLOOD_SECONDS / FLOOD - time.monotonic()))
    arm.until(lambda: all(f.done() for f in futures),
              f'answers to all {FLOOD} goals ({sum(f.done() for f in futures)} came)', 60.0)
    handles = [f.result() for f in futures]
    assert all(h.accepted for h in handles)
    results = [h.get_result_async() for h in handles]
    arm.until(lambda: all(r.done() for r in results),
              f'all {FLOOD} results ({sum(r.done() for r in results)} came)', 60.0)
    ends = collections.Counter((r.result().status, r.result().result.error_string)
                               for r in results)
    # each preempted by the next one taken, the last one taken run to its end
    assert set(ends) <= {(GoalStatus.STATUS_ABORTED, PREEMPTED),
                         (GoalStatus.STATUS_SUCCEEDED, SUCCEEDED)}, ends
    assert ends[GoalStatus.STATUS_SUCCEEDED, SUCCEEDED] >= 1, ends
    home(arm)
