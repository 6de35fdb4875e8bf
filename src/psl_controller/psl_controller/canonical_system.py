"""Canonical system of a DMP: the phase x(t) that drives the forcing term (eq. 2.23-2.24).

Two kinds, as in the thesis text next to eq. 2.24:

* ``"linear"`` (Kulvicius et al. 2012): ``xdot = -1 / duration`` while ``x > 0``, limited to
  non-negative values, so ``x(t) = max(0, 1 - t / duration)``.
* ``"exponential"``: ``xdot = -alpha x / duration``, so ``x(t) = exp(-alpha t / duration)``.

Like dmpbbo's dynamical systems, the class offers both the differential equation (:meth:`rate`)
and its analytical solution (:meth:`phase`), so tests can hold one against the other.
Pure numpy; no ROS.
"""

import numpy as np

KINDS = ('linear', 'exponential')


class CanonicalSystem:
    """Phase variable x in [0, 1] with x(0) = 1, decaying over ``duration`` seconds.

    Args:
        duration: length of the motion in seconds (> 0).
        kind: ``"linear"`` or ``"exponential"``.
        alpha: decay constant of the exponential kind (> 0); ignored by the linear kind.

    Raises:
        ValueError: unknown ``kind``, non-positive or non-finite ``duration`` or ``alpha``.
    """

    def __init__(self, duration: float, kind: str = 'linear', alpha: float = 4.0) -> None:
        if kind not in KINDS:
            raise ValueError(f'unknown canonical system kind {kind!r}; expected one of {KINDS}')
        if not (np.isfinite(duration) and duration > 0.0):
            raise ValueError(f'duration must be finite and > 0, got {duration!r}')
        if not (np.isfinite(alpha) and alpha > 0.0):
            raise ValueError(f'alpha must be finite and > 0, got {alpha!r}')
        self._duration = float(duration)
        self._kind = kind
        self._alpha = float(alpha)

    @property
    def duration(self) -> float:
        return self._duration

    @property
    def kind(self) -> str:
        return self._kind

    @property
    def alpha(self) -> float:
        return self._alpha

    def phase(self, t: np.ndarray) -> np.ndarray:
        """Analytical solution x(t); times before 0 are treated as 0 (x = 1).

        Args:
            t: times in seconds, any shape.

        Returns:
            x with the shape of ``t``.
        """
        tau = np.maximum(np.asarray(t, dtype=float), 0.0) / self._duration
        if self._kind == 'linear':
            return np.maximum(1.0 - tau, 0.0)
        return np.exp(-self._alpha * tau)

    def rate(self, x: np.ndarray) -> np.ndarray:
        """Differential equation xdot(x).

        Linear kind: ``-1 / duration`` for ``x > 0`` and ``0`` for ``x <= 0`` (the phase stops
        at zero). Exponential kind: ``-alpha x / duration``.

        Args:
            x: phase values, any shape.

        Returns:
            xdot with the shape of ``x``.
        """
        x = np.asarray(x, dtype=float)
        if self._kind == 'linear':
            return np.where(x > 0.0, -1.0 / self._duration, 0.0)
        return -self._alpha * x / self._duration

    def gate(self, t: np.ndarray) -> np.ndarray:
        """Factor multiplying the DMP forcing term: 1 at t = 0, exactly 0 for t >= duration.

        Linear kind: the phase itself, ``max(0, 1 - t / duration)``. Exponential kind: the
        phase times that linear decay, ``exp(-alpha t / duration) * max(0, 1 - t / duration)``,
        because the exponential phase alone never reaches zero.

        Args:
            t: times in seconds, any shape (before 0 treated as 0).

        Returns:
            gate values in [0, 1] with the shape of ``t``.
        """
        tau = np.maximum(np.asarray(t, dtype=float), 0.0) / self._duration
        linear_decay = np.maximum(1.0 - tau, 0.0)
        if self._kind == 'linear':
            return linear_decay
        return np.exp(-self._alpha * tau) * linear_decay
