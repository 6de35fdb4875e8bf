"""What a trajectory goal may ask of the arm, for every controller psl serves (``pd_controller``
and the standard robot's, through `psl_controller.follow_joint_trajectory`): whoever sends the
goal, the arm is not moved past its limits. Imports no ROS.

`GoalLimits` is the arm's `psl_task.joint_limits.JointLimits` (``ArmModel.limits``: the joint
ranges, the velocity bound, the torque limits, computed once and held by the safety check too)
with what a controller adds, each a node parameter that can only narrow them:

* the velocity bound narrowed to the node's ``max_velocity`` (none by default:
  `psl_controller.parameters.GOAL_MAX_VELOCITY`);
* the **size**: at most ``max_points`` points and ``max_duration`` s from the trajectory's
  start to its last point, and a start at most ``max_duration`` s after the newest state.

The ranges are not narrowed by the task's ``safety.joint_margin``: psl's own references keep
that margin inside the range (`psl_task.safety_check`), so they pass here with room for the
interpolation between their points.

The rule for a goal (`GoalLimits.check`), refused with one line naming the joint, the value,
where and the bound:

1. at most ``max_points`` points (counted before anything else is read), its last point at
   most ``max_duration`` s from its start;
2. the rule of `psl_task.joint_limits` (the safety check holds psl's references to the same):
   every point's position inside the range, its velocity within the bound, its effort within
   the torque limits; between points, the interpolation the controller samples (linear, cubic
   or quintic: `psl_controller.trajectory_sampling`) inside the range and the velocity bound,
   with a slack of ``POSITION_SLACK`` rad (m) and ``VELOCITY_SLACK`` of the bound. The
   controller clamps what it samples into the limits (`SampledTrajectory.within`), so the
   reference it serves never leaves them.

A goal psl's executor sends is checked here before it goes (`GoalLimits.check_reference`, the
model's limits with the default bounds: `psl_controller.episode`): a controller that rejects it
has limits narrower than the model's (a node parameter, a robot's own JTC), and the executor
says so.

There is no exception for an arm outside its range: every point lies inside. The segment from
the state the controller meets when the trajectory starts to its first point (JTC's, when the
first point is later than the start) cannot be checked when the goal comes: it is clamped into
the range widened to where the arm is, so an arm found outside is brought back toward the range
and never sent further out. To home an arm found outside, send the first point inside the range
(at ``time_from_start`` > 0: the controller moves from where the arm is to it).
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np

from psl_controller.parameters import (GOAL_MAX_DURATION, GOAL_MAX_POINTS,
                                       GOAL_MAX_VELOCITY)
from psl_controller.policy import Reference
from psl_controller.trajectory_controller import GoalRefused
from psl_controller.trajectory_sampling import SampledTrajectory
from psl_task.arm_model import ArmModel
from psl_task.joint_limits import (MAX_VELOCITY, Excess, JointLimits, interpolation_excess,
                                   point_excess)
from psl_task.task import TaskDefinition

NS = 1_000_000_000
UNITS = {'position': '', 'velocity': '/s', 'effort': ' N m'}
SOURCES = {'position': "the model's joint range",
           'velocity': (f"the velocity bound: the URDF's, else {MAX_VELOCITY:g} rad/s; "
                        'safety.max_velocity; the max_velocity parameter'),
           'effort': "the model's torque limit"}


def goal_points(reference: Reference, at_rest: bool = True
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A reference as psl sends it as a FollowJointTrajectory goal
    (`psl_controller.robot_link.trajectory_msg`): the points' times (N,) [integer ns from the
    trajectory's start: a point per control period, the first at ``ref.t[0]``: 0, or later for
    a homing from outside the joint ranges, whose first segment is the controller's], positions,
    velocities (with `at_rest` the last zero: a JTC refuses a trajectory that ends moving; a
    reference ends at rest but for rounding) and the feed-forward, each (N, n)."""
    dt_ns = int(round((reference.t[1] - reference.t[0]) * 1e9)) if len(reference.t) > 1 else 0
    first = int(round(reference.t[0] * 1e9 / dt_ns)) if dt_ns else 0
    times = (first + np.arange(len(reference.t), dtype=np.int64)) * dt_ns
    qd = np.array(reference.qd, dtype=float)
    if at_rest:
        qd[-1] = 0.0
    return times, np.asarray(reference.q, dtype=float), qd, np.asarray(reference.u_ffwd,
                                                                        dtype=float)


