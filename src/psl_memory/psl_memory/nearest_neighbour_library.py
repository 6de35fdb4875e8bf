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

from psl_memory.solved_instances import SolvedInstances, finite_vector

EXACT = 1e-12        # a normalised distance this small is an exact hit


class NearestNeighbourLibrary(SolvedInstances):
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
        super().__init__(self.tau_low.size, default_theta)
        if int(k) < 1 or not power > 0.0:
            raise ValueError(f'need k >= 1 and power > 0, got k={k}, power={power}')
        self.k, self.power = int(k), float(power)

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

