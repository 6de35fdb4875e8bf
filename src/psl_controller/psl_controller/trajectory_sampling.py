"""Sampling of a joint trajectory in time, as ros2_controllers' joint_trajectory_controller (JTC,
Jazzy: ``joint_trajectory_controller/src/trajectory.cpp``) samples one, kept apart from the
controller. Pure numpy; no ROS.

Times are integer nanoseconds from the trajectory start (``time_from_start``), so comparisons
with the points' times are exact. The interpolation between two points follows from the fields
the trajectory gives, as in JTC:

* positions only: **linear** (the velocity is the segment's slope, the acceleration zero);
* positions and velocities: **cubic** (position and velocity of both ends met);
* positions, velocities and accelerations: **quintic** (position, velocity and acceleration of
  both ends met);
* effort (the feed-forward torque, added to the PD output: :mod:`pd_law`): linear, always.

Edge cases, for a query time ``t`` and point times ``t_0 < t_1 < ... < t_{N-1}``:

* empty trajectory: rejected at construction (``ValueError``).
* ``t == t_i`` (exactly on a point): that point's values, bit for bit (no arithmetic), so a
  robot whose states come exactly at the points' times (psl's lockstep simulator) is served
  the very reference batch mode computes; a positions-only trajectory has no velocities to
  give: the velocity is the slope of the segment the point starts (zero at the last point).
* ``t_i < t < t_{i+1}``: the segment's polynomial (above).
* ``t < t_0`` (before the first point): with a point before the trajectory
  (`SampledTrajectory.starting_from`: JTC's state when it first sampled the trajectory) at
  ``t_b <= t``: the segment from that point to the first point, of the first point's degree,
  effort from zero (JTC); before ``t_b``, or with no such point: the first point's position
  with zero velocity and acceleration and its effort.
* ``t > t_{N-1}`` (past the end): the last point as given (JTC holds it; a trajectory a JTC
  accepts ends at rest).
* single-point trajectory: the rules above with ``t_0 = t_{N-1}``.

Limits (`SampledTrajectory.within`: a goal's trajectory on a controller with joint limits,
`psl_controller.goal_limits`): the reference sampled between points (a segment's polynomial,
and the segment from the state before the trajectory) is clamped into the position range and
the velocity bound: a position outside the range is put on its bound, with zero velocity and
acceleration; a velocity beyond its bound is put on it. The segment from the state before the
trajectory keeps a range widened to that state's position (an arm found outside its range is
brought back, never sent further out). A point is never changed: the controller refuses a
trajectory whose points or segments leave the limits (`control_points` and
`psl_task.joint_limits.maxima` give each segment's extremes exactly, to rounding), so what the
clamp catches is the interpolation's overshoot within the refusal's slack, and the segment from
a state the controller meets only when the trajectory starts.

Differences from JTC, deliberately: times are integer nanoseconds, not floating seconds; a
point's fields are all-or-none for the whole trajectory (JTC allows them per point); the
limits above (JTC's trajectory knows none).
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from psl_task.joint_limits import control_points

LINEAR, CUBIC, QUINTIC = 'linear', 'cubic', 'quintic'


class TrajectorySample(NamedTuple):
    """The reference at one time, each (n,): position, velocity, acceleration, effort."""

    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray
    effort: np.ndarray


def _point_array(value, shape: tuple[int, int], name: str) -> np.ndarray | None:
    if value is None:
        return None
    array = np.asarray(value, dtype=float)
    if array.shape != shape:
        raise ValueError(f'{name} must have shape {shape}, got {array.shape}')
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{name} must be finite')
    return array.copy()


class SampledTrajectory:
    """Joint trajectory with points at integer-nanosecond times (see module docstring).

    Args:
        times_ns: time from the trajectory start of each point, integer dtype, shape (N,),
            strictly increasing, first >= 0.
        positions: shape (N, n).
        velocities: shape (N, n), or None (linear interpolation).
        efforts: shape (N, n), or None for zeros.
        accelerations: shape (N, n), or None (at most cubic); needs velocities.

    Raises:
        ValueError: empty trajectory, non-integer or non-increasing or negative times,
            mismatched shapes, non-finite values, accelerations without velocities.
    """

    def __init__(self, times_ns: np.ndarray, positions: np.ndarray,
                 velocities: np.ndarray | None = None,
                 efforts: np.ndarray | None = None,
                 accelerations: np.ndarray | None = None) -> None:
        times_ns = np.asarray(times_ns)
        if times_ns.ndim != 1:
            raise ValueError(f'times_ns must have shape (N,), got {times_ns.shape}')
        if times_ns.size == 0:
            raise ValueError('trajectory is empty: at least one point is required')
        if not np.issubdtype(times_ns.dtype, np.integer):
            raise ValueError(f'times_ns must be integer nanoseconds, got dtype {times_ns.dtype}')
        times_ns = times_ns.astype(np.int64)
        if times_ns[0] < 0:
            raise ValueError(f'first point time must be >= 0 ns, got {times_ns[0]}')
        if np.any(np.diff(times_ns) <= 0):
            raise ValueError('point times must be strictly increasing')
        positions = np.asarray(positions, dtype=float)
        if positions.ndim != 2 or positions.shape[0] != times_ns.size:
            raise ValueError(f'positions must have shape ({times_ns.size}, n), '
                             f'got {positions.shape}')
        shape = positions.shape
        if accelerations is not None and velocities is None:
            raise ValueError('accelerations need velocities (quintic interpolation)')
        self._times_ns = times_ns                                           # (N,)
        self._positions = _point_array(positions, shape, 'positions')       # (N, n)
        velocities = _point_array(velocities, shape, 'velocities')
        accelerations = _point_array(accelerations, shape, 'accelerations')
        self.interpolation = (LINEAR if velocities is None else
                              CUBIC if accelerations is None else QUINTIC)
        zeros = np.zeros(shape)
        self._velocities = zeros if velocities is None else velocities      # (N, n)
        self._accelerations = zeros if accelerations is None else accelerations
        efforts = _point_array(efforts, shape, 'efforts')
        self._efforts = zeros if efforts is None else efforts               # (N, n)
        self.has_effort = efforts is not None
        self._before: tuple[int, np.ndarray, np.ndarray] | None = None     # (t_b, q, qd)
        self._bounds: _Bounds | None = None         # between points (`within`)
        self._start_bounds: _Bounds | None = None   # from the point before the trajectory

    def within(self, low: np.ndarray, high: np.ndarray,
               speed: np.ndarray) -> 'SampledTrajectory':
        """This trajectory with its samples between points clamped into the position range
        [low, high] and the velocity bound |qd| <= speed, each (n,) (module docstring)."""
        bounds = _Bounds(*(np.array(np.broadcast_to(np.asarray(v, dtype=float),
                                                    (self.n_joints,))) for v in (low, high,
                                                                                   speed)))
        if np.any(bounds.low > bounds.high) or np.any(bounds.speed < 0.0):
            raise ValueError('the limits need low <= high and a speed >= 0')
        copy = self._copy()
        copy._bounds = bounds
        if self._before is not None:
            copy._start_bounds = bounds.widened(self._before[1])
        return copy

    def _copy(self) -> 'SampledTrajectory':
        copy = object.__new__(SampledTrajectory)
        copy.__dict__.update(self.__dict__)
        return copy

    def starting_from(self, t_ns: int, positions: np.ndarray,
                      velocities: np.ndarray) -> 'SampledTrajectory':
        """This trajectory with a point before it (JTC's state when it first sampled the
        trajectory): at `t_ns` (from the trajectory start) the arm was at `positions` with
        `velocities`; between then and the first point the reference is the segment between
        the two (module docstring). No effect when `t_ns` is at or past the first point."""
        t_ns = _as_int_ns(t_ns)
        copy = self._copy()
        copy._before, copy._start_bounds = None, None
        if t_ns < self._times_ns[0]:
            q, qd = (np.asarray(v, dtype=float).reshape(self.n_joints)
                     for v in (positions, velocities))
            copy._before = (t_ns, q.copy(), qd.copy() if self.interpolation != LINEAR
                            else np.zeros(self.n_joints))
            if self._bounds is not None:
                copy._start_bounds = self._bounds.widened(q)
        return copy

    @property
    def n_points(self) -> int:
        return self._times_ns.size

    @property
    def n_joints(self) -> int:
        return self._positions.shape[1]

    @property
    def duration_ns(self) -> int:
        """Time of the last point from the trajectory start, in ns."""
        return int(self._times_ns[-1])

    def last_point(self) -> TrajectorySample:
        """The last point (what JTC holds once a goal has succeeded)."""
        return self._point(-1)

    def is_finished(self, t_ns: int) -> bool:
        """True once ``t_ns`` has reached the last point's time (``t_ns >= duration_ns``)."""
        return _as_int_ns(t_ns) >= self.duration_ns

    def sample(self, t_ns: int) -> TrajectorySample:
        """Reference at ``t_ns`` nanoseconds from the trajectory start (module docstring).

        Raises:
            TypeError: ``t_ns`` is not an integer.
        """
        t_ns = _as_int_ns(t_ns)
        times = self._times_ns
        if t_ns < times[0]:
            before = self._before
            if before is None or t_ns < before[0]:
                zeros = np.zeros(self.n_joints)
                return TrajectorySample(self._positions[0].copy(), zeros, zeros.copy(),
                                        self._efforts[0].copy())
            t_b, q_b, qd_b = before
            zeros = np.zeros(self.n_joints)
            return _clamped(_segment(self.interpolation, t_ns - t_b, int(times[0]) - t_b,
                                     (q_b, qd_b, zeros, zeros), self._values(0)),
                            self._start_bounds)
        if t_ns >= times[-1]:
            return self._point(-1)
        # times[i - 1] < t_ns <= times[i]
        i = int(np.searchsorted(times, t_ns, side='left'))
        if times[i] == t_ns:
            return self._point(i)
        t_prev = int(times[i - 1])
        return _clamped(_segment(self.interpolation, t_ns - t_prev, int(times[i]) - t_prev,
                                 self._values(i - 1), self._values(i)), self._bounds)

    def control_points(self) -> tuple[np.ndarray, np.ndarray]:
        """The Bernstein control points of each segment's position and velocity polynomial
        over its own time s in [0, 1]: positions (d + 1, N - 1, n) [rad] and velocities
        (d, N - 1, n) [rad/s] for the interpolation's degree d (1, 3, 5)
        (`psl_task.joint_limits.control_points`: the one law of what a goal's points
        interpolate to, shared with the safety check; `psl_task.joint_limits.maxima` finds
        each joint's extremes from them)."""
        return control_points(np.diff(self._times_ns) * 1e-9, self._positions,
                              None if self.interpolation == LINEAR else self._velocities,
                              self._accelerations if self.interpolation == QUINTIC else None)

    def _values(self, i: int) -> tuple[np.ndarray, ...]:
        return (self._positions[i], self._velocities[i], self._accelerations[i],
                self._efforts[i])

    def _point(self, i: int) -> TrajectorySample:
        """Point i's values; of a positions-only trajectory, whose points carry no velocity,
        the velocity is that of the segment the point starts (JTC samples a point as the
        start of its segment), zero at the last."""
        q, qd, qdd, effort = (v.copy() for v in self._values(i))
        if self.interpolation == LINEAR and i % self.n_points != self.n_points - 1:
            qd = (self._positions[i + 1] - q) / ((self._times_ns[i + 1] - self._times_ns[i])
                                                 * 1e-9)
            return _clamped(TrajectorySample(q, qd, qdd, effort), self._bounds)
        return TrajectorySample(q, qd, qdd, effort)


