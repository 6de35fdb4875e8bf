"""What a trajectory goal may ask of the arm, written once for every controller psl serves
(``pd_controller`` and the standard robot's, through `psl_controller.follow_joint_trajectory`):
whoever sends the goal, the arm is not moved past its limits. Imports no ROS.

`GoalLimits` holds, per joint in the controller's order:

* the **position range**: the model's joint range (``jnt_range`` of a limited joint; an
  unlimited one has none). Not narrowed by the task's ``safety.joint_margin``: psl's own
  references keep that margin inside the range (`psl_task.safety_check`), so they pass here
  with room for the interpolation between their points;
* the **velocity bound**: the smallest of the URDF's ``<limit velocity>`` (a model read from a
  URDF; MuJoCo keeps no velocity limit, an MJCF has none), the task's
  ``safety.max_velocity`` (what psl's own references keep, when the task sets it) and the
  node's ``max_velocity`` parameter (`psl_controller.parameters.GOAL_MAX_VELOCITY` by
  default: the bound for a model and task that give none);
* the **effort bound**: the torque that reaches the joint (`ArmModel.torque_low` /
  ``torque_high``: the motor's ctrlrange narrowed by force ranges), which the PD law clips to;
* the **size**: at most ``max_points`` points and ``max_duration`` s from the trajectory's
  start to its last point, and a start at most ``max_duration`` s after the newest state.

The rule for a goal (`GoalLimits.check`), refused with one line naming the joint, the value,
where and the bound:

1. at most ``max_points`` points (counted before anything else is read), its last point at
   most ``max_duration`` s from its start;
2. every point's position inside the range, its velocity within the bound, its effort within
   the torque limits (strictly: a point is what the arm is sent to);
3. between points, the interpolation the controller samples (linear, cubic or quintic:
   `psl_controller.trajectory_sampling`) inside the range and the velocity bound: each
   segment's extremes found exactly (to rounding) from its Bernstein control points
   (`trajectory_sampling.maxima`). A segment may overshoot by ``POSITION_SLACK`` rad (m) and
   its velocity by ``VELOCITY_SLACK`` of the bound: psl's references are checked on their
   points (every control period), and the polynomial through two points near a limit may
   bulge past it by about ``qdd dt^2 / 8`` (5e-5 rad for 100 rad/s^2 at 500 Hz). The
   controller clamps what it samples into the limits (`SampledTrajectory.within`), so the
   reference it serves never leaves them.

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
import xml.etree.ElementTree as ElementTree

import numpy as np

from psl_controller.parameters import (GOAL_MAX_DURATION, GOAL_MAX_POINTS,
                                       GOAL_MAX_VELOCITY)
from psl_controller.trajectory_controller import GoalRefused
from psl_controller.trajectory_sampling import SampledTrajectory, maxima
from psl_task.arm_model import ArmModel
from psl_task.task import TaskDefinition

POSITION_SLACK = 1e-3       # rad (m) a segment between two points may overshoot the range
VELOCITY_SLACK = 1e-2       # share of the velocity bound a segment's velocity may exceed it by
NS = 1_000_000_000


def urdf_velocity_limits(task: TaskDefinition, joint_names: list[str]) -> np.ndarray:
    """The URDF's ``<limit velocity="...">`` of each joint (inf where it gives none, or the
    model is not a URDF): MuJoCo's URDF import drops them."""
    limits = np.full(len(joint_names), np.inf)
    if task.model_path.suffix.lower() != '.urdf':
        return limits
    try:
        root = ElementTree.parse(task.model_path).getroot()
    except (OSError, ElementTree.ParseError):     # MuJoCo read it: nothing to add here
        return limits
    for joint in root.iter('joint'):
        limit = joint.find('limit')
        if limit is None or joint.get('name') not in joint_names:
            continue
        try:
            velocity = float(limit.get('velocity', 'inf'))
        except ValueError:
            continue
        if velocity > 0.0:
            limits[joint_names.index(joint.get('name'))] = velocity
    return limits


