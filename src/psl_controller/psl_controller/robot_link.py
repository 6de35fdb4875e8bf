"""The executor's `psl_controller.episode.Robot` over ROS: a JointTrajectoryController's
``control_msgs/action/FollowJointTrajectory`` and a clock.

The controller (`RobotLink`, any JTC: psl's ``pd_controller``, psl's standard robot, a robot's
own): its ``<controller>/follow_joint_trajectory`` action, and its ``joints`` and
``command_interfaces`` parameters (`ControllerInfo`: what it drives, and whether goals may carry
the feed-forward torque). A goal is the episode's reference as a trajectory_msgs/JointTrajectory
(a point every control period: positions, velocities, and the feed-forward in ``effort`` on an
effort interface only; the last point at rest, as JTC requires), stamped with its start, the
task's tracking bound as every joint's ``path_tolerance``, no goal tolerance.

The clock (`CLOCKS`, the executor's ``clock`` parameter) is what differs between robots:

* `SimulatorClock`: psl's simulator, paused between episodes. Its ``sim/reset`` says the state
  (``probe``: the arm as it is, exact) and runs an episode of a given length (``teleport``: the
  arm put at the start posture first; ``drive``: from where it is). A goal starts at the
  simulator's current time; the episode's time runs when the reset starts it.
* `RobotClock`: a robot's own wall clock. The posture is the mean of its newest joint states
  (its stamps, its joint order, noise); a goal starts `LEAD` s after its newest state (a goal
  sent again after a late one: twice as long, and so on), and the episode's time runs anyway.
  Joint states that stop for `STALE` s while a goal runs fail it (the goal is cancelled: the
  controller holds), whatever the controller does about it.

Whether a goal came in time (`RobotLink.taken`): psl's controller ends a goal whose start has
passed with ``OLD_HEADER_TIMESTAMP``; a robot's JTC takes it and jumps into it, which its first
feedback shows (``desired.time_from_start`` already past the start): either way the goal was
late. Nothing is read from ``/diagnostics``.
"""
from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointTolerance
from rclpy.node import Node
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from psl_controller.episode import GoalResult, GoalSpec, Instance, RobotError
from psl_controller.follow_joint_trajectory import ACTION
from psl_controller.goal_limits import goal_points
from psl_controller.parameters import COMMAND_INTERFACES
from psl_controller.policy import Reference
from psl_controller.trajectory_controller import OLD_HEADER_TIMESTAMP
from psl_msgs.msg import TaskInstance
from psl_msgs.srv import ResetTask
from psl_ros import names
from psl_ros.action_client import ActionClient
from psl_ros.client import GoalRejected, send_goal
from psl_ros.futures import ask, wait_for
from psl_ros.hot_path import HotPath
from psl_ros.qos import LATCHED, SERVICES
from psl_ros.stamps import duration_msg, time_msg, to_ns
from psl_task.joint_selection import JointSelection

LEAD = 0.3              # s from a robot's newest state to a goal's start (it must reach the
                        # controller meanwhile: > 0.1 s seen under load)
STALE = 0.5             # s: a robot whose newest state is older does not stream
ACK_TIMEOUT = 5.0       # s for a server to appear, a goal to be answered, a first feedback
PARAMETER_TIMEOUT = 5.0  # s for the controller's parameter service (asked up to three times)
STATE_PAUSE = 0.01      # s between two takes of the robot's queued states
KEEP_STATES = 25        # the newest states kept (the homing check averages them)
SIM_RATE = 10.0         # robot s per wall s assumed of psl's simulator before its feedback says
IDLE_TIMEOUT = 10.0     # s for an episode of psl's simulator someone else started to end
REPORT_WAIT = 1.0       # s a live goal change waits for the controller's feedback to say the
                        # loop's rate (two feedbacks: 1/MONITOR_RATE apart)


def trajectory_msg(joint_names: list[str], ref: Reference, start_ns: int, effort: bool,
                   at_rest: bool = True) -> JointTrajectory:
    """A reference as a JointTrajectory stamped `start_ns`: its points as psl sends them
    (`psl_controller.goal_limits.goal_points`: a point per control period from its first,
    positions and velocities, with `at_rest` the last velocity zero), the feed-forward as
    effort if `effort`."""
    msg = JointTrajectory(joint_names=list(joint_names))
    msg.header.stamp = time_msg(start_ns)
    times, q, qd, u = goal_points(ref, at_rest)
    q, qd, u = q.tolist(), qd.tolist(), u.tolist()
    msg.points = [JointTrajectoryPoint(positions=q[k], velocities=qd[k],
                                       effort=u[k] if effort else [],
                                       time_from_start=duration_msg(int(times[k])))
                  for k in range(len(q))]
    return msg