@dataclasses.dataclass(frozen=True, eq=False)
class GoalLimits(JointLimits):
    """The limits a goal must keep (module docstring), per joint in the controller's order.

    Raises:
        ValueError: arrays of different lengths, a range with low > high, a velocity bound
            or size bound that is not positive.
    """

    max_points: int = GOAL_MAX_POINTS
    max_duration: float = GOAL_MAX_DURATION     # s

    def __post_init__(self):
        super().__post_init__()
        if self.max_points < 1 or not self.max_duration > 0.0:
            raise ValueError(f'max_points must be >= 1 and max_duration > 0, got '
                             f'{self.max_points}, {self.max_duration}')

    @classmethod
    def of(cls, arm: ArmModel, max_points: int = GOAL_MAX_POINTS,
           max_duration: float = GOAL_MAX_DURATION,
           max_velocity: float = GOAL_MAX_VELOCITY) -> 'GoalLimits':
        """The limits of a task's arm (``ArmModel.limits``) with the node's size bounds, its
        velocity bound narrowed to `max_velocity`."""
        lim = arm.limits
        return cls(lim.joint_names, lim.position_low, lim.position_high,
                   np.minimum(lim.velocity, float(max_velocity)), lim.effort_low,
                   lim.effort_high, int(max_points), float(max_duration))

    @property
    def max_duration_ns(self) -> int:
        return int(round(self.max_duration * NS)) if np.isfinite(self.max_duration) \
            else np.iinfo(np.int64).max

    # -- the rule --------------------------------------------------------------------------
    def check_size(self, n_points: int) -> None:
        """GoalRefused for more than max_points points (before they are read)."""
        if n_points > self.max_points:
            raise GoalRefused(f'the trajectory has {n_points} points, more than max_points '
                              f'{self.max_points} (a parameter of the controller)')

    def check_timing(self, start_ns: int, end_ns: int, newest_ns: int | None) -> None:
        """GoalRefused for a last point more than max_duration from the trajectory's start
        (`end_ns` its time_from_start), or a start (a stamp, 0: now) more than max_duration
        after the newest state (`newest_ns`, None: none yet)."""
        if end_ns > self.max_duration_ns:
            raise GoalRefused(f'the trajectory lasts {end_ns / NS:.12g} s, longer than '
                              f'max_duration {self.max_duration:g} s (a parameter of the '
                              'controller)')
        if start_ns and newest_ns is not None and start_ns - newest_ns > self.max_duration_ns:
            raise GoalRefused(f'the trajectory starts {(start_ns - newest_ns) / NS:.12g} s after '
                              f'the newest state, later than max_duration '
                              f'{self.max_duration:g} s (a parameter of the controller)')

    def check(self, trajectory: SampledTrajectory, times_ns: np.ndarray,
              positions: np.ndarray, velocities: np.ndarray | None,
              efforts: np.ndarray | None) -> None:
        """GoalRefused unless the trajectory (and its points as given: times (N,), each field
        (N, n) or None) keeps the limits (module docstring, rule 2)."""
        excess = point_excess(self, positions, velocities, efforts)
        if excess is not None:
            k, unit = excess.index, UNITS[excess.field]
            raise GoalRefused(
                f'joint {self.joint_names[excess.joint]!r}: {excess.field} '
                f'{excess.value:.6g}{unit} at point {k} (t = {times_ns[k] / NS:.6g} s) is '
                f'{excess.side} its limit {excess.bound:.6g}{unit} ({SOURCES[excess.field]})')
        if trajectory.n_points < 2:
            return
        with np.errstate(over='ignore', invalid='ignore'):
            b_position, b_velocity = trajectory.control_points()
        if not (np.all(np.isfinite(b_position)) and np.all(np.isfinite(b_velocity))):
            raise GoalRefused('the interpolation between the points overflows: velocities or '
                              'accelerations far too large for the time between the points')
        excess = interpolation_excess(self, b_position, b_velocity)
        if excess is not None:
            raise GoalRefused(self._between(trajectory, times_ns, excess))

    def _between(self, trajectory: SampledTrajectory, times_ns: np.ndarray,
                 excess: Excess) -> str:
        """The reason for a segment past the limits."""
        k, unit = excess.index, UNITS[excess.field]
        t = (times_ns[k] + excess.s * (times_ns[k + 1] - times_ns[k])) / NS
        return (f'joint {self.joint_names[excess.joint]!r}: the {trajectory.interpolation} '
                f'interpolation between points {k} and {k + 1} reaches {excess.field} '
                f'{excess.value:.6g}{unit} at t = {t:.6g} s, {excess.side} its limit '
                f'{excess.bound:.6g}{unit} ({SOURCES[excess.field]}; an overshoot of '
                f'{excess.slack:.3g} is tolerated)')

    def check_reference(self, reference: Reference, effort: bool = True) -> None:
        """GoalRefused unless a reference as psl sends it (`goal_points`; its feed-forward
        as the points' effort if `effort`) keeps these limits: its size and the rule."""
        times, q, qd, u = goal_points(reference)
        u = u if effort else None
        self.check_size(len(times))
        self.check_timing(0, int(times[-1]), None)
        self.check(SampledTrajectory(times, q, qd, u), times, q, qd, u)

    def bound(self, trajectory: SampledTrajectory) -> SampledTrajectory:
        """The trajectory with what it samples clamped into these limits
        (`SampledTrajectory.within`)."""
        return trajectory.within(self.position_low, self.position_high, self.velocity)


@functools.lru_cache(maxsize=8)
def limits_of(task: TaskDefinition, max_points: int = GOAL_MAX_POINTS,
              max_duration: float = GOAL_MAX_DURATION,
              max_velocity: float = GOAL_MAX_VELOCITY) -> GoalLimits:
    """`GoalLimits.of` the task's arm."""
    return GoalLimits.of(ArmModel(task), max_points, max_duration, max_velocity)
