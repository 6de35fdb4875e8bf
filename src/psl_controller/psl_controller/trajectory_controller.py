"""A joint trajectory controller with the semantics of ros2_controllers' JointTrajectoryController
(JTC, Jazzy) on the effort interface, without ROS: goals (a trajectory, its start, tolerances),
preemption, cancel, hold, path and goal tolerances, and the chapter's compliant law
``u = Kp (q_ref - q) + Kd (qd_ref - qd) + u_ffwd`` (`psl_controller.pd_law`). psl's
``pd_controller`` node (a robot that takes torques) and psl's standard robot (the law inside the
robot's loop) both run it; `psl_controller.follow_joint_trajectory` serves it as
``control_msgs/action/FollowJointTrajectory``. Imports no ROS.

One `update` per measured state (``t_ns`` on the robot's clock). What it serves:

* a goal stamped zero starts at the next update; a goal stamped later is accepted at once (it
  preempts the active goal, which ends with ``INVALID_GOAL``, "preempted") but until its stamp
  what ran before goes on (a homing's hold keeps its torque; JTC instead moves from the measured
  state to the first point by then);
* a goal whose stamp the states have passed already is **not** run (JTC would jump into its
  middle): it ends at once with ``OLD_HEADER_TIMESTAMP`` and what runs goes on — unless it
  replaces the running trajectory seamlessly (the same stamp, and the same reference at the last
  state served: a goal change from a later point on), which it then does from the next update;
* before a trajectory's first point (a first point later than its start): the segment from the
  state at the first update to that point (`SampledTrajectory.starting_from`), as JTC;
* while the trajectory runs (before its last point): a joint farther than its path tolerance
  from the reference aborts the goal with ``PATH_TOLERANCE_VIOLATED`` and the controller holds
  the measured position (no feed-forward);
* past the last point: within the goal tolerance the goal succeeds and the last point is held
  (its feed-forward too); otherwise, once ``goal_time`` has passed (if not zero), it aborts with
  ``GOAL_TOLERANCE_VIOLATED`` and holds the measured position; with ``goal_time`` zero it waits;
* cancel: the goal ends canceled and the controller holds the measured position;
* `stop` (a lost robot, the node's watchdog): the goal aborts with ``INVALID_GOAL`` and the
  reason; the next state is held where it is;
* with no trajectory yet: the first measured position is held.

Tolerances, as JTC: 0 = not enforced (or: the default), -1 in a goal = erased, a position and a
velocity bound per joint; JTC uses its defaults for a goal with an illegal tolerance, this
controller refuses such a goal (`GoalRefused`). Another deliberate difference: the feed-forward
is the reference's effort at the state's own time (JTC adds the next cycle's), so that psl's
lockstep simulator computes exactly the torque batch mode does.
"""
from __future__ import annotations

import dataclasses
import threading
from typing import Hashable, Mapping

import numpy as np

from psl_controller.pd_law import PDLaw
from psl_controller.trajectory_sampling import SampledTrajectory, TrajectorySample

# control_msgs/action/FollowJointTrajectory Result.error_code (test_follow_joint_trajectory
# checks them against the generated message)
SUCCESSFUL = 0
INVALID_GOAL = -1
INVALID_JOINTS = -2
OLD_HEADER_TIMESTAMP = -3
PATH_TOLERANCE_VIOLATED = -4
GOAL_TOLERANCE_VIOLATED = -5
ERASED = -1.0       # a goal's tolerance that switches a default off
PREEMPTED = 'Current goal preempted by new incoming action.'    # JTC's words


class GoalRefused(ValueError):
    """A goal this controller does not take (JTC rejects it): the reason."""