@dataclasses.dataclass(frozen=True)
class ControllerInfo:
    """What a JointTrajectoryController says of itself: its joints and its interface."""

    joints: tuple[str, ...]
    interface: str              # one of COMMAND_INTERFACES

    @property
    def effort(self) -> bool:
        """Whether goals may carry the feed-forward torque."""
        return self.interface == 'effort'


def ask_controller(parameters: AsyncParameterClient, controller: str,
                   interface: str = '') -> ControllerInfo:
    """A JointTrajectoryController's ``joints`` and ``command_interfaces`` parameters, through
    the parameter client of its node; `interface` given: that one instead of the parameter's.
    RobotError when it does not answer or commands neither effort nor position. Reading
    parameters moves nothing."""
    if not parameters.wait_for_services(timeout_sec=ACK_TIMEOUT):
        raise RobotError(f'the controller {controller} does not answer (no parameter services '
                         f'of node {controller} within {ACK_TIMEOUT:g} s: is it running?)')
    try:
        response = ask(lambda: parameters.get_parameters(['joints', 'command_interfaces']),
                       PARAMETER_TIMEOUT, f'{controller}/get_parameters')
    except TimeoutError as exc:
        raise RobotError(str(exc)) from None
    joints, interfaces = (list(v.string_array_value) for v in response.values)
    if not interface:
        known = [i for i in interfaces if i in COMMAND_INTERFACES]
        if not known:
            raise RobotError(f'the controller {controller} commands '
                             f'{interfaces or "no interface it names"}: psl drives a '
                             f'JointTrajectoryController on {" or ".join(COMMAND_INTERFACES)} '
                             '(give the interface if its parameters do not say it)')
        interface = 'effort' if 'effort' in known else known[0]
    return ControllerInfo(tuple(joints), interface)


def misfit(info: ControllerInfo, controller: str, joint_names: list[str], feedforward: bool,
           task: str) -> str:
    """Why the controller cannot run the task ('' if it can): it must drive the task's joints,
    and take effort if the task's policy learns a feed-forward torque."""
    if info.joints and sorted(info.joints) != sorted(joint_names):
        return (f'the controller {controller} drives the joints {list(info.joints)}, task '
                f'{task!r} the joints {list(joint_names)}')
    if feedforward and not info.effort:
        return (f'task {task!r} learns a feed-forward torque, and the controller {controller} '
                f'commands {info.interface}: a {info.interface} interface takes no effort (run '
                'a JointTrajectoryController on the effort interface, or a kinematic task)')
    return ''


class _Goal:
    """A goal sent: its handle, result future, newest feedback and when it came."""

    def __init__(self, handle, start_ns: int, duration_ns: int, progress=None):
        self.handle, self.start_ns = handle, start_ns
        self.duration_ns, self.progress = max(1, duration_ns), progress
        self.result = handle.get_result_async()
        self.event = threading.Event()
        self.result.add_done_callback(lambda _: self.event.set())
        self.feedback: tuple[int, float] | None = None      # (time from start [ns], monotonic)
        self.first_feedback = threading.Event()
        self.rated = threading.Event()      # two feedbacks came: the rate is measured
        self.rate: float | None = None                      # robot s per wall s
        self.began: float | None = None     # monotonic time the episode's clock began

    def on_feedback(self, msg) -> None:
        served, now = to_ns(msg.feedback.desired.time_from_start), time.monotonic()
        last = self.feedback
        if last is not None and now > last[1] and served > last[0]:
            self.rate = (served - last[0]) * 1e-9 / (now - last[1])
            self.rated.set()
        self.feedback = (served, now)
        self.first_feedback.set()
        if self.progress is not None:
            self.progress(min(1.0, max(0.0, served / self.duration_ns)))

    def answer(self) -> GoalResult | None:
        if not self.result.done():
            return None
        result = self.result.result().result
        return GoalResult(result.error_code, result.error_string)


