"""A library of solved task instances: theta of the k nearest stored taus, inverse-distance
weighted — the 'library based approach' a parameterized skill is compared with.

With samples (tau_i, theta_i), i = 1..N, a query tau takes the k nearest taus (distance in tau
normalised by the task's tau range, so every task parameter counts alike):

    d_i = || (tau - tau_i) / (tau_high - tau_low) ||_2
    theta(tau) = sum_i w_i theta_i / sum_i w_i,   w_i = d_i ** -power   (Shepard 1968)

over those k (all N if N < k; ties by insertion order). An exact hit (d_i = 0) returns that
theta (the mean of several equal taus); an empty library returns the default theta given at
construction. The library has no predictive variance. Pure numpy, imports no ROS.

References
----------
Shepard, D. (1968). A two-dimensional interpolation function for irregularly-spaced data.
Proceedings of the 23rd ACM National Conference, 517-524. doi:10.1145/800186.810616
"""
from __future__ import annotations

import numpy as np

EXACT = 1e-12        # a normalised distance this small is an exact hit


class NearestNeighbourLibrary:
    """tau -> theta by inverse-distance weighting of the k nearest solved instances.

    Args:
        tau_low, tau_high: the task's tau ranges (E,), high > low.
        default_theta: theta of an empty library (F,), e.g. the task's default policy.
        k: neighbours weighted per query (>= 1).
        power: exponent of the inverse distance (> 0).

    Raises:
        ValueError: bad ranges, default theta, k or power.
    """

    name = 'library'
    has_variance = False   # variance(tau) is None

    def __init__(self, tau_low, tau_high, default_theta, k: int = 3, power: float = 1.0):
        self.tau_low = np.asarray(tau_low, dtype=float)
        self.tau_high = np.asarray(tau_high, dtype=float)
        if (self.tau_low.ndim != 1 or self.tau_low.shape != self.tau_high.shape
                or self.tau_low.size == 0 or not np.all(self.tau_high > self.tau_low)):
            raise ValueError('tau ranges need one low < high per task parameter')
        self.default_theta = finite_vector(default_theta, None, 'default theta')
        if int(k) < 1 or not power > 0.0:
            raise ValueError(f'need k >= 1 and power > 0, got k={k}, power={power}')
        self.k, self.power = int(k), float(power)
        self._taus = np.empty((0, self.tau_dim))           # (N, E)
        self._thetas = np.empty((0, self.theta_dim))       # (N, F)

    @property
    def tau_dim(self) -> int:
        return self.tau_low.size

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
        """Store solved instances taus (n, E), thetas (n, F) in this order; all or none."""
        taus, thetas = check_samples(taus, thetas, self.tau_dim, self.theta_dim)
        self._taus = np.vstack([self._taus, taus])
        self._thetas = np.vstack([self._thetas, thetas])
        return self.num_samples

    def distances(self, tau) -> np.ndarray:
        """Range-normalised distances (N,) of tau to every stored tau."""
        tau = finite_vector(tau, self.tau_dim, 'tau')
        return np.linalg.norm((self._taus - tau) / (self.tau_high - self.tau_low), axis=1)

    def query(self, tau) -> np.ndarray:
        """theta(tau) (F,): see the module docstring."""
        d = self.distances(tau)
        if d.size == 0:
            return self.default_theta.copy()
        hits = d <= EXACT
        if np.any(hits):
            return self._thetas[hits].mean(axis=0)
        nearest = np.argsort(d, kind='stable')[:self.k]
        w = d[nearest] ** -self.power
        return w @ self._thetas[nearest] / w.sum()

    def variance(self, tau) -> None:
        """A library has no predictive variance (variance-driven task selection refuses it)."""
        finite_vector(tau, self.tau_dim, 'tau')
        return None


def check_samples(taus, thetas, tau_dim: int, theta_dim: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """taus (n, E) and thetas (n, F) as float arrays, or ValueError: a row of the wrong size,
    NaN or inf, or unequal counts. (Shared with `gaussian_process_map`.)"""
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
