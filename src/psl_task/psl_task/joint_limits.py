"""The limits psl holds a task's arm to, per driven joint, and the rule a trajectory through
points keeps them by: written once for the safety check (`psl_task.safety_check`: every
reference before it runs, in both rollout modes) and for every controller psl serves
(`psl_controller.goal_limits`: every goal, whoever sends it), so that a reference the safety
check passes is a goal the controllers take, and batch mode never runs a candidate the graph's
controller would reject. Imports no ROS.

`JointLimits` (``ArmModel.limits``), per joint in command order:

* the **position range**: the model's joint range (``jnt_range`` of a limited joint; an
  unlimited one has none);
* the **velocity bound**: the URDF's ``<limit velocity>`` (MuJoCo's URDF import drops it:
  `psl_task.model_spec.urdf_velocity_limits`), else `MAX_VELOCITY` (an MJCF has none); the
  task's ``safety.max_velocity`` where it is lower;
* the **effort bound**: the torque that reaches the joint (`ArmModel.torque_low` /
  ``torque_high``: the motor's ctrlrange narrowed by force ranges), which the PD law clips to.

The rule a trajectory through points keeps (`point_excess`, `interpolation_excess`):

1. every point's position inside the range, its velocity within the bound, its effort within
   the torque limits (strictly: a point is what the arm is sent to);
2. between points, the interpolation a JointTrajectoryController samples (linear, cubic or
   quintic by the fields given: `control_points`; psl's goals carry positions and velocities:
   cubic) inside the range and the velocity bound, each segment's extremes found exactly (to
   rounding) from its Bernstein control points (`maxima`). A segment may overshoot the range
   by `POSITION_SLACK` rad (m) and the bound by `VELOCITY_SLACK` of it: the polynomial through
   two points near a limit may bulge past it by about ``qdd dt^2 / 8`` (5e-5 rad for 100 rad/s^2
   at 500 Hz); beyond the slack the trajectory is refused, the safety check's candidate as the
   controller's goal.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

# [rad/s (m/s)] the velocity bound of a joint whose model gives none (an MJCF has no velocity
# limit; MuJoCo drops a URDF's): arms' joints are far slower (2-4 rad/s for industrial arms,
# 10-20 for small fast ones); psl's demonstrations on the embedded tasks reach 4 rad/s
MAX_VELOCITY = 100.0
POSITION_SLACK = 1e-3       # rad (m) a segment between two points may overshoot the range
VELOCITY_SLACK = 1e-2       # share of the velocity bound a segment's velocity may exceed it by
MAX_SUBDIVISIONS = 48       # halvings of a segment in `maxima` (a width of 2^-48 of it)
MAX_CANDIDATES = 1 << 16    # subintervals `maxima` keeps at once (then it stops: a bound)
FIELDS = ('position', 'velocity', 'effort')


@dataclasses.dataclass(frozen=True, eq=False)
class JointLimits:
    """The limits of an arm's joints (module docstring), per joint in command order.

    Raises:
        ValueError: arrays of different lengths or with NaN, a range with low > high, a
            velocity bound that is not positive.
    """

    joint_names: tuple[str, ...]
    position_low: np.ndarray        # (n,) rad (m); -inf: unlimited
    position_high: np.ndarray       # (n,)
    velocity: np.ndarray            # (n,) rad/s (m/s), > 0
    effort_low: np.ndarray          # (n,) N m (N)
    effort_high: np.ndarray         # (n,)

    def __post_init__(self):
        n = len(self.joint_names)
        object.__setattr__(self, 'joint_names', tuple(self.joint_names))
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

    def tolerated(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What a segment between points may reach (rule 2): the position range widened by
        POSITION_SLACK (low, high) and the velocity bound raised by VELOCITY_SLACK of it,
        each (n,)."""
        return (self.position_low - POSITION_SLACK, self.position_high + POSITION_SLACK,
                self.velocity + VELOCITY_SLACK * self.velocity)

    def bounds(self, field: str) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of a field of `FIELDS`, each (n,)."""
        return {'position': (self.position_low, self.position_high),
                'velocity': (-self.velocity, self.velocity),
                'effort': (self.effort_low, self.effort_high)}[field]


class Excess(NamedTuple):
    """Where a trajectory leaves its limits (`point_excess`, `interpolation_excess`)."""

    field: str          # one of FIELDS
    joint: int
    index: int          # the point, or the first point of the segment
    s: float            # where in the segment, [0, 1] (0 at a point)
    value: float        # the value reached there
    bound: float        # the bound it passes (low or high)
    over: float         # how far beyond the bound (between points: beyond bound and slack)
    slack: float        # what was tolerated beyond the bound (0 at points)
    between: bool       # between points (the interpolation), not at one

    @property
    def side(self) -> str:
        return 'below' if self.value < self.bound else 'above'


def point_excess(limits: JointLimits, positions: np.ndarray | None,
                 velocities: np.ndarray | None, efforts: np.ndarray | None) -> Excess | None:
    """Rule 1 (module docstring) on the points, each field (N, n) or None (not given): the
    first field (position, velocity, effort) with a value beyond its bound, at its largest
    excess; None when every point keeps the limits."""
    for field, values in zip(FIELDS, (positions, velocities, efforts)):
        if values is None:
            continue
        low, high = limits.bounds(field)
        excess = np.maximum(low - values, values - high)                  # (N, n)
        if np.any(excess > 0.0):
            k, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
            value = float(values[k, j])
            bound = float(low[j] if value < low[j] else high[j])
            return Excess(field, int(j), int(k), 0.0, value, bound, float(excess[k, j]), 0.0,
                          False)
    return None


def interpolation_excess(limits: JointLimits, b_position: np.ndarray,
                         b_velocity: np.ndarray) -> Excess | None:
    """Rule 2 (module docstring) on the segments given by their Bernstein control points
    (`control_points`: positions (d + 1, N - 1, n), velocities (d, N - 1, n), finite): the
    first field and side (position above, below; velocity above, below) some segment passes
    by more than the slack, at that joint's extreme; None when every segment keeps the
    limits."""
    if b_position.shape[1] == 0:                    # one point: no segment
        return None
    low, high, speed = limits.tolerated()
    for field, points, sides in (
            ('position', b_position, ((high, limits.position_high),
                                      (-low, -limits.position_low))),
            ('velocity', b_velocity, ((speed, limits.velocity), (speed, limits.velocity)))):
        for sign, (allowed, bound) in zip((1.0, -1.0), sides):      # (n,) each, signed
            if not np.any((sign * points).max(axis=(0, 1)) > allowed):
                continue                # every control point within: so is every segment
            top, _, _ = maxima(sign * points, allowed)
            if np.any(top > allowed):
                j = int(np.argmax(top - allowed))
                top, segment, s = maxima(sign * points[:, :, j:j + 1])     # its extreme
                return Excess(field, j, int(segment[0]), float(s[0]), float(sign * top[0]),
                              float(sign * bound[j]), float(top[0] - allowed[j]),
                              float(allowed[j] - bound[j]), True)
    return None


def control_points(durations: np.ndarray, positions: np.ndarray,
                   velocities: np.ndarray | None = None,
                   accelerations: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The Bernstein control points of each segment's position and velocity polynomial over
    its own time s in [0, 1], for points (..., N, n) whose segments last `durations` (N - 1,)
    [s]: positions (d + 1, ..., N - 1, n) [rad] and velocities (d, ..., N - 1, n) [rad/s]
    for the interpolation's degree d: 1 (positions only), 3 (with velocities), 5 (with
    accelerations too), as a JointTrajectoryController interpolates
    (`psl_controller.trajectory_sampling`). A polynomial lies within the convex hull of its
    control points, and its first and last are its values at the segment's ends (Farin,
    *Curves and Surfaces for CAGD*, 5th ed., 2002, ch. 4-5); `maxima` finds each joint's
    extremes from them. The Hermite conditions give them: a cubic's are q0, q0 + v0 T/3,
    q1 - v1 T/3, q1; a quintic's q0, q0 + v0 T/5, q0 + 2 v0 T/5 + a0 T^2/20,
    q1 - 2 v1 T/5 + a1 T^2/20, q1 - v1 T/5, q1 (T the segment's length); the velocity's are
    d (b_{i+1} - b_i) / T."""
    big_t = np.asarray(durations, dtype=float)[:, None]                 # (N-1, 1) s
    q = positions
    q0, q1 = q[..., :-1, :], q[..., 1:, :]
    if velocities is None:
        b = np.stack([q0, q1])
    elif accelerations is None:
        v0, v1 = velocities[..., :-1, :], velocities[..., 1:, :]
        b = np.stack([q0, q0 + v0 * big_t / 3.0, q1 - v1 * big_t / 3.0, q1])
    else:
        v0, v1 = velocities[..., :-1, :], velocities[..., 1:, :]
        a0, a1 = accelerations[..., :-1, :], accelerations[..., 1:, :]
        t2 = big_t ** 2 / 20.0
        b = np.stack([q0, q0 + v0 * big_t / 5.0, q0 + 0.4 * v0 * big_t + a0 * t2,
                      q1 - 0.4 * v1 * big_t + a1 * t2, q1 - v1 * big_t / 5.0, q1])
    return b, (len(b) - 1) * np.diff(b, axis=0) / big_t


