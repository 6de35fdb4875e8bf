"""Sampling of a joint trajectory in time, in the spirit of ros2_controllers'
joint_trajectory_controller (JTC), kept apart from the controller. Pure numpy; no ROS.

Times are integer nanoseconds from the trajectory start (``time_from_start``), so comparisons
with the points' times are exact. Edge cases, for a query time ``t`` and point times
``t_0 < t_1 < ... < t_{N-1}``:

* empty trajectory: rejected at construction (``ValueError``).
* ``t < t_0`` (before the first point): position of the first point, **zero** velocity and the
  first point's effort (held as feed-forward). JTC instead interpolates from the state at the
  trajectory's arrival to the first point; we keep it simple and hold the first point.
* ``t == t_i`` (exactly on a point): that point's position, velocity and effort, bit for bit.
* ``t_i < t < t_{i+1}`` (between points): linear interpolation of position, velocity and effort
  with ``s = (t - t_i) / (t_{i+1} - t_i)``. (JTC uses cubic / quintic splines when velocities /
  accelerations are given; linear interpolation is our deliberate simplification.)
* ``t > t_{N-1}`` (past the end): last position, **zero** velocity, last effort.
* single-point trajectory: the rules above with ``t_0 = t_{N-1}``.

Effort is meant to be added to the PD output as feed-forward (see :mod:`pd_law`).
"""

import numpy as np


def _point_array(value, shape: tuple[int, int], name: str) -> np.ndarray:
    if value is None:
        return np.zeros(shape)
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
        velocities: shape (N, n), or None for zeros.
        efforts: shape (N, n), or None for zeros.

    Raises:
        ValueError: empty trajectory, non-integer or non-increasing or negative times,
            mismatched shapes, non-finite values.
    """

    def __init__(self, times_ns: np.ndarray, positions: np.ndarray,
                 velocities: np.ndarray | None = None,
                 efforts: np.ndarray | None = None) -> None:
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
        self._times_ns = times_ns  # (N,)
        self._positions = _point_array(positions, shape, 'positions')  # (N, n)
        self._velocities = _point_array(velocities, shape, 'velocities')  # (N, n)
        self._efforts = _point_array(efforts, shape, 'efforts')  # (N, n)

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

    def is_finished(self, t_ns: int) -> bool:
        """True once ``t_ns`` has reached the last point's time (``t_ns >= duration_ns``)."""
        return _as_int_ns(t_ns) >= self.duration_ns

    def sample(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Reference at ``t_ns`` nanoseconds from the trajectory start (module docstring rules).

        Returns:
            (q, qd, u_ffwd), each a new array of shape (n,).

        Raises:
            TypeError: ``t_ns`` is not an integer.
        """
        t_ns = _as_int_ns(t_ns)
        times = self._times_ns
        if t_ns < times[0]:
            return self._positions[0].copy(), np.zeros(self.n_joints), self._efforts[0].copy()
        if t_ns > times[-1]:
            return self._positions[-1].copy(), np.zeros(self.n_joints), self._efforts[-1].copy()
        # times[i - 1] < t_ns <= times[i]
        i = int(np.searchsorted(times, t_ns, side='left'))
        if times[i] == t_ns:
            return self._positions[i].copy(), self._velocities[i].copy(), self._efforts[i].copy()
        t_prev, t_next = int(times[i - 1]), int(times[i])
        s = (t_ns - t_prev) / (t_next - t_prev)  # in (0, 1)
        return (_lerp(self._positions[i - 1], self._positions[i], s),
                _lerp(self._velocities[i - 1], self._velocities[i], s),
                _lerp(self._efforts[i - 1], self._efforts[i], s))


def _lerp(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    return a + s * (b - a)


def _as_int_ns(t_ns) -> int:
    if isinstance(t_ns, bool) or not isinstance(t_ns, (int, np.integer)):
        raise TypeError(f't_ns must be an integer number of nanoseconds, got {t_ns!r}')
    return int(t_ns)