class SimulatorClock:
    """psl's simulator's time (module docstring): its ``sim/reset``."""

    name = 'simulator'
    can_teleport = True
    runs_between_episodes = False       # paused: no goal can come after its start then
    rate_from_feedback = True           # lockstep: as fast as the loop; realtime: 1

    def __init__(self, link: 'RobotLink'):
        self.link = link
        self.reset_client = link.node.create_client(ResetTask, names.RESET,
                                                    callback_group=link.group,
                                                    qos_profile=SERVICES)

    def _reset(self, mode: str, duration: float = 0.0) -> ResetTask.Response:
        client, link = self.reset_client, self.link
        if not client.wait_for_service(timeout_sec=ACK_TIMEOUT):
            raise RobotError(f'the simulator service {client.srv_name} is not available')
        try:
            response = wait_for(client.call_async(ResetTask.Request(
                task=link.task_name, tau=link.tau.tolist(), mode=mode, duration=duration)),
                10.0, client.srv_name)
        except TimeoutError as exc:
            raise RobotError(str(exc)) from None
        if not response.success:
            raise RobotError(response.message)
        return response

    def measure(self, count: int) -> tuple[int, np.ndarray, np.ndarray]:
        response = self.wait_for_end(IDLE_TIMEOUT)
        select = self.link.selection
        try:
            q = select.pick(response.joint_names, response.position)
            qd = select.pick(response.joint_names, response.velocity)
        except ValueError as exc:
            raise RobotError(f'the simulator: {exc}') from None
        return to_ns(response.stamp), q, qd

    def start_time(self, attempt: int = 0) -> int:
        return self.measure(1)[0]

    def begin(self, start_ns: int, num_steps: int, mode: str) -> int:
        response = self._reset(mode, num_steps * self.link.control_period)
        return to_ns(response.stamp)

    def rate(self, goal: _Goal) -> float:
        """Lockstep runs as fast as the loop, realtime at 1: the feedback's, else a guess."""
        return goal.rate or SIM_RATE

    def wait(self, seconds: float, done) -> None:
        """The simulator's time runs only in an episode: a drive episode of `seconds` (the
        controller holds what it ran), to its end."""
        if not done():
            self._reset('drive', seconds)
            self.wait_for_end(seconds + self.link.margin)

    def wait_for_end(self, timeout: float) -> ResetTask.Response:
        """The simulator's state once an episode it runs has ended (its probe answers; a
        refusal for another reason is raised after `timeout` s)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return self._reset('probe')
            except RobotError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.01)

    def watch(self, goal: _Goal) -> str:
        return ''


class RobotClock:
    """A robot's own wall clock (module docstring): its joint states."""

    name = 'robot'
    can_teleport = False
    runs_between_episodes = True
    rate_from_feedback = False          # the wall clock's

    def __init__(self, link: 'RobotLink'):
        self.link = link

    def measure(self, count: int) -> tuple[int, np.ndarray, np.ndarray]:
        return self.link.measured(count)

    def start_time(self, attempt: int = 0) -> int:
        """LEAD s after the newest state, twice that for a goal sent again, and so on: a
        burst of load that made one goal late may last."""
        return self.link.measured(1)[0] + int(LEAD * 2 ** attempt * 1e9)

    def begin(self, start_ns: int, num_steps: int, mode: str) -> int:
        return start_ns

    def rate(self, goal: _Goal) -> float:
        return 1.0

    def wait(self, seconds: float, done) -> None:
        until = time.monotonic() + seconds
        while time.monotonic() < until and not done():
            time.sleep(self.link.control_period)

    def watch(self, goal: _Goal) -> str:
        """Why the goal cannot go on ('' if it can): the robot's states have stopped."""
        silent = time.monotonic() - self.link.state_seen
        if silent > STALE:
            return (f'joint states stopped: none for {silent:.3f} s on '
                    f'{self.link.states_topic}; the goal was cancelled (the controller holds)')
        return ''


CLOCKS = {clock.name: clock for clock in (SimulatorClock, RobotClock)}