def maxima(points: np.ndarray, above: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each joint's largest value over m polynomials on [0, 1], given by their Bernstein
    control points (k, m, n) (`control_points`): (value (n,), the polynomial it is reached on
    (n,), s there (n,)); -inf, 0, 0 for m = 0. With `above` (n,), only whether a joint's
    maximum exceeds it is sought: a joint's value is then a value reached beyond `above` (not
    necessarily the largest), or, where none is, the largest reached at the polynomials' ends
    and halvings that were looked at (at most `above` + its rounding).

    Branch and bound on the convex hull property: the value at an interval's ends is reached,
    the largest control point bounds the interval from above; an interval whose bound does
    not exceed the best value reached (by more than 1e-12 of its size) or `above` is dropped,
    the others are halved (de Casteljau) until none is left. Without `above` the value is the
    maximum to 1e-12 (relative); intervals left after MAX_SUBDIVISIONS halvings or beyond
    MAX_CANDIDATES (pathological input) add their bound.
    """
    k, m, n = points.shape
    best, where, at = np.full(n, -np.inf), np.zeros(n, dtype=np.int64), np.zeros(n)
    if m == 0:
        return best, where, at
    floor = np.full(n, -np.inf) if above is None else np.asarray(above, dtype=float)
    ends = np.concatenate([points[0], points[-1]])                      # (2m, n)
    row = ends.argmax(axis=0)
    best, where, at = ends[row, np.arange(n)], row % m, (row // m).astype(float)

    def threshold() -> np.ndarray:
        """Below it an interval cannot matter; inf for a joint found beyond `above`."""
        tight = np.maximum(best + 1e-12 * np.maximum(1.0, np.abs(best)), floor)
        return tight if above is None else np.where(best > floor, np.inf, tight)
    segment, joint = np.nonzero(points.max(axis=0) > threshold())
    b = points[:, segment, joint]                                       # (k, r)
    start, width = np.zeros(segment.size), 1.0
    for _ in range(MAX_SUBDIVISIONS):
        if segment.size == 0 or segment.size > MAX_CANDIDATES:
            break
        left, right = _halves(b)
        width /= 2.0
        middle = left[-1]                                               # reached: (r,)
        for j in np.unique(joint):
            mine = np.flatnonzero(joint == j)
            i = mine[int(np.argmax(middle[mine]))]
            if middle[i] > best[j]:
                best[j], where[j], at[j] = middle[i], segment[i], start[i] + width
        b = np.concatenate([left, right], axis=1)
        segment, joint = np.tile(segment, 2), np.tile(joint, 2)
        start = np.concatenate([start, start + width])
        keep = b.max(axis=0) > threshold()[joint]
        b, segment, joint, start = b[:, keep], segment[keep], joint[keep], start[keep]
    if segment.size:                     # not resolved: their bound (never below the truth)
        bound = b.max(axis=0)
        for j in np.unique(joint):
            mine = np.flatnonzero(joint == j)
            i = mine[int(np.argmax(bound[mine]))]
            if bound[i] > best[j]:
                best[j], where[j], at[j] = bound[i], segment[i], start[i] + width / 2.0
    return best, where, at


def _halves(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """de Casteljau at s = 1/2: the control points (k, r) of the left and right halves."""
    left, right, current = [b[0]], [b[-1]], b
    for _ in range(len(b) - 1):
        current = 0.5 * (current[:-1] + current[1:])
        left.append(current[0])
        right.append(current[-1])
    return np.stack(left), np.stack(right[::-1])
