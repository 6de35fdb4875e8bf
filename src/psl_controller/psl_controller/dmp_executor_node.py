"""The DMP executor node: serves the ``execute_rollout`` action (psl_msgs/ExecuteRollout).

One rollout: check the goal, give the controller the task's gains if the task changed (its
parameter service, validated there), roll out the policy for theta on the control grid, check the
reference against the task's safety limits (`psl_task.safety_check`: a refused candidate is never
sent, no episode runs, the result carries the penalty and the reason in ``refused``), send the
commanded trajectory to the controller (``joint_trajectory``, stamped zero = "start with the
next state"), start an episode of the task instance with the simulator's ``sim/reset``
service, then wait for the reward evaluator's ``rollout_evaluation`` of that episode and
return it. Rollouts run one at a time; a bad goal gets ``success=false`` and a message.

Goal changes (`TaskPolicy.reference_with_new_goal`: the DMP's attractor moves smoothly to a new
goal from a switch time on):

- known before the start (the action goal's ``new_goal``, ``new_goal_time``): the reference is
  computed with the change, and the change is announced to the evaluator before the reset
  (service ``reward_evaluator/goal_change``, psl_msgs/GoalChange stamped zero = the next
  episode), so the episode is scored against the new goal. Deterministic: the same as a batch
  recomputation.
- live (psl_msgs/GoalUpdate on ``goal_update`` while a rollout runs): the switch is moved to
  ``max(time_from_start, the episode's step + a lead)``. The step is bounded from the
  simulator's progress reports on /diagnostics (steps done, steps per second) and the wall
  time since, at `RATE_MARGIN` times the measured rate; the lead covers `LOAD_FACTOR` times
  the wall time this rollout's first trajectory took to compute, build and publish (in
  lockstep, where the loop runs faster than real time on every core, the change comes a
  second or more after the request). The executor announces the change (stamped with the
  episode, with the changed trajectory's last point) to the evaluator and has its answer,
  checks that the episode is still short of the switch, and sends the
  controller the trajectory with the part from the switch on replaced, stamped with the
  episode's start: the controller takes it from its next state on, and refuses it if it would
  leave the reference already served; the evaluator then sees that the controller's last
  reference is not the announced one and keeps the episode's goal, so the evaluation always
  agrees with what was executed. One goal change per rollout; an update that comes too late,
  names another episode, holds a bad goal or a time outside the episode, or whose spliced
  reference the safety check refuses changes nothing, and the result message says why.

Every reference that reaches the controller passes the task's safety check: the rollout's,
a live goal change's spliced one, and a drive reset's homing quintic (whose feed-forward is
the model's inverse dynamics with the instance applied: it holds the arm against gravity).

A robot psl does not simulate (``robot: external``): it only publishes ``joint_states`` (its
stamps, its joint order) and takes ``effort_command``; nobody serves ``sim/reset``. psl runs
each episode itself, from the measured joint states alone: a homing quintic from the measured
posture to the start posture (always: the robot is wherever it was left), stamped to start
`LEAD` s after the newest state, announced on ``task_instance`` with ``homing: true`` (the
world's tau: psl's simulator playing a robot places it), run until a state at its end came,
then checked against ``homing.tolerance`` on the mean of the last `SETTLE_STATES` states
(noise), again each new state for up to another ``homing.settle_time`` (a robot settles in
its own time); an arm at rest off the start (the robot is heavier than its model) is held
again with a corrected torque, up to `HOLD_CORRECTIONS` times; then the primitive, stamped
the same way, its episode announced on ``task_instance`` by the executor; the evaluator
matches states and references by the robot's stamps (`psl_optimizer.episode_grid`). A state
loss the controller's watchdog reports for the episode's trajectory fails the rollout at
once, with the controller's reason.
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time

import numpy as np
import rclpy
from rclpy.action import CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile, ReliabilityPolicy
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from psl_controller.homing import corrected_hold, hold_stiffness, homing_reference
from psl_controller.parameters import ExecutorParameters
from psl_controller.policy import Reference, TaskPolicy, policy_for
from psl_msgs.action import ExecuteRollout
from psl_msgs.msg import GoalUpdate, RolloutEvaluation, TaskInstance
from psl_msgs.srv import GoalChange, ResetTask
from psl_ros import names
from psl_ros.action_server import ActionServer
from psl_ros.futures import ask, wait_for
from psl_ros.guard import guard_subscription
from psl_ros.hot_path import HotPath
from psl_ros.matching import PUBLISHER, SUBSCRIPTION, MatchedEndpoints, MatchReport
from psl_ros.node_main import run_node
from psl_ros.parameters import check_update, declare
from psl_ros.qos import LATCHED, RELIABLE, SERVICES
from psl_ros.stamps import duration_msg, time_msg, to_ns
from psl_task.arm_model import ArmModel, joint_names_of
from psl_task.joint_selection import JointSelection
from psl_task.safety_check import SafetyCheck, Verdict
from psl_task.task import TaskDefinition, TaskError, load_task

LEAD_STEPS = 5          # control periods of lead at the least
RATE_MARGIN = 1.5       # the loop may run this many times faster than last measured
LOAD_FACTOR = 3.0       # computing and publishing a trajectory during an episode (the loop
                        # busy on every core) may take this many times longer than before it
LIVE_ATTEMPTS = 4       # switch times tried, each later, before a live change gives up
DEFAULT_RATE = 5000.0   # steps/s assumed before the simulator has reported any
REPORT_WAIT = 1.0       # s a live change waits for the simulator's report of the episode's start
ACK_TIMEOUT = 5.0       # s for a subscriber or service to appear, a message to be acknowledged
PARAMETER_TIMEOUT = 5.0  # s for the controller's parameter service to answer a request (asked
                         # up to three times: `psl_ros.futures.ask`)
LEAD = 0.3              # s from the newest state of an external robot to a trajectory's start
                        # (it must reach the controller meanwhile: > 0.1 s seen under load)
STALE = 0.5             # s: an external robot whose newest state is older is not streaming
# what the controller reports of a trajectory (pd_controller_node): a late one is sent again,
# the others fail the rollout with the controller's reason
FAULTS = ('state loss', 'late trajectory', 'tracking abort')
TAKEN = 'trajectory taken'      # the controller's acknowledgement of a stamped trajectory
SETTLE_STATES = 25      # the states averaged for the homing check on an external robot
STATE_PAUSE = 0.01      # s between two takes of the robot's queued states
HOLD_CORRECTIONS = 3    # holds with a corrected torque when homing comes to rest off the start


def trajectory_msg(joint_names: list[str], ref: Reference) -> JointTrajectory:
    msg = JointTrajectory()
    msg.joint_names = list(joint_names)
    dt_ns = int(round((ref.t[1] - ref.t[0]) * 1e9)) if len(ref.t) > 1 else 0
    for k in range(len(ref.t)):
        msg.points.append(JointTrajectoryPoint(
            positions=ref.q[k].tolist(), velocities=ref.qd[k].tolist(),
            effort=ref.u_ffwd[k].tolist(), time_from_start=duration_msg(k * dt_ns)))
    return msg


def penalty_evaluation(task_id: str, tau, task: TaskDefinition, component: str,
                       verdict: Verdict) -> RolloutEvaluation:
    """The evaluation of a candidate the safety check refused or whose episode the controller
    aborted: the task's penalty minus the violation (`Verdict.penalty`), not fulfilled, the
    violation as its one component."""
    return RolloutEvaluation(task=task_id, tau=list(tau), reward=verdict.penalty(
        task.safety.penalty), fulfilled=False, component_names=[component],
        component_values=[verdict.violation])


@dataclasses.dataclass
class _Rollout:
    """The rollout that runs, as far as a live goal change needs it."""

    goal: ExecuteRollout.Goal
    task: TaskDefinition
    policy: TaskPolicy
    joint_names: list[str]
    reference: Reference            # what the controller tracks
    prepare_cost: float = 0.0       # [s] wall time to compute, build and publish the first one
    publish_cost: float = 0.0       # [s] ... of which to publish it
    reset_sent: float = 0.0         # monotonic time of the reset request
    t0: int | None = None           # the episode's first state [ns], once the reset answered
    num_steps: int = 0
    change_time: float | None = None    # [s] the goal change made, if any
    pending: GoalUpdate | None = None   # a live update that came before the reset answered
    notes: list[str] = dataclasses.field(default_factory=list)   # for the result message


def splice(old: Reference, new: Reference, k: int) -> Reference:
    """old's points before index k, new's from k on."""
    return Reference(*(np.concatenate([a[:k], b[k:]])
                       for a, b in zip((old.t, old.q, old.qd, old.u_ffwd),
                                       (new.t, new.q, new.qd, new.u_ffwd))))


class DMPExecutor(Node):

    def __init__(self):
        super().__init__('dmp_executor')
        # every update (and declaration) checked by ExecutorParameters (one place)
        self.add_on_set_parameters_callback(
            lambda params: check_update(self, ExecutorParameters, params))
        declare(self, ExecutorParameters)
        group = ReentrantCallbackGroup()
        self.matches = MatchReport(self)        # what the loop's endpoints matched
        self.pub_trajectory = self.matches.create_publisher(JointTrajectory,
                                                            names.JOINT_TRAJECTORY, RELIABLE)
        self.reset_client = self.create_client(ResetTask, names.RESET, callback_group=group,
                                               qos_profile=SERVICES)
        self.matches.create_subscription(RolloutEvaluation, names.ROLLOUT_EVALUATION,
                                         self.on_evaluation, RELIABLE, callback_group=group)
        self.create_subscription(DiagnosticArray, names.DIAGNOSTICS,
                                 guard_subscription(self.get_logger(), names.DIAGNOSTICS,
                                                    self.on_diagnostics), 10,
                                 callback_group=group)
        self.goal_change_client = self.create_client(GoalChange, names.GOAL_CHANGE,
                                                     callback_group=group, qos_profile=SERVICES)
        self.matches.create_subscription(GoalUpdate, names.GOAL_UPDATE, self.on_goal_update,
                                         10, callback_group=group)
        # an external robot: psl runs the episodes from its joint states
        self.external = self.get_parameter('robot').value == 'external'
        self._states: list[tuple] = []          # (stamp [ns], q, qd, names), the newest last
        self._state_seen = 0.0                  # monotonic time of the newest
        self._selections: dict = {}             # task path -> its JointSelection
        # trajectory start [ns] -> (what of FAULTS, why, violation) the controller reported
        self._faults: dict[int, tuple[str, str, float]] = {}
        self._taken: set[int] = set()           # starts [ns] of trajectories the controller took
        if self.external:
            # the controller's report of its robot topics (remapped as this node's)
            self.loop_reports = MatchedEndpoints(self, callback_group=group)
            self.pub_task = self.matches.create_publisher(TaskInstance, names.TASK_INSTANCE,
                                                          LATCHED)
            # the robot's states at its rate (500 Hz), needed only now and then: a lean loop
            # takes what queued every STATE_PAUSE s (the executor's callbacks cost a core)
            self.state_path = HotPath(self, 'robot_states', pause=STATE_PAUSE)
            self.state_path.subscribe(JointState, names.JOINT_STATES, self.on_state,
                                      QoSProfile(depth=SETTLE_STATES,
                                                 reliability=ReliabilityPolicy.RELIABLE))
            self.state_path.start()
        self._rollout_lock = threading.Lock()
        self._safety_checks: dict = {}          # task path -> SafetyCheck
        # gains per task: the controller gets a rollout's task's gains when they differ from
        # the gains it runs (its parameter service validates them)
        self.controller_parameters = AsyncParameterClient(self, 'pd_controller',
                                                          callback_group=group)
        self._gains: tuple | None = None        # (kp, kd, tracking bound) the controller runs
        self._cv = threading.Condition()
        self._evaluations: dict[int, RolloutEvaluation] = {}   # by episode start [ns]
        self._progress: dict[int, float] = {}   # episode start [ns] -> fraction done
        # episode start [ns] -> (steps done, steps per second, monotonic time of the report)
        self._reports: dict[int, tuple[int, float, float]] = {}
        self._last_rate = DEFAULT_RATE          # steps/s of the last report
        self._live_lock = threading.Lock()      # guards _running and live changes
        self._running: _Rollout | None = None
        self._server = ActionServer(
            self, ExecuteRollout, names.EXECUTE_ROLLOUT, execute_callback=self.execute,
            goal_callback=lambda goal: GoalResponse.ACCEPT,
            cancel_callback=lambda handle: CancelResponse.ACCEPT, callback_group=group)
        self.get_logger().info('serving execute_rollout')

    def on_evaluation(self, msg: RolloutEvaluation) -> None:
        with self._cv:
            self._evaluations[to_ns(msg.stamp)] = msg
            self._cv.notify_all()

    def destroy_node(self):
        if self.external:
            self.state_path.stop()
        super().destroy_node()

    def on_state(self, msg: JointState) -> None:
        """An external robot's joint state: the task's joints by name, kept (the newest few)."""
        self._states.append((to_ns(msg.header.stamp), np.asarray(msg.position, dtype=float),
                             np.asarray(msg.velocity, dtype=float), list(msg.name)))
        del self._states[:-SETTLE_STATES]
        self._state_seen = time.monotonic()

    def _measured(self, task: TaskDefinition, count: int = 1) -> tuple[int, np.ndarray,
                                                                        np.ndarray]:
        """(stamp of the newest, mean q, mean qd) of the robot's newest `count` states, the
        task's joints; RuntimeError when the robot does not stream or lacks a joint."""
        deadline = time.monotonic() + ACK_TIMEOUT       # the first: discovery may take this
        while not self._states or time.monotonic() - self._state_seen > STALE:
            if time.monotonic() > deadline:
                raise RuntimeError(f'the robot publishes no joint states on '
                                   f'{self.resolve_topic_name(names.JOINT_STATES)} (none for '
                                   f'{STALE:g} s, waited {ACK_TIMEOUT:g} s)')
            time.sleep(0.01)
        if task.path not in self._selections:   # compiles the model: once per task
            self._selections[task.path] = JointSelection(joint_names_of(task))
        select = self._selections[task.path]
        states = self._states[-count:]
        try:
            q = np.mean([select.pick(names_, q) for _, q, _, names_ in states], axis=0)
            qd = np.mean([select.pick(names_, qd) for _, _, qd, names_ in states], axis=0)
        except ValueError as exc:
            raise RuntimeError(f'the robot: {exc}') from None
        return states[-1][0], q, qd

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        """The simulator reports episode progress about every tenth of an episode; the
        controller a state loss. /diagnostics is shared by every rollout worker: only this
        namespace's nodes count."""
        namespace = self.get_namespace().rstrip('/')
        controller = f'{namespace}/pd_controller: '
        for status in msg.status:
            kind = status.name[len(controller):]
            if not status.name.startswith(controller) or kind not in (*FAULTS, TAKEN):
                continue
            values = {kv.key: kv.value for kv in status.values}
            start = int(values.get('trajectory_start_ns', 0))
            with self._cv:
                if kind != TAKEN:
                    self._faults[start] = (kind, status.message, float(values.get(
                        'violation', 0.0)))
                elif self.external:
                    self._taken.add(start)
                self._cv.notify_all()
        mine = namespace + '/sim:'
        for status in msg.status:
            if not status.name.startswith(mine):
                continue
            values = {kv.key: kv.value for kv in status.values}
            if 'steps_done' in values and 'episode_start_ns' in values:
                t0, done = int(values['episode_start_ns']), int(values['steps_done'])
                self._progress[t0] = done / max(1, int(values['steps']))
                rate = float(values.get('steps_per_second', 0.0))
                if rate > 0.0:
                    self._last_rate = rate
                with self._cv:
                    self._reports[t0] = (done, rate, time.monotonic())
                    self._cv.notify_all()

    def execute(self, goal_handle) -> ExecuteRollout.Result:
        with self._rollout_lock:
            result = ExecuteRollout.Result()
            try:
                result.evaluation, notes, result.refused, result.aborted = self._rollout(
                    goal_handle)
                done = ('refused by the safety check' if result.refused else
                        result.aborted if result.aborted else 'rollout done')
                result.success, result.message = True, '; '.join([done] + notes)
                goal_handle.succeed()
            except (TaskError, ValueError, RuntimeError, TimeoutError) as exc:
                result.success, result.message = False, str(exc)
                self.get_logger().warning(f'rollout failed: {exc}')
                if goal_handle.is_cancel_requested:
                    goal_handle.canceled()
                else:
                    goal_handle.abort()
            return result

    def _rollout(self, goal_handle) -> tuple[RolloutEvaluation, list[str], str, str]:
        """(evaluation, notes, the safety check's reason or '', the controller's reason for an
        aborted episode or '')."""
        goal = goal_handle.request
        task = load_task(goal.task)
        tau, theta = np.asarray(goal.tau), np.asarray(goal.theta)
        task.validate_tau(tau)
        policy = policy_for(task)
        started = time.monotonic()
        changes = len(goal.new_goal) > 0
        if changes:
            reference = policy.reference_with_new_goal(theta, tau, goal.new_goal_time,
                                                       np.asarray(goal.new_goal))
        else:
            reference = policy.reference(theta, tau)
        compute_cost = time.monotonic() - started
        verdict = self._safety(task).check(tau, reference.q, reference.qd)
        if not verdict.safe:        # never sent: no trajectory, no episode
            self.get_logger().info(f'candidate refused by the safety check: {verdict.reason}')
            return (penalty_evaluation(goal.task, goal.tau, task, 'safety_violation', verdict),
                    [verdict.reason], verdict.reason, '')
        if not self.external and not self.reset_client.wait_for_service(timeout_sec=5.0):
            raise RuntimeError('the simulator service sim/reset is not available')
        # joint order of the simulator, which the controller maps by name
        run = _Rollout(goal=goal, task=task, policy=policy, joint_names=joint_names_of(task),
                       reference=reference,
                       change_time=goal.new_goal_time if changes else None)
        with self._live_lock:
            self._running = run
        try:
            response = (self._robot_episode if self.external else self._start_episode)(
                run, changes, compute_cost)
            with self._live_lock:
                run.t0, run.num_steps = to_ns(response.stamp), response.num_steps
                if run.pending is not None:
                    self._change_live(run, run.pending)
            evaluation, aborted = self._await_evaluation(goal_handle, task, response)
            with self._live_lock:
                if run.change_time is not None and evaluation.goal_change_time < 0:
                    run.notes.append('the controller refused the changed trajectory (it came '
                                     'too late): the episode kept its goal')
                return evaluation, run.notes, '', aborted
        finally:
            with self._live_lock:
                self._running = None

    def _safety(self, task: TaskDefinition) -> SafetyCheck:
        if task.path not in self._safety_checks:
            self._safety_checks[task.path] = SafetyCheck(ArmModel(task))
        return self._safety_checks[task.path]

    def _start_episode(self, run: _Rollout, changes: bool,
                       compute_cost: float) -> ResetTask.Response:
        """Announce a goal change to the evaluator (if any), send the controller the
        trajectory, start the episode; the reset's response. `compute_cost`: the wall time
        the reference took to compute [s]."""
        goal = run.goal
        self._wait_for_subscriber(self.pub_trajectory, 'controller')
        reset = self.get_parameter('reset').value or run.task.homing.reset
        self._set_gains(run)
        if reset == 'drive':
            self._home(run)
        if changes:
            self._announce_known_change(run)
        try:
            building = time.monotonic()
            trajectory = trajectory_msg(run.joint_names, run.reference)
            publishing = time.monotonic()
            self.pub_trajectory.publish(trajectory)
            run.publish_cost = time.monotonic() - publishing
            run.prepare_cost = compute_cost + (publishing - building) + run.publish_cost
            self._acked(self.pub_trajectory, 'the controller did not receive the trajectory')
            run.reset_sent = time.monotonic()     # no step of the episode before this
            response = self._call(self.reset_client,
                                  ResetTask.Request(task=goal.task, tau=goal.tau, mode=reset))
            if not response.success:
                raise ValueError(response.message)
        except BaseException:
            if changes:        # no episode: the evaluator's next one has no goal change
                self._withdraw(GoalUpdate())
            raise
        return response

    def _robot_episode(self, run: _Rollout, changes: bool,
                       compute_cost: float) -> ResetTask.Response:
        """`_start_episode` on an external robot: psl homes the arm and starts the episode
        itself, announcing it on task_instance; a reset's response as if the simulator had."""
        goal, task = run.goal, run.task
        self._wait_for_subscriber(self.pub_trajectory, 'controller')
        self._robot_connected()
        self._set_gains(run)
        self._home_robot(run)
        if changes:
            self._announce_known_change(run)
        try:
            building = time.monotonic()
            trajectory = trajectory_msg(run.joint_names, run.reference)
            run.prepare_cost = compute_cost + (time.monotonic() - building)
            num_steps = task.num_steps_of(np.asarray(goal.tau))
            t0 = self._start_on_robot(trajectory, TaskInstance(
                task=goal.task, tau=list(goal.tau), num_steps=num_steps,
                control_period=task.control_period), task)
            run.reset_sent = time.monotonic()
        except BaseException:
            if changes:        # no episode: the evaluator's next one has no goal change
                self._withdraw(GoalUpdate())
            raise
        return ResetTask.Response(success=True, stamp=time_msg(t0), num_steps=num_steps,
                                  message='episode started by psl')

    def _robot_connected(self) -> None:
        """Wait (ACK_TIMEOUT) until the controller reports its command publisher matched with
        a subscriber (the robot's command controller) and its state subscription with a
        publisher (the robot's broadcaster), both halves; RuntimeError naming the topic."""
        controller = self.get_namespace().rstrip('/') + '/pd_controller'
        wanted = ((PUBLISHER, names.EFFORT_COMMAND, 'nothing takes the commands on'),
                  (SUBSCRIPTION, names.JOINT_STATES, 'nothing publishes joint states on'))
        deadline = time.monotonic() + ACK_TIMEOUT
        for kind, name, missing in wanted:
            topic = self.resolve_topic_name(name)
            while self.loop_reports.counts(kind, topic).get(controller, 0) < 1:
                if time.monotonic() > deadline:
                    raise RuntimeError(f'the controller reaches no robot: {missing} {topic} '
                                       f'(waited {ACK_TIMEOUT:g} s)')
                time.sleep(0.01)

    def _start_on_robot(self, trajectory: JointTrajectory, episode: TaskInstance,
                        task: TaskDefinition) -> int:
        """Send the controller `trajectory` stamped to start LEAD s after the robot's newest
        state, and announce `episode` (stamped the same) on task_instance; the start [ns] once
        the controller has taken it (its acknowledgement on /diagnostics). Sent again, later,
        when the controller refused it because the robot's states had passed its start."""
        for _ in range(3):
            newest, _, _ = self._measured(task)
            t0 = newest + int(LEAD * 1e9)
            trajectory.header.stamp = episode.stamp = time_msg(t0)
            self.pub_trajectory.publish(trajectory)
            self.pub_task.publish(episode)
            deadline = time.monotonic() + LEAD + ACK_TIMEOUT
            with self._cv:
                while t0 not in self._taken and t0 not in self._faults:
                    if time.monotonic() > deadline:
                        raise RuntimeError('the controller neither took nor refused the '
                                           f'trajectory within {LEAD + ACK_TIMEOUT:g} s')
                    self._cv.wait(timeout=0.05)
                self._taken.discard(t0)
                fault = self._faults.get(t0)
                if fault is None:
                    return t0
                if fault[0] != 'late trajectory':
                    raise RuntimeError(fault[1])
                del self._faults[t0]
            self.get_logger().warning(f'{fault[1]}: sending it again')
        raise RuntimeError(f'the trajectory did not reach the controller within {LEAD:g} s '
                           'of the robot\'s newest state, three times')

    def _home_robot(self, run: _Rollout) -> None:
        """`_home` on an external robot, from its measured joint states (module docstring).
        An arm that comes to rest off the start (the robot's gravity is not the model's) is
        held there again with the held torque corrected, up to HOLD_CORRECTIONS times
        (`psl_controller.homing.corrected_hold`)."""
        task, spec = run.task, run.task.homing
        _, q0, qd0 = self._measured(task)
        reference = self._homing(run, q0, qd0)
        self._run_on_robot(run, reference)
        q, qd = self._settled(run)
        held, waited = reference.u_ffwd[-1], float(reference.t[-1]) + spec.settle_time
        stiffness = None
        for _ in range(HOLD_CORRECTIONS):
            if self._homed(run, q, qd) or np.abs(qd).max() > spec.tolerance:
                break                                     # there, or not at rest
            if stiffness is None:
                stiffness = hold_stiffness(self._gains[0] if self._gains else
                                           task.controller.kp, self._inverse_dynamics(run),
                                           task.start_posture)
            hold = corrected_hold(task.start_posture, held, stiffness, q, spec.settle_time,
                                  task.control_period)
            held = hold.u_ffwd[-1]
            self._run_on_robot(run, hold)
            q, qd = self._settled(run)
            waited += 2 * spec.settle_time
        self._check_homed(run, q, qd, waited)

    def _run_on_robot(self, run: _Rollout, reference: Reference) -> None:
        """Run a homing `reference` on the robot (announced, not evaluated) and wait for the
        robot's first state past its end; RuntimeError on a fault or none in time."""
        goal, task = run.goal, run.task
        duration = float(reference.t[-1])
        t0 = self._start_on_robot(trajectory_msg(run.joint_names, reference), TaskInstance(
            task=goal.task, tau=list(goal.tau), num_steps=len(reference.t) - 1,
            control_period=task.control_period, homing=True), task)
        end = t0 + int(round(duration * 1e9))
        deadline = time.monotonic() + LEAD + duration + self.get_parameter(
            'timeout_margin').value
        with self._cv:
            while True:
                if t0 in self._faults:
                    raise RuntimeError(f'homing: {self._faults[t0][1]}')
                if self._states and self._states[-1][0] >= end:
                    return
                if time.monotonic() > deadline:
                    raise RuntimeError(f'homing: no joint state of its end within '
                                       f'{duration:.1f} s + the timeout margin')
                self._cv.wait(timeout=0.01)

    def _settled(self, run: _Rollout) -> tuple[np.ndarray, np.ndarray]:
        """The posture and velocity (means of the newest SETTLE_STATES: the noise averaged)
        once homed, or after another homing.settle_time: a robot settles in its own time."""
        until = time.monotonic() + run.task.homing.settle_time
        while True:
            _, q, qd = self._measured(run.task, SETTLE_STATES)
            if time.monotonic() > until or self._homed(run, q, qd):
                return q, qd
            time.sleep(run.task.control_period)

    def _announce_known_change(self, run: _Rollout) -> None:
        """Tell the evaluator of the goal change the action goal asked for, before the episode
        (stamped zero: the next episode)."""
        goal = run.goal
        self._announce(GoalUpdate(time_from_start=goal.new_goal_time, goal=list(goal.new_goal),
                                  last_reference=run.reference.q[-1].tolist()))

    def _set_gains(self, run: _Rollout) -> None:
        """The controller's gains := the task's (``controller.kp/kd``, and its
        ``safety.max_tracking_error``) when they differ from
        the gains it runs (at first: those of the task it was started with): two tasks of
        different gains share one running controller. Gains set by hand (``pd_controller``
        parameters) stay as long as the rollouts' tasks have the same gains. A task of
        another robot is refused by the simulator first (a probe), with its reason."""
        task = run.task
        wanted = (tuple(task.controller.kp.tolist()), tuple(task.controller.kd.tolist()),
                  task.safety.max_tracking_error)
        if self._gains is None:
            self._gains = self._controller_task_gains()
        if wanted == self._gains:
            return
        if not self.external:
            self._probe(run.goal)      # the simulator runs this task's robot, or says why not
        response = ask(lambda: self.controller_parameters.set_parameters([
            Parameter('kp', value=list(wanted[0])), Parameter('kd', value=list(wanted[1])),
            Parameter('max_tracking_error', value=float(wanted[2]))]),
            PARAMETER_TIMEOUT, 'pd_controller/set_parameters')
        refused = [r.reason for r in response.results if not r.successful]
        if refused:
            raise ValueError(f'the controller refused the gains of task {task.name!r}: '
                             f'{refused[0]}')
        self._gains = wanted

    def _controller_task_gains(self) -> tuple:
        """(kp, kd, max_tracking_error) of the task the controller was started with (its
        ``task`` parameter)."""
        if not self.controller_parameters.wait_for_services(timeout_sec=5.0):
            raise RuntimeError("the controller's parameter service is not available")
        response = ask(lambda: self.controller_parameters.get_parameters(['task']),
                       PARAMETER_TIMEOUT, 'pd_controller/get_parameters')
        start = load_task(response.values[0].string_value)
        return (tuple(start.controller.kp.tolist()), tuple(start.controller.kd.tolist()),
                start.safety.max_tracking_error)

    def _home(self, run: _Rollout) -> None:
        """Drive the arm from where it is to the task's start posture (a ``drive`` reset):
        the simulator says the current state (reset mode ``probe``), the controller gets the
        homing quintic (`psl_controller.homing`), a homing episode runs it (announced, not
        evaluated), and the arm must then be within the homing tolerance of the start
        posture, at rest; RuntimeError naming the joint that is not."""
        goal, task, spec = run.goal, run.task, run.task.homing
        probe = self._probe(goal)
        q0, qd0 = np.asarray(probe.position), np.asarray(probe.velocity)
        start = task.start_posture
        if np.abs(q0 - start).max() <= spec.tolerance and np.abs(qd0).max() <= spec.tolerance:
            return                                  # there already
        reference = self._homing(run, q0, qd0)
        self.pub_trajectory.publish(trajectory_msg(run.joint_names, reference))
        self._acked(self.pub_trajectory, 'the controller did not receive the homing trajectory')
        response = self._call(self.reset_client, ResetTask.Request(
            task=goal.task, tau=goal.tau, mode='drive', duration=float(reference.t[-1]),
            homing=True))
        if not response.success:
            raise ValueError(f'homing: {response.message}')
        deadline = time.monotonic() + reference.t[-1] + self.get_parameter(
            'timeout_margin').value
        while True:                                 # the episode runs; then say the state
            probe = self._probe(goal, quiet=True)
            if probe.success or time.monotonic() > deadline:
                break
            time.sleep(0.01)
        if not probe.success:
            raise RuntimeError(f'homing: the homing episode did not end within '
                               f'{reference.t[-1]:.1f} s + the timeout margin: {probe.message}')
        self._check_homed(run, np.asarray(probe.position), np.asarray(probe.velocity),
                          float(reference.t[-1]))

    def _homing(self, run: _Rollout, q0: np.ndarray, qd0: np.ndarray) -> Reference:
        """The homing quintic from q0, qd0 to the start posture with the model's inverse
        dynamics as its feed-forward (`psl_controller.homing`); ValueError unless it passes
        the safety check."""
        task = run.task
        reference = homing_reference(q0, qd0, task.start_posture, task.homing,
                                     task.control_period, self._inverse_dynamics(run))
        verdict = self._safety(task).check(np.asarray(run.goal.tau), reference.q,
                                           reference.qd)
        if not verdict.safe:
            raise ValueError(f'homing refused by the safety check: {verdict.reason}')
        return reference

    @staticmethod
    def _homed(run: _Rollout, q: np.ndarray, qd: np.ndarray) -> bool:
        """Within homing.tolerance of the start posture, at rest."""
        return bool(np.maximum(np.abs(q - run.task.start_posture), np.abs(qd)).max()
                    <= run.task.homing.tolerance)

    def _inverse_dynamics(self, run: _Rollout):
        """The model's inverse dynamics with the rollout's instance applied, (q, qd, qdd) ->
        torque: the homing's feed-forward."""
        tau = run.task.validate_tau(np.asarray(run.goal.tau))
        arm = self._safety(run.task).arm
        return lambda q, qd, qdd: arm.inverse_dynamics(tau, q, qd, qdd)

    def _check_homed(self, run: _Rollout, q: np.ndarray, qd: np.ndarray,
                     duration: float) -> None:
        """RuntimeError naming the joint unless q is within homing.tolerance of the start
        posture, at rest."""
        start, spec = run.task.start_posture, run.task.homing
        error = np.maximum(np.abs(q - start), np.abs(qd))
        if error.max() > spec.tolerance:
            j = int(np.argmax(error))
            raise RuntimeError(
                f'homing did not settle: joint {run.joint_names[j]!r} is at {q[j]:.4g} rad '
                f'({qd[j]:.3g} rad/s), start posture {start[j]:.4g}, after '
                f'{duration:.2f} s (tolerance {spec.tolerance:g}): raise the '
                'controller gains or homing.settle_time, or relax homing.tolerance')

    def _probe(self, goal, quiet: bool = False) -> ResetTask.Response:
        """The simulator's current state (reset mode ``probe``: no episode starts)."""
        response = self._call(self.reset_client,
                              ResetTask.Request(task=goal.task, tau=goal.tau, mode='probe'))
        if not response.success and not quiet:
            raise ValueError(response.message)
        return response

    def _await_evaluation(self, goal_handle, task: TaskDefinition,
                          response: ResetTask.Response) -> tuple[RolloutEvaluation, str]:
        """The episode's evaluation and '', or for an episode the controller aborted the
        penalty (`psl_task.safety_check`: penalty - violation, not fulfilled) and its reason;
        RuntimeError for any other fault, a cancel or no evaluation in time."""
        t0 = to_ns(response.stamp)
        timeout = response.num_steps * task.control_period + self.get_parameter(
            'timeout_margin').value
        deadline = time.monotonic() + timeout
        feedback, last = ExecuteRollout.Feedback(), -1.0
        with self._cv:
            while t0 not in self._evaluations:
                if goal_handle.is_cancel_requested:
                    raise RuntimeError('rollout canceled')
                # a state loss fails at once; an aborted episode runs to its end first (the
                # simulator takes no reset before), its evaluation then dropped
                if t0 in self._faults and self._faults[t0][0] != 'tracking abort':
                    raise RuntimeError(self._faults[t0][1])
                if time.monotonic() > deadline:
                    if t0 in self._faults:
                        raise RuntimeError(self._faults[t0][1])
                    done = self._progress.get(t0)
                    raise RuntimeError(
                        f'no rollout_evaluation within {timeout:.1f} s; the simulator reported '
                        + ('no progress (is the controller running?)' if done is None else
                           f'{100 * done:.0f} % of the episode (is the reward_evaluator '
                           'running?)'))
                self._cv.wait(timeout=0.05)
                feedback.progress = float(self._progress.get(t0, 0.0))
                if feedback.progress != last:
                    goal_handle.publish_feedback(feedback)
                    last = feedback.progress
            evaluation = self._evaluations.pop(t0)
            fault = self._faults.get(t0)
            self._evaluations.clear()
            self._faults.clear()
            self._progress.clear()
            self._reports.clear()
        if fault is None:
            return evaluation, ''
        kind, reason, violation = fault
        if kind != 'tracking abort':
            raise RuntimeError(reason)
        aborted = penalty_evaluation(evaluation.task, evaluation.tau, task, 'tracking_abort',
                                     Verdict(False, reason, violation))
        aborted.stamp = evaluation.stamp
        return aborted, reason

    # -- live goal changes ---------------------------------------------------------------
    def on_goal_update(self, msg: GoalUpdate) -> None:
        with self._live_lock:
            run = self._running
            if run is None:
                self.get_logger().warning('goal update ignored: no rollout runs')
            elif run.t0 is None:
                run.pending = msg               # applied once the episode has started
            else:
                self._change_live(run, msg)

    def _change_live(self, run: _Rollout, msg: GoalUpdate) -> None:
        """Apply a live goal update to the running episode (under _live_lock), or note why
        not in the rollout's result message."""
        try:
            self._try_change_live(run, msg)
        except RuntimeError as exc:     # a node of the loop did not take its message
            run.notes.append(f'goal update failed: {exc}')
            self.get_logger().error(run.notes[-1])

    def _try_change_live(self, run: _Rollout, msg: GoalUpdate) -> None:
        def ignore(reason: str) -> None:
            run.notes.append(f'goal update ignored: {reason}')
            self.get_logger().warning(run.notes[-1])
        stamp = to_ns(msg.stamp)
        if stamp not in (0, run.t0):
            return ignore(f'it names the episode at {stamp} ns, the one that runs started at '
                          f'{run.t0} ns')
        if run.change_time is not None:
            return ignore(f'the goal changed already at {run.change_time:g} s (one change '
                          'per rollout)')
        dt = run.task.control_period
        end = run.num_steps * dt
        if not 0.0 <= msg.time_from_start <= end:        # NaN and inf too
            return ignore(f'time_from_start {msg.time_from_start:g} s is outside the episode '
                          f'[0, {end:g}] s')
        wanted = math.ceil(msg.time_from_start / dt - 1e-9)
        # the goal itself first, at the time asked for: a goal the safety check refuses is
        # refused for that reason, whatever the loop's progress
        try:
            asked = splice(run.reference, run.policy.reference_with_new_goal(
                np.asarray(run.goal.theta), np.asarray(run.goal.tau), wanted * dt,
                np.asarray(msg.goal)), wanted)
        except ValueError as exc:
            return ignore(str(exc))
        verdict = self._safety(run.task).check(np.asarray(run.goal.tau), asked.q, asked.qd)
        if not verdict.safe:
            return ignore(f'refused by the safety check: {verdict.reason}')
        cost = LOAD_FACTOR * run.prepare_cost       # [s] to compute, build and publish it
        announced = False

        def give_up(reason: str) -> None:
            if announced:          # the evaluator keeps the episode's goal
                self._withdraw(GoalUpdate(stamp=time_msg(run.t0)))
            ignore(reason)
        for _ in range(LIVE_ATTEMPTS):
            started = time.monotonic()
            k = max(wanted, self._step_bound(run) + self._steps_in(run, cost))
            if k >= run.num_steps:
                return give_up(f'the episode ends at {run.num_steps * dt:g} s, before the goal '
                               f'could change (at {k * dt:g} s at the earliest)')
            try:
                new = run.policy.reference_with_new_goal(
                    np.asarray(run.goal.theta), np.asarray(run.goal.tau), k * dt,
                    np.asarray(msg.goal))
            except ValueError as exc:
                return give_up(str(exc))
            reference = splice(run.reference, new, k)
            # the check every reference that reaches the controller passes (as the rollout's)
            verdict = self._safety(run.task).check(np.asarray(run.goal.tau), reference.q,
                                                   reference.qd)
            if not verdict.safe:
                return give_up(f'refused by the safety check: {verdict.reason}')
            trajectory = trajectory_msg(run.joint_names, reference)
            trajectory.header.stamp = time_msg(run.t0)     # a replacement for this episode
            # the evaluator first: the episode cannot end before the controller has it
            self._announce(GoalUpdate(stamp=time_msg(run.t0), time_from_start=k * dt,
                                      goal=list(msg.goal),
                                      last_reference=reference.q[-1].tolist()))
            announced = True
            if self._step_bound(run) + self._steps_in(run, LOAD_FACTOR * run.publish_cost) < k:
                break                                   # still ahead of the loop: send it
            cost = LOAD_FACTOR * (time.monotonic() - started)
        else:
            return give_up('the episode ran ahead of every switch time tried')
        self.pub_trajectory.publish(trajectory)
        run.reference, run.change_time = reference, k * dt
        run.notes.append(f'goal changed at {k * dt:g} s (live)')
        self._acked(self.pub_trajectory, 'the controller did not receive the changed trajectory')

    def _step_bound(self, run: _Rollout) -> int:
        """An upper bound of the step the episode has reached: the last progress report's,
        or 0 at the reset, plus RATE_MARGIN times the measured rate over the time since. A
        live change can arrive before the simulator's report of the episode's start (another
        topic, another thread): it waits for that report up to REPORT_WAIT."""
        if not self.external:   # the simulator reports the episode's start with its rate
            with self._cv:      # (a realtime loop's 500 steps/s, not DEFAULT_RATE's 5000)
                self._cv.wait_for(lambda: run.t0 in self._reports, timeout=REPORT_WAIT)
        report = self._reports.get(run.t0)
        if report is None:
            done, since = 0, run.reset_sent
        else:
            done, _, since = report
        return done + math.ceil(self._rate(run) * (time.monotonic() - since))

    def _steps_in(self, run: _Rollout, seconds: float) -> int:
        """The steps the loop may make in `seconds` of wall time (at least LEAD_STEPS)."""
        return LEAD_STEPS + math.ceil(self._rate(run) * seconds)

    def _rate(self, run: _Rollout) -> float:
        if self.external:               # a robot runs on the wall clock
            return RATE_MARGIN / run.task.control_period
        report = self._reports.get(run.t0)
        rate = report[1] if report is not None and report[1] > 0 else self._last_rate
        return RATE_MARGIN * rate

    # -- plumbing ------------------------------------------------------------------------
    def _wait_for_subscriber(self, publisher, who: str) -> None:
        deadline = time.monotonic() + ACK_TIMEOUT
        while publisher.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                raise RuntimeError(f'no {who} subscribes to {publisher.topic_name}')
            time.sleep(0.01)

    def _acked(self, publisher, failure: str) -> None:
        if not publisher.wait_for_all_acked(rclpy.duration.Duration(seconds=ACK_TIMEOUT)):
            raise RuntimeError(failure)

    def _announce(self, change: GoalUpdate) -> None:
        """Tell the reward evaluator of a goal change and have its answer (RuntimeError
        otherwise)."""
        client = self.goal_change_client
        if not client.wait_for_service(timeout_sec=ACK_TIMEOUT):
            raise RuntimeError(f'the reward_evaluator service {client.srv_name} is not '
                               'available')
        response = self._call(client, GoalChange.Request(change=change))
        if not response.success:
            raise RuntimeError(f'the reward_evaluator refused the goal change: '
                               f'{response.message}')

    def _withdraw(self, change: GoalUpdate) -> None:
        """Withdraw an announced goal change (`change` without a goal); a failure is only
        logged: the evaluator keeps a change the controller never got only if the
        controller's last reference happens to be the announced one."""
        try:
            self._announce(change)
        except RuntimeError as exc:
            self.get_logger().error(f'could not withdraw a goal change: {exc}')

    def _call(self, client, request):
        try:
            return wait_for(client.call_async(request), 10.0, client.srv_name)
        except TimeoutError as exc:
            raise RuntimeError(str(exc)) from exc       # a failed rollout, with the reason


def main(args=None):
    run_node(DMPExecutor, args, threads=4)    # its action waits on other callbacks


if __name__ == '__main__':
    main()