@dataclasses.dataclass(frozen=True, eq=False)
class GoalLimits:
    """The limits a goal must keep (module docstring), per joint in the controller's order.

    Raises:
        ValueError: arrays of different lengths, a range with low > high, a velocity bound
            or size bound that is not positive.
    """

    joint_names: tuple[str, ...]
    position_low: np.ndarray        # (n,) rad (m); -inf: unlimited
    position_high: np.ndarray       # (n,)
    velocity: np.ndarray            # (n,) rad/s (m/s), > 0
    effort_low: np.ndarray          # (n,) N m (N)
    effort_high: np.ndarray         # (n,)
    max_points: int = GOAL_MAX_POINTS
    max_duration: float = GOAL_MAX_DURATION     # s

    def __post_init__(self):
        n = len(self.joint_names)
        for name in ('position_low', 'position_high', 'velocity', 'effort_low',
                     'effort_high'):
            value = np.array(getattr(self, name), dtype=float)
            if value.shape != (n,) or np.isnan(value).any():
                raise ValueError(f'{name} needs {n} numbers, got {value}')
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        if np.any(self.position_low > self.position_high) or \
                np.any(self.effort_low > self.effort_high):
            raise ValueError('a range needs low <= high')
        if not np.all(self.velocity > 0.0):
            raise ValueError(f'velocity bounds must be > 0, got {self.velocity}')
        if self.max_points < 1 or not self.max_duration > 0.0:
            raise ValueError(f'max_points must be >= 1 and max_duration > 0, got '
                             f'{self.max_points}, {self.max_duration}')

    @classmethod
    def of(cls, arm: ArmModel, max_points: int = GOAL_MAX_POINTS,
           max_duration: float = GOAL_MAX_DURATION,
           max_velocity: float = GOAL_MAX_VELOCITY) -> 'GoalLimits':
        """The limits of a task's arm (module docstring) with the node's size and velocity
        bounds."""
        m, names = arm.model, list(arm.joint_names)
        limited = m.jnt_limited[arm.joint_ids].astype(bool)
        low = np.where(limited, m.jnt_range[arm.joint_ids, 0], -np.inf)
        high = np.where(limited, m.jnt_range[arm.joint_ids, 1], np.inf)
        velocity = np.minimum(urdf_velocity_limits(arm.task, names),
                              min(float(arm.task.safety.max_velocity), float(max_velocity)))
        return cls(tuple(names), low, high, velocity, arm.torque_low, arm.torque_high,
                   int(max_points), float(max_duration))

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
        (N, n) or None) keeps the limits (module docstring, rules 2 and 3)."""
        names = self.joint_names
        for field, values, low, high, unit in (
                ('position', positions, self.position_low, self.position_high, ''),
                ('velocity', velocities, -self.velocity, self.velocity, '/s'),
                ('effort', efforts, self.effort_low, self.effort_high, ' N m')):
            if values is None:
                continue
            excess = np.maximum(low - values, values - high)              # (N, n)
            if np.any(excess > 0.0):
                k, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
                value = values[k, j]
                side, bound = ('below', low[j]) if value < low[j] else ('above', high[j])
                raise GoalRefused(
                    f'joint {names[j]!r}: {field} {value:.6g}{unit} at point {k} (t = '
                    f'{times_ns[k] / NS:.6g} s) is {side} its limit {bound:.6g}{unit} '
                    f'({self._source(field)})')
        if trajectory.n_points < 2:
            return
        with np.errstate(over='ignore', invalid='ignore'):
            b_position, b_velocity = trajectory.control_points()
        if not (np.all(np.isfinite(b_position)) and np.all(np.isfinite(b_velocity))):
            raise GoalRefused('the interpolation between the points overflows: velocities or '
                              'accelerations far too large for the time between the points')
        for field, points, low, high, slack in (
                ('position', b_position, self.position_low, self.position_high,
                 np.full(len(names), POSITION_SLACK)),
                ('velocity', b_velocity, -self.velocity, self.velocity,
                 VELOCITY_SLACK * self.velocity)):
            for sign, bound, side in ((1.0, high, 'above'), (-1.0, -low, 'below')):
                top, segment, s = maxima(sign * points, bound + slack)
                over = top - bound
                if np.any(over > slack):
                    j = int(np.argmax(over - slack))
                    k = int(segment[j])
                    t = (times_ns[k] + s[j] * (times_ns[k + 1] - times_ns[k])) / NS
                    unit = '/s' if field == 'velocity' else ''
                    raise GoalRefused(
                        f'joint {names[j]!r}: the {trajectory.interpolation} interpolation '
                        f'between points {k} and {k + 1} reaches {field} {sign * top[j]:.6g}'
                        f'{unit} at t = {t:.6g} s, {side} its limit {sign * bound[j]:.6g}'
                        f'{unit} ({self._source(field)}; an overshoot of {slack[j]:.3g} is '
                        'tolerated)')

    def _source(self, field: str) -> str:
        return {'position': "the model's joint range",
                'velocity': 'the velocity bound: URDF, safety.max_velocity, max_velocity',
                'effort': "the model's torque limit"}[field]

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
