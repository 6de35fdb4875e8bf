"""The solved task instances a baseline tau -> theta map keeps: samples (tau_i, theta_i) added
in order, all-or-none, with the checks both baselines (`nearest_neighbour_library`,
`gaussian_process_map`) share. A map derives from `SolvedInstances` and refits in `_changed`.
Pure numpy, imports no ROS.
"""
from __future__ import annotations

import numpy as np


class SolvedInstances:
    """Samples taus (N, E) and thetas (N, F), in the order they were added.

    Args:
        tau_dim: E (>= 1).
        default_theta: theta while there are no samples (F,), e.g. the task's default policy.

    Raises:
        ValueError: a default theta that is empty or not finite.
    """

    def __init__(self, tau_dim: int, default_theta):
        self.default_theta = finite_vector(default_theta, None, 'default theta')
        self._taus = np.empty((0, int(tau_dim)))            # (N, E)
        self._thetas = np.empty((0, self.theta_dim))        # (N, F)

    @property
    def tau_dim(self) -> int:
        return self._taus.shape[1]

    @property
    def theta_dim(self) -> int:
        return self.default_theta.size

    @property
    def num_samples(self) -> int:
        return len(self._taus)

    @property
    def taus(self) -> np.ndarray:
        """The stored task parameters (N, E), in the order they were added."""
        return self._taus.copy()

    @property
    def thetas(self) -> np.ndarray:
        """The stored policy parameters (N, F)."""
        return self._thetas.copy()

    def add(self, tau, theta) -> int:
        """Store one solved instance; returns the number of samples. Raises ValueError (and
        stores nothing) for a tau or theta of the wrong size or with NaN or inf."""
        return self.extend(np.atleast_2d(tau), np.atleast_2d(theta))

    def extend(self, taus, thetas) -> int:
        """Store solved instances taus (n, E), thetas (n, F) in this order (all or none),
        then let the map refit once (`_changed`)."""
        taus, thetas = check_samples(taus, thetas, self.tau_dim, self.theta_dim)
        self._taus = np.vstack([self._taus, taus])
        self._thetas = np.vstack([self._thetas, thetas])
        self._changed()
        return self.num_samples

    def _changed(self) -> None:
        """Called after samples were added (a map that fits overrides it)."""


def check_samples(taus, thetas, tau_dim: int, theta_dim: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """taus (n, E) and thetas (n, F) as float arrays, or ValueError: a row of the wrong size,
    NaN or inf, or unequal counts."""
    taus = np.array([finite_vector(t, tau_dim, 'tau') for t in np.atleast_2d(taus)])
    thetas = np.array([finite_vector(t, theta_dim, 'theta') for t in np.atleast_2d(thetas)])
    if len(taus) != len(thetas):
        raise ValueError(f'{len(taus)} taus but {len(thetas)} thetas')
    return taus.reshape(-1, tau_dim), thetas.reshape(-1, theta_dim)


def finite_vector(value, size: int | None, name: str) -> np.ndarray:
    """value as a float vector of `size` entries (any non-zero size for None), or ValueError."""
    array = np.asarray(value, dtype=float)
    if array.ndim != 1 or array.size == 0 or (size is not None and array.size != size):
        raise ValueError(f'{name} must be a vector of {size or "some"} entries, got shape '
                         f'{array.shape}')
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{name} contains NaN or inf')
    return array