@dataclasses.dataclass(frozen=True)
class Tolerances:
    """Path and goal tolerances per joint (controller order), 0 = not enforced, and the time
    after the last point within which the goal tolerance must be met (0 = no limit)."""

    path_position: np.ndarray
    path_velocity: np.ndarray
    goal_position: np.ndarray
    goal_velocity: np.ndarray
    goal_time: float = 0.0

    @classmethod
    def none(cls, n: int, goal_velocity: float = 0.0) -> 'Tolerances':
        zeros = np.zeros(n)
        return cls(zeros, zeros, zeros, np.full(n, float(goal_velocity)))

    def resolved(self, joint_names: list[str], path: Mapping[str, tuple[float, float]],
                 goal: Mapping[str, tuple[float, float]], goal_time: float) -> 'Tolerances':
        """These defaults with a goal's tolerances (by joint name: (position, velocity); 0 =
        the default, -1 = erased, another negative value refused) and its goal time (0 =
        the default). GoalRefused for an unknown joint or an illegal value."""
        def resolve(default: float, value: float, what: str) -> float:
            if not np.isfinite(value):
                raise GoalRefused(f'{what} must be finite, got {value}')
            if value > 0.0:
                return float(value)
            if abs(value - ERASED) < np.finfo(np.float32).eps:
                return 0.0
            if value < 0.0:
                raise GoalRefused(f'{what} = {value}: a tolerance is > 0, 0 (the default) or '
                                  '-1 (erased)')
            return float(default)

        arrays = {name: getattr(self, name).copy() for name in (
            'path_position', 'path_velocity', 'goal_position', 'goal_velocity')}
        for kind, given in (('path', path), ('goal', goal)):
            for name, (position, velocity) in given.items():
                if name not in joint_names:
                    raise GoalRefused(f'{kind}_tolerance names joint {name!r}, not one of the '
                                      f"controller's {joint_names}")
                j = joint_names.index(name)
                for field, value in (('position', position), ('velocity', velocity)):
                    array = arrays[f'{kind}_{field}']
                    array[j] = resolve(array[j], value, f'{kind}_tolerance {name} {field}')
        return Tolerances(**arrays, goal_time=resolve(self.goal_time, goal_time,
                                                      'goal_time_tolerance'))


@dataclasses.dataclass(frozen=True)
class Goal:
    """A goal in the controller's joint order: its key (who asked), the trajectory, its start
    on the robot's clock (0: the next update) and its tolerances."""

    key: Hashable
    trajectory: SampledTrajectory
    start_ns: int
    tolerances: Tolerances


@dataclasses.dataclass(frozen=True)
class Result:
    """What became of a goal: its key, control_msgs' error code, words for people, and
    whether it was canceled (a canceled goal's code is SUCCESSFUL, as JTC's)."""

    key: Hashable
    error_code: int
    error_string: str
    canceled: bool = False


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """The last update: the state's time, the active goal (None: none, or a hold), the sample
    time from its start (negative before it), the reference served, the measured state, the
    error and the torque."""

    t_ns: int
    key: Hashable | None
    time_from_start_ns: int
    desired: TrajectorySample
    q: np.ndarray
    qd: np.ndarray
    torque: np.ndarray

    @property
    def error(self) -> tuple[np.ndarray, np.ndarray]:
        return self.desired.positions - self.q, self.desired.velocities - self.qd


@dataclasses.dataclass
class _Running:
    """What is served: a trajectory from its start (a hold is a one-point trajectory)."""

    trajectory: SampledTrajectory
    start_ns: int                       # on the robot's clock
    goal: Goal | None                   # None: a hold (no tolerances, no result)
    started: bool = True                # False until the first update at or past start_ns
    sampled: bool = False               # True after its first update as the running one


def hold_at(q: np.ndarray) -> SampledTrajectory:
    """A one-point trajectory: the position q at rest, no feed-forward."""
    q = np.asarray(q, dtype=float)
    return SampledTrajectory(np.zeros(1, dtype=np.int64), q[None], np.zeros((1, q.size)))


