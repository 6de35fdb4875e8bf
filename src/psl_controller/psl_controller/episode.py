"""One rollout's episodes on any robot, written once: homing, the primitive, a live goal change.

psl owns the episode (DESIGN.md 3b). Everything it does to the robot goes through a `Robot`:
the measured posture, a clock that says when a goal may start (and, for psl's simulator,
advances), ``control_msgs/FollowJointTrajectory`` goals to the robot's controller and their
answers, and the announcement of the task instance. psl's lockstep simulator, psl's standard
robot and a robot's own JointTrajectoryController differ only in that `Robot`
(`psl_controller.robot_link`: the controller's address and the clock); this module imports no
ROS.

An episode, from the goal the executor got:

1. the beginning (`Episode.begin`): ``teleport`` (psl's simulator only: the arm is put at the
   start posture when the primitive starts) or ``drive``: from the measured posture (the mean
   of the newest `SETTLE_STATES` states on a noisy robot) a homing quintic to the start
   posture (`psl_controller.homing`, its feed-forward the model's inverse dynamics with the
   instance applied, clipped into the torque limits: `Episode._homing_goal`) as one goal,
   announced as a homing episode. An arm found outside its joint
   ranges (a foreign goal or a push left it there) is brought back inside: the safety check
   passes a homing reference that only moves such a joint toward its range
   (`psl_task.safety_check`, with the measured posture as its start), the episode says so in
   one line, and the goal's points start at the first one inside every range
   (`psl_task.safety_check.inside_from`): the segment from the measured state to it is the
   controller's own. Then the arm must come within
   ``homing.tolerance`` of the start posture, at rest, within ``homing.settle_time`` more; an
   arm at rest off the start (the robot is not its model) is held again with a corrected torque
   (`psl_controller.homing.corrected_hold`), up to `HOLD_CORRECTIONS` times; one still moving
   off the start is first given up to `REST_WAITS` more ``settle_time`` to come to rest;
2. the primitive (`Episode.run`): its task instance announced, the reference as one goal
   stamped to start at the clock's next start (`Robot.start_time`), with the task's
   ``safety.max_tracking_error`` as the path tolerance (the controller aborts beyond it:
   ``PATH_TOLERANCE_VIOLATED``); a goal that came after its start (``OLD_HEADER_TIMESTAMP``,
   or accepted when the robot's newest state had passed its start) is sent again, later;
3. the answer: the goal's result, and the reference it ran (with a goal change, if one took).
   A goal of the episode that a goal not sent by this episode preempted (the controller's
   ``INVALID_GOAL`` with JTC's words, `PREEMPTION_WORDS`) raises `Preempted`: no outcome, and
   not the candidate's doing (the executor says so; the session runs the rollout again).

Every reference that reaches the controller has passed the task's safety check, and every goal
is checked against the model's limits as the controllers psl serves check it before it is sent
(`psl_controller.goal_limits.GoalLimits.check_reference`, their default bounds): a controller
that rejects it has narrower limits than the model's (a node parameter, a robot's own
JointTrajectoryController), and the rollout fails saying so (`Robot.send`). A live goal
change (`Episode.change_goal`) replaces the running goal with one of the same start whose
reference is the old one up to a switch step and the new goal's from there; the controller takes
it only if it has not served that step yet (psl's controller refuses a replacement that would
jump; the switch is chosen ahead of the episode's progress, bounded from the controller's
feedback and the loop's rate).
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time
from typing import Callable, Protocol

import numpy as np

from psl_controller.goal_limits import GoalLimits
from psl_controller.homing import corrected_hold, hold_stiffness, homing_reference
from psl_controller.policy import Reference, TaskPolicy
from psl_controller.trajectory_controller import (GOAL_TOLERANCE_VIOLATED, INVALID_GOAL,
                                                  OLD_HEADER_TIMESTAMP,
                                                  PATH_TOLERANCE_VIOLATED, PREEMPTED,
                                                  SUCCESSFUL, GoalRefused)
from psl_task.arm_model import joint_names_of
from psl_task.safety_check import SafetyCheck, inside_from
from psl_task.task import TaskDefinition

SETTLE_STATES = 25      # the newest states averaged for the homing check on a noisy robot
HOLD_CORRECTIONS = 3    # holds with a corrected torque when homing comes to rest off the start
REST_WAITS = 5          # settle times an arm still moving off the start is given to come to rest
START_ATTEMPTS = 3      # goals sent, each later, before a late start fails the rollout
LEAD_STEPS = 5          # control periods of lead at the least (a live change)
RATE_MARGIN = 1.5       # the loop may run this many times faster than last measured
LOAD_FACTOR = 3.0       # computing and sending a goal during an episode (the loop busy on every
                        # core) may take this many times longer than before it
LIVE_ATTEMPTS = 4       # switch times tried, each later, before a live change gives up


# what a JointTrajectoryController answers a goal another goal preempted, with INVALID_GOAL:
# psl's controller's words, and ros2_controllers JTC's (Jazzy: preempt_active_goal)
PREEMPTION_WORDS = (PREEMPTED, 'Current goal cancelled due to new incoming action.')


class RobotError(RuntimeError):
    """The robot did not do what the episode needs (a rejected goal, lost states, no answer)."""


class Preempted(RobotError):
    """A goal the episode did not send preempted one of its goals (someone else commands the
    controller): nothing the candidate did."""


@dataclasses.dataclass(frozen=True)
class GoalSpec:
    """A FollowJointTrajectory goal: the reference (sampled every control period from its
    start), the start on the robot's clock, the path tolerance (no goal tolerance: the goal
    ends with its last point), and whom to tell how far it got (the controller's feedback)."""

    reference: Reference
    start_ns: int
    path_tolerance: float = 0.0         # rad, every joint; 0 = none
    progress: Callable[[float], None] | None = None     # told the fraction done (feedback)


@dataclasses.dataclass(frozen=True)
class GoalResult:
    """A goal's answer: control_msgs' error code and words for people."""

    error_code: int
    error_string: str


@dataclasses.dataclass(frozen=True)
class Instance:
    """An episode as the graph announces it (psl_msgs/TaskInstance)."""

    stamp_ns: int
    task: str
    tau: np.ndarray
    num_steps: int
    control_period: float
    homing: bool = False


class Robot(Protocol):
    """What an episode needs of a robot (`psl_controller.robot_link.RobotLink` over ROS)."""

    can_teleport: bool          # psl's simulator: the arm can be put at the start posture

    def measure(self, count: int) -> tuple[int, np.ndarray, np.ndarray]:
        """(stamp, q, qd): the task's joints, the mean of the newest `count` states."""

    def start_time(self, attempt: int = 0) -> int:
        """The robot-clock stamp a goal sent now can start at; a later one for a goal sent
        again (`attempt` > 0: the one before came late)."""

    def send(self, goal: GoalSpec) -> object:
        """Send a goal; its handle once accepted (RobotError if rejected: the controller's
        limits may be narrower than the model's, see its log)."""

    def taken(self, handle: object, before_ns: int) -> bool:
        """Whether the controller took the goal before the robot's clock passed `before_ns`
        (False: it came late; psl's controller then ends it with OLD_HEADER_TIMESTAMP and
        goes on with what it runs, a robot's JTC would jump into it: cancel it)."""

    def begin(self, start_ns: int, num_steps: int, mode: str) -> int:
        """Let the episode's time run from `start_ns` for `num_steps` periods (the simulator:
        its reset of that length, ``teleport`` or ``drive``; a robot: its clock runs anyway):
        the episode's first state's stamp."""

    def finish(self, handle: object, end_ns: int, timeout: float,
               cancelled: Callable[[], bool]) -> GoalResult:
        """Wait for the goal's result and the robot's state at `end_ns` (RobotError when the
        states stop, neither comes within `timeout` s, or `cancelled()`: the goal is then
        cancelled, the controller holds)."""

    def wait(self, seconds: float, done: Callable[[], bool]) -> None:
        """Let `seconds` of the robot's time pass while the arm holds, or until `done()`."""

    def cancel(self, handle: object) -> None:
        """Cancel a goal (the controller holds the position)."""

    def progress(self, handle: object) -> tuple[int, float, float] | None:
        """(served time from the goal's start [ns], monotonic time it was reported, the loop's
        rate [robot s per wall s]) from the controller's newest feedback, or None."""

    def announce(self, instance: Instance) -> None:
        """Announce an episode (task_instance)."""


@dataclasses.dataclass
class Outcome:
    """What an episode did: its start and length, the reference that ran, the goal's answer,
    the time a goal change took effect (None: none) and its goal, notes for the result
    message."""

    start_ns: int
    num_steps: int
    reference: Reference
    result: GoalResult
    change_time: float | None = None
    new_goal: np.ndarray | None = None      # the DMP's goal from change_time on
    notes: list[str] = dataclasses.field(default_factory=list)

    @property
    def aborted(self) -> bool:
        """The controller stopped the episode: the tracking error passed the bound."""
        return self.result.error_code == PATH_TOLERANCE_VIOLATED


class Episode:
    """The episodes of one rollout: (task, tau) on `robot` (module docstring).

    Args:
        robot: the robot.
        task, tau: the task instance.
        policy: the task's policy (a live goal change recomputes its reference).
        safety: the task's safety check (every reference sent passes it).
        inverse_dynamics: the model's (q, qd, qdd) -> torque with the instance applied (the
            homing's feed-forward).
        kp: the controller's proportional gains (the corrected hold's stiffness).
        task_id: the task's name as the graph announces it.
        timeout_margin: seconds to wait beyond a goal's length.
        log: where notes for people go.
        cancelled: asked while a goal runs; True cancels it (RobotError 'rollout canceled').
    """

    def __init__(self, robot: Robot, task: TaskDefinition, tau: np.ndarray,
                 policy: TaskPolicy, safety: SafetyCheck,
                 inverse_dynamics: Callable, kp: np.ndarray, task_id: str,
                 timeout_margin: float = 10.0, log: Callable[[str], None] = print,
                 cancelled: Callable[[], bool] = lambda: False):
        self.robot, self.task, self.tau = robot, task, np.asarray(tau, dtype=float)
        self.policy, self.safety = policy, safety
        self.limits = GoalLimits.of(safety.arm)     # what a controller psl serves takes
        self.inverse_dynamics, self.kp = inverse_dynamics, np.asarray(kp, dtype=float)
        self.task_id, self.margin, self.log = task_id, timeout_margin, log
        self.cancelled = cancelled
        self.handle = None              # the primitive's goal while it runs
        self.outcome: Outcome | None = None
        self.send_cost = 0.0            # [s] wall time to send the primitive's goal
        self._change = threading.Condition()    # guards handle, outcome and _changing
        self._changing = False          # a live goal change is being sent
        self._progress: Callable[[float], None] | None = None
        self._superseded: set = set()   # goals this episode replaced itself (a live change)
        self.notes: list[str] = []      # for people: what the beginning did (homing back)

    # -- the beginning --------------------------------------------------------------------
    def begin(self, mode: str) -> None:
        """Bring the arm to the start posture at rest (``drive``); ``teleport`` is left to
        the simulator when the primitive starts (`run`)."""
        if mode == 'teleport':
            if not self.robot.can_teleport:
                raise ValueError('teleport is for psl\'s simulator: a robot is driven to the '
                                 'start posture (reset drive)')
            return
        task, spec = self.task, self.task.homing
        _, q0, qd0 = self.robot.measure(SETTLE_STATES)
        if self._homed(q0, qd0):
            return
        safety = self.safety
        reference = self._homing_goal(homing_reference(
            q0, qd0, task.start_posture, spec, task.control_period, self.inverse_dynamics,
            safety.low, safety.high), start=q0)
        outside = safety.outside(q0)
        if outside.any():
            self._say(f'the arm is outside its joint ranges ({self._where(q0, outside)}): '
                      'homing brings it back inside')
        self._hold(reference, inside_from(reference.q, safety.low, safety.high))
        q, qd = self._settled()
        held = reference.u_ffwd[-1]
        waited = float(reference.t[-1]) + spec.settle_time
        stiffness = None
        for _ in range(HOLD_CORRECTIONS):
            if self._homed(q, qd):
                break
            if np.abs(qd).max() > spec.tolerance:     # still moving: it comes to rest in its
                q, qd = self._at_rest()                 # own time (a lightly damped payload)
                waited += REST_WAITS * spec.settle_time
                if self._homed(q, qd) or np.abs(qd).max() > spec.tolerance:
                    break                             # there, or it does not come to rest
            if stiffness is None:
                stiffness = hold_stiffness(self.kp, self.inverse_dynamics, task.start_posture)
            hold = self._homing_goal(corrected_hold(task.start_posture, held, stiffness, q,
                                                    spec.settle_time, task.control_period))
            held = hold.u_ffwd[-1]
            self._hold(hold)
            q, qd = self._settled()
            waited += 2 * spec.settle_time
        start, error = task.start_posture, np.maximum(np.abs(q - task.start_posture),
                                                      np.abs(qd))
        if error.max() > spec.tolerance:
            j = int(np.argmax(error))
            raise RobotError(
                f'homing did not settle: joint {joint_names_of(task)[j]!r} is at '
                f'{q[j]:.4g} rad ({qd[j]:.3g} rad/s), start posture {start[j]:.4g}, after '
                f'{waited:.2f} s (tolerance {spec.tolerance:g}): raise the controller gains '
                'or homing.settle_time, or relax homing.tolerance')

    def _homing_goal(self, reference: Reference, start: np.ndarray | None = None
                     ) -> Reference:
        """A homing reference as it is sent: its feed-forward clipped into the torque limits
        (`psl_controller.homing`: the law clips the total torque anyway, and a controller
        rejects an effort beyond them), checked by the safety check (`start`: the measured
        posture it leaves from). ValueError if the check refuses it."""
        limits = self.limits
        reference = Reference(reference.t, reference.q, reference.qd,
                              np.clip(reference.u_ffwd, limits.effort_low, limits.effort_high))
        verdict = self.safety.check(self.tau, reference.q, reference.qd, reference.u_ffwd,
                                    start=start)
        if not verdict.safe:
            raise ValueError(f'homing refused by the safety check: {verdict.reason}')
        return reference

    def _send(self, goal: GoalSpec) -> object:
        """Send a goal that keeps the model's limits as a controller psl serves checks them
        (module docstring); RobotError, nothing sent, for one that does not."""
        try:
            self.limits.check_reference(goal.reference)
        except GoalRefused as exc:
            raise RobotError(f"psl's goal breaks the model's limits, not sent: {exc}") from None
        return self.robot.send(goal)

    def _say(self, line: str) -> None:
        """A note for people: logged, and kept for the rollout's result."""
        self.log(line)
        self.notes.append(line)

    def _where(self, q: np.ndarray, outside: np.ndarray) -> str:
        """Which joints of q are outside their ranges, and by how much (`SafetyCheck.outside`)."""
        names, low, high = joint_names_of(self.task), self.safety.low, self.safety.high
        return ', '.join(
            f'joint {names[j]!r} at {q[j]:.4g} rad, '
            + (f'above its limit {high[j]:.4g}' if q[j] > high[j] else
               f'below its limit {low[j]:.4g}') + f' by {outside[j]:.3g}'
            for j in np.flatnonzero(outside))

    def _hold(self, reference: Reference, first: int = 0) -> None:
        """Run a homing reference (announced, not evaluated) to its end; the goal's points
        from index `first` on (those before are the controller's segment from the measured
        state: module docstring, 1)."""
        task = self.task
        num_steps = len(reference.t) - 1
        sent = reference if first == 0 else Reference(
            *(a[first:] for a in (reference.t, reference.q, reference.qd, reference.u_ffwd)))
        handle, start = self._start(sent, num_steps, 'drive', homing=True,
                                    path=float('inf'))
        result = self.robot.finish(handle, start + num_steps * task.control_period_ns,
                                   float(reference.t[-1]) + self.margin, self.cancelled)
        if self._preempted(handle, result):
            raise Preempted(f'the homing goal was preempted by a goal that is not psl\'s '
                            f'(the controller: {result.error_string!r})')
        if result.error_code not in (SUCCESSFUL, GOAL_TOLERANCE_VIOLATED):
            raise RobotError(f'homing: {result.error_string}')

    def _preempted(self, handle: object, result: GoalResult) -> bool:
        """Whether a goal this episode did not send preempted `handle` (module docstring, 3)."""
        return (result.error_code == INVALID_GOAL and result.error_string in PREEMPTION_WORDS
                and handle not in self._superseded)

    def _settled(self) -> tuple[np.ndarray, np.ndarray]:
        """The posture and velocity (means of the newest SETTLE_STATES: the noise averaged)
        once homed, or after another homing.settle_time: a robot settles in its own time."""
        found = []

        def homed() -> bool:
            _, q, qd = self.robot.measure(SETTLE_STATES)
            found[:] = [q, qd]
            return self._homed(q, qd)
        if not homed():
            self.robot.wait(self.task.homing.settle_time, homed)
            homed()
        return found[0], found[1]

    def _at_rest(self) -> tuple[np.ndarray, np.ndarray]:
        """The posture and velocity (means of the newest SETTLE_STATES) once the arm is at
        rest (within homing.tolerance of no velocity), or after REST_WAITS more
        homing.settle_time."""
        found = []

        def resting() -> bool:
            _, q, qd = self.robot.measure(SETTLE_STATES)
            found[:] = [q, qd]
            return bool(np.abs(qd).max() <= self.task.homing.tolerance)
        if not resting():
            self.robot.wait(REST_WAITS * self.task.homing.settle_time, resting)
            resting()
        return found[0], found[1]

    def _homed(self, q: np.ndarray, qd: np.ndarray) -> bool:
        """Within homing.tolerance of the start posture, at rest."""
        return bool(np.maximum(np.abs(q - self.task.start_posture), np.abs(qd)).max()
                    <= self.task.homing.tolerance)

    # -- the primitive --------------------------------------------------------------------
    def run(self, reference: Reference, mode: str, started: Callable[[], None] = lambda: None,
            change: tuple[float, np.ndarray] | None = None,
            progress: Callable[[float], None] | None = None) -> Outcome:
        """The primitive's episode of `reference` (its first point at the episode's start):
        `started` is called once it runs (a live goal change may come then); `change`: the
        goal change (time, goal) `reference` holds already, if any; `progress` is told the
        fraction of the episode done as the controller reports it."""
        task = self.task
        num_steps = task.num_steps_of(self.tau)
        if len(reference.t) != num_steps + 1:
            raise ValueError(f'the reference has {len(reference.t)} points, the episode '
                             f'{num_steps + 1}')
        outcome = Outcome(0, num_steps, reference, GoalResult(SUCCESSFUL, ''),
                          *(change if change is not None else (None, None)))
        handle, start = self._start(reference, num_steps, mode, homing=False,
                                    path=task.safety.max_tracking_error, progress=progress)
        outcome.start_ns = start
        with self._change:
            self.outcome, self.handle, self._progress = outcome, handle, progress
        started()
        end = start + num_steps * task.control_period_ns
        timeout = num_steps * task.control_period + self.margin
        while True:
            result = self.robot.finish(handle, end, timeout, self.cancelled)
            with self._change:          # a goal change replaced the goal meanwhile: its turn
                self._change.wait_for(lambda: not self._changing, timeout=timeout)
                if self.handle is handle:
                    self.handle = None
                    break
                handle = self.handle
        if self._preempted(handle, result):
            raise Preempted(f'the episode\'s goal was preempted by a goal that is not psl\'s '
                            f'(the controller: {result.error_string!r})')
        if result.error_code not in (SUCCESSFUL, PATH_TOLERANCE_VIOLATED,
                                     GOAL_TOLERANCE_VIOLATED):
            raise RobotError(result.error_string or f'the controller ended the episode '
                             f'with error code {result.error_code}')
        outcome.result = result
        return outcome

    def _start(self, reference: Reference, num_steps: int, mode: str, homing: bool,
               path: float, progress: Callable[[float], None] | None = None
               ) -> tuple[object, int]:
        """Announce the episode, send its goal stamped at the clock's next start and let the
        time run: (goal handle, start stamp). A goal that came late is sent again, later."""
        robot, task = self.robot, self.task
        mode = 'drive' if homing else mode
        for attempt in range(START_ATTEMPTS):
            start = robot.start_time(attempt)
            robot.announce(Instance(start, self.task_id, self.tau, num_steps,
                                    task.control_period, homing))
            sending = time.monotonic()
            handle = self._send(GoalSpec(reference, start, _bound(path), progress))
            self.send_cost = time.monotonic() - sending
            if robot.taken(handle, start):
                began = robot.begin(start, num_steps, mode)
                if began != start:
                    raise RobotError(f'the episode began at {began} ns, its goal at {start} ns')
                return handle, start
            robot.cancel(handle)
            self.log(f'the goal reached the controller after its start ({attempt + 1} of '
                     f'{START_ATTEMPTS}): sending it again, later')
        raise RobotError(f'the goal did not reach the controller before its start, '
                         f'{START_ATTEMPTS} times (OLD_HEADER_TIMESTAMP)')

    # -- a live goal change ---------------------------------------------------------------
    def change_goal(self, theta: np.ndarray, goal: np.ndarray, time_from_start: float) -> str:
        """Move the running primitive's goal to `goal` from `time_from_start` on (at the
        earliest step the episode has not reached yet); what happened, for the result
        message. ValueError for a goal the policy or the safety check refuses, or when no
        primitive runs."""
        with self._change:
            if self.handle is None or self._changing:
                raise ValueError('no episode runs' if self.handle is None else
                                 'a goal change is under way')
            self._changing = True
        try:
            return self._change_goal(theta, goal, time_from_start)
        finally:
            with self._change:
                self._changing = False
                self._change.notify_all()

    def _change_goal(self, theta: np.ndarray, goal: np.ndarray, time_from_start: float) -> str:
        outcome, task = self.outcome, self.task
        if outcome.change_time is not None:
            raise ValueError(f'the goal changed already at {outcome.change_time:g} s (one '
                             'change per rollout)')
        dt, steps = task.control_period, outcome.num_steps
        end = steps * dt
        if not 0.0 <= time_from_start <= end:        # NaN and inf too
            raise ValueError(f'time_from_start {time_from_start:g} s is outside the episode '
                             f'[0, {end:g}] s')
        wanted = math.ceil(time_from_start / dt - 1e-9)
        theta, goal = np.asarray(theta, dtype=float), np.asarray(goal, dtype=float)
        # the goal itself first, at the time asked for: a goal the safety check refuses is
        # refused for that reason, whatever the loop's progress
        computing = time.monotonic()
        asked = splice(outcome.reference, self.policy.reference_with_new_goal(
            theta, self.tau, wanted * dt, goal), wanted)
        verdict = self.safety.check(self.tau, asked.q, asked.qd, asked.u_ffwd)
        if not verdict.safe:
            raise ValueError(f'refused by the safety check: {verdict.reason}')
        # [s] to compute, check and send it, the loop busy on every core meanwhile
        cost = LOAD_FACTOR * (time.monotonic() - computing + self.send_cost)
        for _ in range(LIVE_ATTEMPTS):
            started = time.monotonic()
            k = max(wanted, self._step_bound() + self._steps_in(cost) + 1)
            if k >= steps:
                return (f'goal update ignored: the episode ends at {end:g} s, before the goal '
                        f'could change (at {k * dt:g} s at the earliest)')
            reference = splice(outcome.reference, self.policy.reference_with_new_goal(
                theta, self.tau, k * dt, goal), k)
            verdict = self.safety.check(self.tau, reference.q, reference.qd, reference.u_ffwd)
            if not verdict.safe:
                raise ValueError(f'refused by the safety check: {verdict.reason}')
            if self._step_bound() + self._steps_in(LOAD_FACTOR * self.send_cost) >= k:
                cost = LOAD_FACTOR * (time.monotonic() - started)
                continue                                # the loop came too close: later
            replaced = self.handle          # the new goal preempts it: psl's own doing
            self._superseded.add(replaced)
            try:
                handle = self._send(GoalSpec(
                    reference, outcome.start_ns, _bound(task.safety.max_tracking_error),
                    self._progress))
            except RobotError as exc:
                self._superseded.discard(replaced)
                return f'goal update failed: {exc}'
            switch = outcome.start_ns + k * task.control_period_ns
            if not self.robot.taken(handle, switch):
                self.robot.cancel(handle)
                return ('goal update refused by the controller: it came after the switch '
                        'time; the episode kept its goal')
            with self._change:
                self.handle, outcome.reference = handle, reference
                outcome.change_time, outcome.new_goal = k * dt, goal
            return f'goal changed at {k * dt:g} s (live)'
        return 'goal update ignored: the episode ran ahead of every switch time tried'

    def _step_bound(self) -> int:
        """An upper bound of the step the episode has reached: the controller's newest
        feedback (or the start) plus RATE_MARGIN times the loop's rate over the time since."""
        report = self.robot.progress(self.handle)
        dt = self.task.control_period
        if report is None:
            return 0
        served_ns, seen, rate = report
        return max(0, math.ceil(served_ns * 1e-9 / dt
                                + RATE_MARGIN * rate * (time.monotonic() - seen) / dt))

    def _steps_in(self, seconds: float) -> int:
        """The steps the loop may make in `seconds` of wall time (at least LEAD_STEPS)."""
        report = self.robot.progress(self.handle)
        rate = 1.0 if report is None else report[2]
        return LEAD_STEPS + math.ceil(RATE_MARGIN * rate * seconds / self.task.control_period)


def _bound(tolerance: float) -> float:
    """A task's tracking bound as a path tolerance: inf (no bound) is 0 (none)."""
    return float(tolerance) if np.isfinite(tolerance) else 0.0


def splice(old: Reference, new: Reference, k: int) -> Reference:
    """old's points before index k, new's from k on."""
    return Reference(*(np.concatenate([a[:k], b[k:]])
                       for a, b in zip((old.t, old.q, old.qd, old.u_ffwd),
                                       (new.t, new.q, new.qd, new.u_ffwd))))