@dataclasses.dataclass(frozen=True, eq=False)
class _Bounds:
    """A position range and a velocity bound, each (n,)."""

    low: np.ndarray
    high: np.ndarray
    speed: np.ndarray

    def widened(self, q: np.ndarray) -> '_Bounds':
        """The range widened to the position q (the state before a trajectory)."""
        return _Bounds(np.minimum(self.low, q), np.maximum(self.high, q), self.speed)


def _clamped(sample: TrajectorySample, bounds: _Bounds | None) -> TrajectorySample:
    """`sample` within `bounds` (module docstring): a position outside the range on its
    bound at rest, a velocity beyond its bound on it; unchanged (the same arrays) inside."""
    if bounds is None:
        return sample
    q, qd, qdd, effort = sample
    outside = (q < bounds.low) | (q > bounds.high)
    if outside.any():
        q = np.clip(q, bounds.low, bounds.high)
        qd, qdd = np.where(outside, 0.0, qd), np.where(outside, 0.0, qdd)
    if np.any(np.abs(qd) > bounds.speed):
        qd = np.clip(qd, -bounds.speed, bounds.speed)
    return TrajectorySample(q, qd, qdd, effort)


def _segment(kind: str, t_ns: int, length_ns: int, a: tuple, b: tuple) -> TrajectorySample:
    """The segment from point a to point b (each (q, qd, qdd, effort)) of length `length_ns`,
    at `t_ns` from a: JTC's `interpolate_between_points` (its coefficients), 0 < t < length."""
    t, big_t = t_ns * 1e-9, length_ns * 1e-9
    q0, v0, a0, e0 = a
    q1, v1, a1, e1 = b
    effort = e0 + (e1 - e0) / big_t * t
    if kind == LINEAR:
        slope = (q1 - q0) / big_t
        return TrajectorySample(q0 + slope * t, slope, np.zeros_like(q0), effort)
    if kind == CUBIC:
        c2 = (-3.0 * q0 + 3.0 * q1 - 2.0 * v0 * big_t - v1 * big_t) / big_t ** 2
        c3 = (2.0 * q0 - 2.0 * q1 + v0 * big_t + v1 * big_t) / big_t ** 3
        return TrajectorySample(q0 + v0 * t + c2 * t ** 2 + c3 * t ** 3,
                                v0 + 2.0 * c2 * t + 3.0 * c3 * t ** 2,
                                2.0 * c2 + 6.0 * c3 * t, effort)
    t2, t3, t4, t5 = (big_t ** k for k in (2, 3, 4, 5))
    c2 = 0.5 * a0
    c3 = (-20.0 * q0 + 20.0 * q1 - 3.0 * a0 * t2 + a1 * t2 - 12.0 * v0 * big_t
          - 8.0 * v1 * big_t) / (2.0 * t3)
    c4 = (30.0 * q0 - 30.0 * q1 + 3.0 * a0 * t2 - 2.0 * a1 * t2 + 16.0 * v0 * big_t
          + 14.0 * v1 * big_t) / (2.0 * t4)
    c5 = (-12.0 * q0 + 12.0 * q1 - a0 * t2 + a1 * t2 - 6.0 * v0 * big_t
          - 6.0 * v1 * big_t) / (2.0 * t5)
    return TrajectorySample(
        q0 + v0 * t + c2 * t ** 2 + c3 * t ** 3 + c4 * t ** 4 + c5 * t ** 5,
        v0 + 2.0 * c2 * t + 3.0 * c3 * t ** 2 + 4.0 * c4 * t ** 3 + 5.0 * c5 * t ** 4,
        2.0 * c2 + 6.0 * c3 * t + 12.0 * c4 * t ** 2 + 20.0 * c5 * t ** 3, effort)


def _as_int_ns(t_ns) -> int:
    if isinstance(t_ns, bool) or not isinstance(t_ns, (int, np.integer)):
        raise TypeError(f't_ns must be an integer number of nanoseconds, got {t_ns!r}')
    return int(t_ns)