class RobotLink:
    """`psl_controller.episode.Robot` for one task instance at a time (`prepare`), over the
    executor's node (module docstring)."""

    def __init__(self, node: Node, controller: str, clock: str, group,
                 command_interface: str = '', timeout_margin: float = 10.0, matches=None):
        self.node, self.group, self.margin = node, group, timeout_margin
        self.controller = controller.rstrip('/')
        action = f'{self.controller}/{ACTION}'
        self.action_name = node.resolve_topic_name(action)
        self.client = ActionClient(node, FollowJointTrajectory, action, callback_group=group)
        self.parameters = AsyncParameterClient(node, self.controller, callback_group=group)
        self.command_interface = command_interface
        self._info: ControllerInfo | None = None
        self.pub_task = (node if matches is None else matches).create_publisher(
            TaskInstance, names.TASK_INSTANCE, LATCHED)
        self._states: list[tuple] = []          # (stamp [ns], q, qd, names), the newest last
        self.state_seen = 0.0                   # monotonic time of the newest
        self._state_cv = threading.Condition()
        self.states_topic = node.resolve_topic_name(names.JOINT_STATES)
        self.clock = CLOCKS[clock](self)
        self.can_teleport = self.clock.can_teleport
        self.state_path = None
        if clock == RobotClock.name:
            # the robot's states at its rate, needed only now and then: a lean loop takes
            # what queued every STATE_PAUSE s (the executor's callbacks would cost a core)
            self.state_path = HotPath(node, 'robot_states', pause=STATE_PAUSE)
            qos = QoSProfile(depth=KEEP_STATES, reliability=ReliabilityPolicy.RELIABLE)
            if matches is not None:         # reported (`psl_ros.matching`)
                matches.subscribe(self.state_path, JointState, names.JOINT_STATES,
                                  self._on_state, qos)
            else:
                self.state_path.subscribe(JointState, names.JOINT_STATES, self._on_state, qos)
            self.state_path.start()
        self.task_name, self.tau = '', np.zeros(0)
        self.joint_names: list[str] = []
        self.selection: JointSelection | None = None
        self.control_period = 0.0
        self.control_period_ns = 0
        self.episode_running = False            # between begin and the end of finish
        self._last_goal: _Goal | None = None    # the goal sent last

    def destroy(self) -> None:
        if self.state_path is not None:
            self.state_path.stop()

    def prepare(self, task_name: str, tau: np.ndarray, joint_names: list[str],
                control_period: float) -> None:
        """The task instance the next episodes are of."""
        self.task_name, self.tau = task_name, np.asarray(tau, dtype=float)
        if joint_names != self.joint_names:
            self.joint_names, self.selection = list(joint_names), JointSelection(joint_names)
        self.control_period = control_period
        self.control_period_ns = int(round(control_period * 1e9))
        self.episode_running = False

    # -- the controller -------------------------------------------------------------------
    def info(self) -> ControllerInfo:
        """The controller's joints and interface (asked once: `ask_controller`)."""
        if self._info is None:
            self._info = ask_controller(self.parameters, self.controller,
                                        self.command_interface)
        return self._info

    def check(self, joint_names: list[str], feedforward: bool, task: str) -> ControllerInfo:
        """The controller, checked against a task (`misfit`); RobotError with the line."""
        info = self.info()
        why = misfit(info, self.controller, joint_names, feedforward, task)
        if why:
            raise RobotError(why)
        return info

    def send(self, goal: GoalSpec) -> _Goal:
        info = self.info()
        msg = FollowJointTrajectory.Goal()
        msg.trajectory = trajectory_msg(self.joint_names, goal.reference, goal.start_ns,
                                        info.effort)
        if goal.path_tolerance > 0.0:
            msg.path_tolerance = [JointTolerance(name=j, position=goal.path_tolerance)
                                  for j in self.joint_names]
        # no goal tolerance: the goal ends with its last point (the reward judges the end)
        msg.goal_tolerance = [JointTolerance(name=j, position=-1.0, velocity=-1.0)
                              for j in self.joint_names]
        box: list[_Goal] = []

        def on_feedback(feedback) -> None:
            if box:
                box[0].on_feedback(feedback)
        try:
            handle = send_goal(self.client, msg, ACK_TIMEOUT, self.action_name,
                               feedback=on_feedback)
        except GoalRejected:        # psl checked it against the model's limits (`Episode`)
            raise RobotError(f'the controller {self.controller} rejected the goal (its limits '
                             "may be narrower than the model's: see its log)") from None
        except (TimeoutError, RuntimeError) as exc:
            raise RobotError(f'the controller did not take the goal: {exc}') from None
        duration = int(round(float(goal.reference.t[-1]) * 1e9))
        box.append(_Goal(handle, goal.start_ns, duration, goal.progress))
        self._last_goal = box[0]
        return box[0]

    def taken(self, goal: _Goal, before_ns: int) -> bool:
        """False when the goal came late (module docstring); RobotError when neither its
        first feedback nor its result comes within ACK_TIMEOUT s while the clock runs."""
        if not (self.clock.runs_between_episodes or self.episode_running):
            return True         # psl's simulator is paused: nothing has passed the start
        deadline = time.monotonic() + ACK_TIMEOUT
        while time.monotonic() < deadline:
            answer = goal.answer()
            if answer is not None:
                return answer.error_code != OLD_HEADER_TIMESTAMP
            if goal.feedback is not None:
                return goal.start_ns + goal.feedback[0] < before_ns
            goal.first_feedback.wait(0.005)
        raise RobotError(f'the controller {self.controller} neither answered nor reported on '
                         f'the goal within {ACK_TIMEOUT:g} s')

    def cancel(self, goal: _Goal) -> None:
        try:
            wait_for(goal.handle.cancel_goal_async(), ACK_TIMEOUT, f'{self.action_name} cancel')
        except TimeoutError as exc:
            self.node.get_logger().error(f'cancel: {exc}')

    def finish(self, goal: _Goal, end_ns: int, timeout: float,
               cancelled=lambda: False) -> GoalResult:
        deadline = time.monotonic() + timeout + LEAD
        try:
            while not goal.event.wait(0.02):
                why = 'rollout canceled' if cancelled() else self.clock.watch(goal)
                if why:
                    self.cancel(goal)
                    raise RobotError(why)
                if time.monotonic() > deadline:
                    self.cancel(goal)
                    raise RobotError(f'the controller {self.controller} gave no result within '
                                     f'{timeout:.1f} s of the goal\'s start')
            if self.state_path is not None:     # the robot's clock: its state of the end
                self.wait_for_state(end_ns, max(0.5, deadline - time.monotonic()))
            return goal.answer()
        finally:
            self.episode_running = False

    def progress(self, goal: _Goal) -> tuple[int, float, float] | None:
        """From the goal's newest feedback, once two have measured the loop's rate (waited
        for up to REPORT_WAIT s once its clock began), else (0, when its clock began, the
        clock's rate guess); None before the clock began."""
        if goal is None or goal.began is None:
            return None
        if self.clock.rate_from_feedback and not goal.rated.is_set() and goal.answer() is None:
            goal.rated.wait(REPORT_WAIT)
        if goal.feedback is None:
            return 0, goal.began, self.clock.rate(goal)
        served, seen = goal.feedback
        return served, seen, self.clock.rate(goal)

    # -- the clock ------------------------------------------------------------------------
    def measure(self, count: int) -> tuple[int, np.ndarray, np.ndarray]:
        return self.clock.measure(count)

    def start_time(self, attempt: int = 0) -> int:
        return self.clock.start_time(attempt)

    def begin(self, start_ns: int, num_steps: int, mode: str) -> int:
        began = self.clock.begin(start_ns, num_steps, mode)
        self.episode_running = True
        if self._last_goal is not None:
            self._last_goal.began = time.monotonic()
        return began

    def wait(self, seconds: float, done) -> None:
        self.clock.wait(seconds, done)

    def announce(self, instance: Instance) -> None:
        self.pub_task.publish(TaskInstance(
            stamp=time_msg(instance.stamp_ns), task=instance.task, tau=instance.tau.tolist(),
            num_steps=instance.num_steps, control_period=instance.control_period,
            homing=instance.homing))

    # -- a robot's states -----------------------------------------------------------------
    def _on_state(self, msg: JointState) -> None:
        with self._state_cv:
            self._states.append((to_ns(msg.header.stamp), np.asarray(msg.position, dtype=float),
                                 np.asarray(msg.velocity, dtype=float), list(msg.name)))
            del self._states[:-KEEP_STATES]
            self.state_seen = time.monotonic()
            self._state_cv.notify_all()

    def measured(self, count: int = 1) -> tuple[int, np.ndarray, np.ndarray]:
        """(stamp of the newest, mean q, mean qd) of the robot's newest `count` states, the
        task's joints; RobotError when the robot does not stream or lacks a joint."""
        deadline = time.monotonic() + ACK_TIMEOUT       # the first: discovery may take this
        while not self._states or time.monotonic() - self.state_seen > STALE:
            if time.monotonic() > deadline:
                raise RobotError(f'the robot publishes no joint states on {self.states_topic} '
                                 f'(none for {STALE:g} s, waited {ACK_TIMEOUT:g} s)')
            time.sleep(0.01)
        with self._state_cv:
            states = self._states[-count:]
        try:
            q = np.mean([self.selection.pick(n, q) for _, q, _, n in states], axis=0)
            qd = np.mean([self.selection.pick(n, qd) for _, _, qd, n in states], axis=0)
        except ValueError as exc:
            raise RobotError(f'the robot: {exc}') from None
        return states[-1][0], q, qd

    def wait_for_state(self, end_ns: int, timeout: float) -> None:
        """Until a state stamped `end_ns` or later came (RobotError after `timeout` s or when
        the states stop)."""
        deadline = time.monotonic() + timeout
        with self._state_cv:
            while not (self._states and self._states[-1][0] >= end_ns):
                if time.monotonic() > deadline:
                    raise RobotError(f'no joint state of the episode\'s end within {timeout:.1f} '
                                     f's')
                if time.monotonic() - self.state_seen > STALE and self._states:
                    raise RobotError(f'joint states stopped: none for '
                                     f'{time.monotonic() - self.state_seen:.3f} s on '
                                     f'{self.states_topic}')
                self._state_cv.wait(0.02)
