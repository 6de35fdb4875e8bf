"""A joint trajectory encoded by Gaussian Mixture Regression (reference chapter eq. 2.25).

A Gaussian mixture over u = [s, q] (s = t / duration, the phase in [0, 1]; q the joint angles)
is fitted to a demonstration with EM (the `gmr` package); conditioning on s gives the trajectory

    q(s) = sum_k h_k(s) (mu_q,k + Sigma_qs,k / Sigma_ss,k (s - mu_s,k)),
    h_k(s) = pi_k N(s; mu_s,k, Sigma_ss,k) / sum_j pi_j N(s; mu_s,j, Sigma_ss,j).

The fit fixes the component layout (priors pi_k, phase means mu_s,k and variances Sigma_ss,k,
components sorted by phase); the tunable numbers are, per component and joint, the mean
mu_q,k and the slope Sigma_qs,k / Sigma_ss,k: theta = [means (K, n), slopes (K, n)] flattened,
2 K n numbers, one fixed-size vector per trajectory for CMA-ES and the skill memory. The
conditioning itself is `gmr.GMM.predict` on a mixture rebuilt from theta (the joint
covariance keeps the fitted residual Sigma_q|s, so every rebuilt covariance stays positive
definite). Velocities are the exact derivative of q(s). Imports no ROS.
"""
from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class GMRTrajectorySample:
    t: np.ndarray      # (T,)
    y: np.ndarray      # (T, n)
    yd: np.ndarray     # (T, n)


class GMRTrajectory:
    """q(t) by GMR over [phase, q] with a fixed component layout; theta = means and slopes."""

    def __init__(self, n_dims: int, n_components: int, duration: float):
        if n_dims < 1 or n_components < 1 or not duration > 0.0:
            raise ValueError('GMRTrajectory needs n_dims >= 1, n_components >= 1, duration > 0')
        self.n_dims, self.n_components, self.duration = int(n_dims), int(n_components), duration
        self.priors: np.ndarray | None = None        # (K,)
        self.phase_means: np.ndarray | None = None   # (K,)
        self.phase_vars: np.ndarray | None = None    # (K,)
        self.residual: np.ndarray | None = None      # (K, n, n): Sigma_q|s of the fit
        self.means = np.zeros((n_components, n_dims))
        self.slopes = np.zeros((n_components, n_dims))

    @property
    def num_parameters(self) -> int:
        return 2 * self.n_components * self.n_dims

    def fit(self, t: np.ndarray, y: np.ndarray, seed: int = 0) -> None:
        """EM on the demonstration's samples [t / duration, y] (t (T,), y (T, n))."""
        t, y = np.asarray(t, dtype=float), np.asarray(y, dtype=float)
        if y.ndim != 2 or y.shape != (t.size, self.n_dims):
            raise ValueError(f'fit needs y of shape ({t.size}, {self.n_dims}), got {y.shape}')
        samples = np.column_stack([t / self.duration, y])
        from gmr import GMM     # here, not at import: gmr loads scipy.stats (1 s of a start)
        gmm = GMM(self.n_components, random_state=np.random.RandomState(seed))
        gmm.from_samples(samples, R_diff=1e-6, n_iter=200, init_params='kmeans++')
        order = np.argsort(gmm.means[:, 0])
        priors, means, covs = gmm.priors[order], gmm.means[order], gmm.covariances[order]
        self.priors = priors / priors.sum()
        self.phase_means = means[:, 0].copy()
        self.phase_vars = np.maximum(covs[:, 0, 0], 1e-8)
        cross = covs[:, 1:, 0]                                   # Sigma_qs (K, n)
        self.means = means[:, 1:].copy()
        self.slopes = cross / self.phase_vars[:, None]
        # Sigma_q|s = Sigma_qq - Sigma_qs Sigma_ss^-1 Sigma_sq, kept positive definite
        residual = covs[:, 1:, 1:] - np.einsum('ki,kj->kij', cross, cross) \
            / self.phase_vars[:, None, None]
        eye = np.eye(self.n_dims)
        self.residual = np.array([0.5 * (r + r.T) + 1e-9 * eye for r in residual])

    def _check_fitted(self) -> None:
        if self.priors is None:
            raise RuntimeError('fit the GMR trajectory to a demonstration first')

    def get_theta(self) -> np.ndarray:
        return np.concatenate([self.means.ravel(), self.slopes.ravel()])

    def set_theta(self, theta) -> None:
        theta = np.asarray(theta, dtype=float).ravel()
        if theta.size != self.num_parameters:
            raise ValueError(f'theta needs {self.num_parameters} entries, got {theta.size}')
        half = self.n_components * self.n_dims
        self.means = theta[:half].reshape(self.n_components, self.n_dims).copy()
        self.slopes = theta[half:].reshape(self.n_components, self.n_dims).copy()

    def mixture(self) -> 'GMM':
        """The joint mixture over [s, q] that theta stands for."""
        self._check_fitted()
        k, n = self.n_components, self.n_dims
        cov = np.zeros((k, n + 1, n + 1))
        cross = self.slopes * self.phase_vars[:, None]          # Sigma_qs
        cov[:, 0, 0] = self.phase_vars
        cov[:, 1:, 0] = cov[:, 0, 1:] = cross
        cov[:, 1:, 1:] = self.residual + np.einsum('ki,kj->kij', cross, cross) \
            / self.phase_vars[:, None, None]
        means = np.column_stack([self.phase_means, self.means])
        from gmr import GMM
        return GMM(k, priors=self.priors, means=means, covariances=cov)

    def integrate(self, dt: float, t_end: float | None = None) -> GMRTrajectorySample:
        """q(t) on the grid t = 0, dt, ..., t_end (default: the duration): the conditional mean
        (eq. 2.25) from `gmr`, and its exact time derivative; after the duration the
        trajectory holds q(1) (a settle phase), as a DMP settles at its goal."""
        t_end = self.duration if t_end is None else t_end
        t = np.arange(int(round(t_end / dt)) + 1) * dt
        s = np.minimum(t / self.duration, 1.0)        # after the movement: hold its end
        y = self.mixture().predict(np.array([0]), s[:, None])
        yd = self._velocity(s) / self.duration
        yd[t > self.duration] = 0.0
        return GMRTrajectorySample(t=t, y=y, yd=yd)

    def _velocity(self, s: np.ndarray) -> np.ndarray:
        """d q / d s of the conditional mean: sum_k h_k' m_k(s) + h_k slope_k, with
        h_k' = h_k (g_k - sum_j h_j g_j), g_k = -(s - mu_k) / var_k."""
        d = s[:, None] - self.phase_means[None, :]                          # (T, K)
        log_w = np.log(self.priors)[None, :] - 0.5 * d ** 2 / self.phase_vars \
            - 0.5 * np.log(2 * np.pi * self.phase_vars)
        h = np.exp(log_w - log_w.max(axis=1, keepdims=True))
        h /= h.sum(axis=1, keepdims=True)
        g = -d / self.phase_vars
        dh = h * (g - np.sum(h * g, axis=1, keepdims=True))                  # (T, K)
        local = self.means[None] + self.slopes[None] * d[:, :, None]       # (T, K, n)
        return np.einsum('tk,tkn->tn', dh, local) + h @ self.slopes
