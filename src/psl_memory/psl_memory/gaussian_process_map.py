"""Gaussian-process regression as the tau -> theta map: a baseline beside the skill memory.

scikit-learn's `GaussianProcessRegressor` (Rasmussen & Williams 2006, alg. 2.1) on

    x = tau normalised from the task's tau range to [-1, 1]                      (E,)
    y = (theta - default_theta) / s                                              (F,)

with s the one common spread the skill memory normalises theta with (`scaler_around`: all
entries of theta share their units), so the prior mean is the default theta (an empty or
untrained GP predicts the default, like the ELM skill). Standardising each dimension by its
own spread instead (RMS around the default) made the learner slower on reach_over_obstacle
(78 against 62 rollouts over 30 tasks, 5 seeds; docs/benchmarks.md), presumably because it
raises the dimensions that hardly move to the size of those that carry the task. Kernel:
``ConstantKernel * RBF(one length scale per task parameter) + WhiteKernel``, shared by the F
outputs; its hyper-parameters are fitted by maximising the log marginal likelihood after every
add (few samples: cheap), always from the same initial values and with a fixed random state,
so the map is a function of its samples in their order: a map rebuilt from saved samples
(`extend`) predicts bit for bit what the original did.

`variance(tau)` is the GP's predictive variance (with the white noise) in theta's units,
per dimension (s^2 times the GP's, the same for every dimension); empty: the prior's,
(`AMPLITUDE0` + `NOISE0`) s^2.
scikit-learn is imported at the first fit, not with this module (it takes most of a second).
Imports no ROS.

References
----------
Rasmussen, C. E., & Williams, C. K. I. (2006). Gaussian Processes for Machine Learning.
MIT Press. ISBN 0-262-18253-X.
"""
from __future__ import annotations

import warnings

import numpy as np

from psl_memory.elm import RangeScaler
from psl_memory.parameterized_skill import scaler_around
from psl_memory.solved_instances import SolvedInstances, finite_vector

# initial kernel hyper-parameters and their bounds (inputs in [-1, 1], outputs in units of s)
AMPLITUDE0, AMPLITUDE_BOUNDS = 1.0, (1e-2, 1e2)
LENGTH_SCALE0, LENGTH_SCALE_BOUNDS = 0.5, (1e-2, 1e2)
NOISE0, NOISE_BOUNDS = 1e-2, (1e-6, 1e1)


class GaussianProcessMap(SolvedInstances):
    """tau -> theta by GP regression with the default theta as prior mean.

    Args:
        tau_low, tau_high: the task's tau ranges (E,).
        default_theta: the prior mean of theta (F,), e.g. the task's default policy.
        random_state: seed of the optimiser's restarts (fixed: the map is deterministic).
        n_restarts: restarts of the hyper-parameter optimiser from random initial values.

    Raises:
        ValueError: bad ranges or default theta.
    """

    name = 'gp'
    has_variance = True

    def __init__(self, tau_low, tau_high, default_theta, random_state: int = 0,
                 n_restarts: int = 2):
        self.tau_scaler = RangeScaler(tau_low, tau_high)
        super().__init__(self.tau_scaler.dim, default_theta)
        theta_scaler = scaler_around(self.default_theta)
        self.spread = float(0.5 * (theta_scaler.high[0] - theta_scaler.low[0]))   # s
        self.random_state, self.n_restarts = int(random_state), int(n_restarts)
        self._gp = None                                    # fitted regressor, None: empty

    @property
    def kernel(self):
        """The fitted kernel (None while empty)."""
        return None if self._gp is None else self._gp.kernel_

    def _changed(self) -> None:
        self._fit()

    def _fit(self) -> None:
        from sklearn.exceptions import ConvergenceWarning
        from sklearn.gaussian_process import GaussianProcessRegressor
        from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

        y = (self._thetas - self.default_theta) / self.spread            # (N, F)
        kernel = (ConstantKernel(AMPLITUDE0, AMPLITUDE_BOUNDS)
                  * RBF(np.full(self.tau_dim, LENGTH_SCALE0), LENGTH_SCALE_BOUNDS)
                  + WhiteKernel(NOISE0, NOISE_BOUNDS))
        gp = GaussianProcessRegressor(kernel, normalize_y=False,
                                      n_restarts_optimizer=self.n_restarts,
                                      random_state=self.random_state)
        with warnings.catch_warnings():      # a bound reached with few samples is expected
            warnings.simplefilter('ignore', ConvergenceWarning)
            gp.fit(self.tau_scaler.to_unit(self._taus), y)
        self._gp = gp

    def _predict(self, tau) -> tuple[np.ndarray, np.ndarray]:
        x = self.tau_scaler.to_unit(finite_vector(tau, self.tau_dim, 'tau'))[None]
        mean, std = self._gp.predict(x, return_std=True)
        return mean.reshape(-1), np.broadcast_to(np.reshape(std, (-1,)), (self.theta_dim,))

    def query(self, tau) -> np.ndarray:
        """The posterior mean of theta at tau (F,); the default theta while empty."""
        if self._gp is None:
            finite_vector(tau, self.tau_dim, 'tau')
            return self.default_theta.copy()
        mean, _ = self._predict(tau)
        return self.default_theta + self.spread * mean

    def variance(self, tau) -> np.ndarray:
        """The predictive variance of theta at tau, per dimension (F,), in theta's units."""
        if self._gp is None:
            finite_vector(tau, self.tau_dim, 'tau')
            return np.full(self.theta_dim, (AMPLITUDE0 + NOISE0) * self.spread ** 2)
        _, std = self._predict(tau)
        return (self.spread * std) ** 2
