"""Feed-forward torque signal of the dynamics modality, on the DMP's own basis (section 2.2).

Per joint j::

    u_ffwd_j(t) = sum_k psi_k(x(t)) theta_D[j, k] / sum_k psi_k(x(t))

with the same normalised Gaussians ``psi_k`` (eq. 2.24) on the same canonical phase ``x(t)``
as the DMP's forcing term, but **ungated**: after the motion the phase rests at 0 and the
signal holds the value of the last basis functions, so a held payload stays compensated while
the episode settles. Linear in theta_D, so an arbitrary torque profile is projected onto it by
least squares (`FeedForward.fit`, used for the inverse-dynamics oracle). Given the arm's torque
limits, the signal is clipped into them: the PD law clips the total torque anyway, and every
controller psl serves rejects a goal whose effort passes them (`psl_task.joint_limits`), so a
candidate whose theta_D asks more runs with the most the motors give instead of being refused.
Pure numpy; no ROS.
"""
from __future__ import annotations

import numpy as np

from psl_controller.basis_functions import NormalizedGaussianBasis
from psl_controller.canonical_system import CanonicalSystem


class FeedForward:
    """theta_D (n_joints * n_basis,), row-major over (n_joints, n_basis) -> u_ffwd(t).

    Args:
        canonical: the DMP's canonical system (phase x(t)).
        basis: the DMP's normalised Gaussian basis on the phase.
        n_joints: number of joints (>= 1).
        torque_low, torque_high: (n_joints,) N m, the arm's torque limits the signal is
            clipped into (module docstring); None: not clipped.

    Raises:
        ValueError: n_joints < 1, torque limits of another size or low > high.
    """

    def __init__(self, canonical: CanonicalSystem, basis: NormalizedGaussianBasis,
                 n_joints: int, torque_low: np.ndarray | None = None,
                 torque_high: np.ndarray | None = None) -> None:
        if int(n_joints) != n_joints or n_joints < 1:
            raise ValueError(f'n_joints must be an integer >= 1, got {n_joints!r}')
        self._canonical, self._basis, self._n_joints = canonical, basis, int(n_joints)
        self._low = None if torque_low is None else np.asarray(torque_low, dtype=float)
        self._high = None if torque_high is None else np.asarray(torque_high, dtype=float)
        for bound in (self._low, self._high):
            if bound is not None and bound.shape != (self._n_joints,):
                raise ValueError(f'torque limits must have {self._n_joints} entries, got '
                                 f'{bound.shape}')
        if self._low is not None and self._high is not None and np.any(self._low > self._high):
            raise ValueError(f'torque_low {self._low} above torque_high {self._high}')

    @property
    def n_joints(self) -> int:
        return self._n_joints

    @property
    def n_basis(self) -> int:
        return self._basis.n_basis

    @property
    def num_parameters(self) -> int:
        return self._n_joints * self._basis.n_basis

    def design(self, t: np.ndarray) -> np.ndarray:
        """Basis activations psi_k(x(t)) / sum_j psi_j(x(t)), shape (T, K) for t of shape (T,)."""
        t = np.atleast_1d(np.asarray(t, dtype=float)).reshape(-1)
        return self._basis.activations(self._canonical.phase(t))

    def signal(self, theta_d: np.ndarray, t: np.ndarray) -> np.ndarray:
        """u_ffwd(t), shape (T, n_joints).

        Raises:
            ValueError: theta_d of the wrong size or not finite.
        """
        return self._clipped(self.design(t) @ self._weights(theta_d).T)

    def _clipped(self, u: np.ndarray) -> np.ndarray:
        """u (..., n_joints) clipped into the torque limits, if any (the same array when
        every value is inside: bit-identical)."""
        if self._low is None and self._high is None:
            return u
        return np.clip(u, self._low, self._high, out=u)

    def signal_population(self, theta_ds: np.ndarray, t: np.ndarray) -> np.ndarray:
        """`signal` of each row of theta_ds (B, num_parameters) within rounding (one product
        of another shape: BLAS may sum it in another order, by CPU): (B, T, n_joints).

        Raises:
            ValueError: theta_ds of the wrong shape or not finite.
        """
        theta_ds = np.asarray(theta_ds, dtype=float)
        if theta_ds.ndim != 2:
            raise ValueError(f'theta_ds must be (B, {self.num_parameters}), got {theta_ds.shape}')
        weights = np.stack([self._weights(theta_d) for theta_d in theta_ds])   # (B, n, K)
        signal = self.design(t) @ weights.reshape(-1, self.n_basis).T        # (T, B n)
        return self._clipped(np.ascontiguousarray(
            signal.reshape(len(signal), len(theta_ds), self._n_joints).transpose(1, 0, 2)))

    def fit(self, t: np.ndarray, u: np.ndarray, regularization: float = 1e-9) -> np.ndarray:
        """Least-squares projection of torques u (T, n_joints) sampled at t (T,) onto the basis:
        ``min ||Phi theta_j - u_j||^2 + regularization ||theta_j||^2`` per joint.

        Returns:
            theta_D, flat (n_joints * n_basis,).

        Raises:
            ValueError: shapes that do not match, non-finite values, negative regularization.
        """
        phi = self.design(t)                                           # (T, K)
        u = np.asarray(u, dtype=float)
        if u.shape != (len(phi), self._n_joints):
            raise ValueError(f'u must have shape ({len(phi)}, {self._n_joints}), got {u.shape}')
        if not np.all(np.isfinite(u)):
            raise ValueError('u must be finite')
        if not (np.isfinite(regularization) and regularization >= 0.0):
            raise ValueError(f'regularization must be finite and >= 0, got {regularization!r}')
        k = self.n_basis
        design = np.vstack([phi, np.sqrt(regularization) * np.eye(k)])   # (T+K, K)
        rhs = np.vstack([u, np.zeros((k, self._n_joints))])              # (T+K, n_joints)
        weights, *_ = np.linalg.lstsq(design, rhs, rcond=None)           # (K, n_joints)
        return weights.T.reshape(-1).copy()

    def _weights(self, theta_d: np.ndarray) -> np.ndarray:
        theta_d = np.asarray(theta_d, dtype=float)
        if theta_d.size != self.num_parameters:
            raise ValueError(f'theta_D must have {self.num_parameters} = n_joints * n_basis '
                             f'entries, got {theta_d.size}')
        if not np.all(np.isfinite(theta_d)):
            raise ValueError('theta_D must be finite (found NaN or inf)')
        return theta_d.reshape(self._n_joints, self.n_basis)          # (n_joints, K)