class TrajectoryController:
    """See the module docstring. Thread-safe: goals, cancels and `stop` come from other
    threads than `update`."""

    def __init__(self, joint_names: list[str], law: PDLaw, defaults: Tolerances | None = None):
        if law.n_joints != len(joint_names):
            raise ValueError(f'the law has {law.n_joints} joints, the controller '
                             f'{len(joint_names)}')
        self.joint_names = list(joint_names)
        self.law = law                          # replaced whole (gains set while it runs)
        self.defaults = defaults if defaults is not None else Tolerances.none(len(joint_names))
        self._lock = threading.Lock()
        self._active: Goal | None = None        # the goal whose result is pending
        self._running: _Running | None = None   # what is served
        self._before: _Running | None = None    # served until _running's start
        self._hold_next = False                 # hold the next state where it is
        self.last: Snapshot | None = None

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def active_key(self) -> Hashable | None:
        goal = self._active
        return None if goal is None else goal.key

    # -- goals ----------------------------------------------------------------------------
    def submit(self, goal: Goal) -> list[Result]:
        """Take an accepted goal (module docstring); the results it ends: the goal it
        preempts, or the goal itself if its start has passed."""
        if goal.trajectory.n_joints != self.n_joints:
            raise GoalRefused(f'the trajectory has {goal.trajectory.n_joints} joints, the '
                              f'controller {self.n_joints}')
        with self._lock:
            last = self.last
            newest = None if last is None else last.t_ns
            if goal.start_ns and newest is not None and goal.start_ns < newest:
                if not self._replaces(goal, last):
                    return [Result(goal.key, OLD_HEADER_TIMESTAMP, (
                        f'the trajectory came {(newest - goal.start_ns) * 1e-9:.3f} s after its '
                        'start (header stamp): not run, the controller goes on with what it '
                        'runs'))]
                self._running = _Running(goal.trajectory, goal.start_ns, goal)
                self._before = None
            else:
                current = self._running
                if not goal.start_ns:
                    self._before = None
                elif current is not None and current.started:
                    self._before = current      # served until the new start
                # (else: what is served until the earlier goal's start goes on until this one's)
                self._running = _Running(goal.trajectory, goal.start_ns, goal, started=False)
            self._hold_next = False
            ended = self._end_active(INVALID_GOAL, PREEMPTED)
            self._active = goal
            return ended

    def _replaces(self, goal: Goal, last: Snapshot) -> bool:
        """Whether `goal` replaces the running trajectory without a jump: the same start,
        and the same reference at the last state served."""
        running = self._running
        if running is None or running.goal is None or not running.started \
                or running.start_ns != goal.start_ns or last.key != running.goal.key:
            return False
        new = goal.trajectory.sample(last.time_from_start_ns)
        return all(np.array_equal(a, b) for a, b in zip(new, last.desired))

    def cancel(self, key: Hashable) -> list[Result]:
        """Cancel the goal `key` if it is the active one: it ends canceled and the controller
        holds the measured position."""
        with self._lock:
            if self.active_key != key:
                return []
            last = self.last
            if last is None:
                self._running, self._before, self._hold_next = None, None, True
            else:
                self._hold(last.q, last.t_ns)
            return self._end_active(SUCCESSFUL, 'canceled: the controller holds the position',
                                    canceled=True)

    def stop(self, reason: str) -> list[Result]:
        """The robot is lost (its states stopped): the active goal aborts with `reason`, and
        the next state is held where it is."""
        with self._lock:
            self._running, self._before, self._hold_next = None, None, True
            return self._end_active(INVALID_GOAL, reason)

    def _end_active(self, code: int, why: str, canceled: bool = False) -> list[Result]:
        goal, self._active = self._active, None
        return [] if goal is None else [Result(goal.key, code, why, canceled)]

    def _hold(self, q: np.ndarray, t_ns: int) -> None:
        """Serve the position q at rest, no feed-forward, from t_ns on."""
        self._running, self._before = _Running(hold_at(q), t_ns, None), None

    # -- the control step -----------------------------------------------------------------
    def update(self, t_ns: int, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray,
                                                                          list[Result]]:
        """The torque for the state (q, qd) measured at `t_ns` (controller order, finite),
        and the goals that ended with it."""
        with self._lock:
            results: list[Result] = []
            running = self._running
            if running is None or self._hold_next:
                self._hold_next = False
                running = self._running = _Running(hold_at(q), t_ns, None)
            if not running.started:
                if running.start_ns == 0:
                    running.start_ns = t_ns
                if t_ns >= running.start_ns:
                    running.started, self._before = True, None
                    running.trajectory = running.trajectory.starting_from(
                        t_ns - running.start_ns, q, qd)
                elif self._before is not None:
                    running = self._before              # until the new start
                else:                                   # nothing ran: hold here until then
                    running = self._before = _Running(hold_at(q), t_ns, None)
            since = t_ns - running.start_ns
            desired = running.trajectory.sample(since)
            goal = running.goal
            if goal is not None and running is self._running and goal is self._active:
                results = self._check(goal, running, t_ns, desired, q, qd)
                running.sampled = True
                if results:                             # a hold from now on
                    running = self._running
                    since = t_ns - running.start_ns
                    desired = running.trajectory.sample(since)
            torque = self.law.torque(q, qd, desired.positions, desired.velocities,
                                     desired.effort)
            # the active goal's feedback: its sample time, negative while it waits for its
            # start (what is served then is what ran before, as the desired state)
            active, current = self._active, self._running
            key = None if active is None or current.goal is not active else active.key
            shown = since if key is None else t_ns - current.start_ns if current.start_ns else 0
            self.last = Snapshot(t_ns, key, shown, desired, np.array(q, dtype=float),
                                 np.array(qd, dtype=float), torque)
            return torque, results

    def _check(self, goal: Goal, running: _Running, t_ns: int, desired: TrajectorySample,
               q: np.ndarray, qd: np.ndarray) -> list[Result]:
        """The tolerances of the running goal at this state (JTC's update): the results."""
        tol = goal.tolerances
        error, error_d = desired.positions - q, desired.velocities - qd
        since, end = t_ns - running.start_ns, running.trajectory.duration_ns
        if since < end or not running.sampled:     # moving (or a first sample past the end)
            bad = ((tol.path_position > 0) & (np.abs(error) > tol.path_position)) | \
                  ((tol.path_velocity > 0) & (np.abs(error_d) > tol.path_velocity))
            if np.any(bad):
                j = int(np.flatnonzero(bad)[0])
                self._hold(q, t_ns)
                return self._end_active(PATH_TOLERANCE_VIOLATED, (
                    f'path tolerance violated at {since * 1e-9:.3f} s: joint '
                    f'{self.joint_names[j]!r} is {abs(error[j]):.4g} rad from the reference '
                    f'(tolerance {tol.path_position[j]:g} rad), {abs(error_d[j]):.4g} rad/s '
                    f'(tolerance {tol.path_velocity[j]:g}); the controller holds'))
            if since < end:
                return []
        outside = ((tol.goal_position > 0) & (np.abs(error) > tol.goal_position)) | \
                  ((tol.goal_velocity > 0) & (np.abs(error_d) > tol.goal_velocity))
        if not np.any(outside):                 # done: the last point is held as it is
            last = running.trajectory.last_point()
            self._running = _Running(SampledTrajectory(
                np.zeros(1, dtype=np.int64), last.positions[None], last.velocities[None],
                last.effort[None], last.accelerations[None]), t_ns, None)
            return self._end_active(SUCCESSFUL, 'Goal successfully reached!')
        late = (since - end) * 1e-9
        if tol.goal_time > 0.0 and late > tol.goal_time:
            j = int(np.flatnonzero(outside)[0])
            self._hold(q, t_ns)
            return self._end_active(GOAL_TOLERANCE_VIOLATED, (
                f'goal tolerance not met {late:.3f} s after the end (goal_time_tolerance '
                f'{tol.goal_time:g} s): joint {self.joint_names[j]!r} is {abs(error[j]):.4g} '
                f'rad from the last point (tolerance {tol.goal_position[j]:g}), '
                f'{abs(error_d[j]):.4g} rad/s (tolerance {tol.goal_velocity[j]:g}); the '
                'controller holds'))
        return []
