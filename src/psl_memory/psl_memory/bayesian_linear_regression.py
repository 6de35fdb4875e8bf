"""Bayesian linear regression readout with predictive variance (eq. 2.12-2.14).

Every output i has weights ``w_i`` (column i of W, (N_H,)) with the isotropic zero-mean prior
``N(0, alpha^{-1} I)`` and Gaussian noise of precision beta, alpha and beta shared by all outputs.
The posterior (eq. 2.12, Bishop 2006 eq. 3.53-3.54) is ``N(w_i | m_i, S_N)`` with

    S_N^{-1} = alpha I + beta H^T H,        M = [m_1 ... m_F] = beta S_N H^T Y      (N_H, F)

so M is the ridge solution (eq. 2.8) with regulariser alpha / beta. The predictive distribution
of output i (eq. 2.13-2.14) has mean ``m_i^T h`` and variance ``1/beta + h^T S_N h``, the same for
every output.

Only sufficient statistics are kept (H^T H, H^T Y, sum of squared targets, N): an update costs
O(n N_H^2 + N_H^2 F + N_H^3), independent of the number of samples seen. ``S_N`` is held as the
Cholesky factor of ``S_N^{-1}``; no inverse is formed.

With ``estimate=True``, alpha and beta are re-estimated after each update by evidence
maximisation (Bishop 2006, section 3.5.2, eq. 3.91-3.95, here for F outputs with shared alpha
and beta), iterated from the current values until the relative change of both is below
`tolerance` or `max_iterations` is reached:

    lambda_i = eigenvalues of beta H^T H
    gamma    = sum_i lambda_i / (alpha + lambda_i)           effective number of parameters
    alpha    = F gamma / ||M||_F^2
    beta     = (N F - F gamma) / sum_n ||y_n - M^T h_n||^2

where the residual sum is ``sum y^2 - 2 tr(M^T H^T Y) + tr(M^T H^T H M)``, evaluated from the
sufficient statistics. When there are too few samples (N < 2), the targets are all zero, the
residuals vanish to rounding precision, or an iterate leaves [`PRECISION_MIN`, `PRECISION_MAX`],
the previous alpha and beta are kept.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy.linalg import cho_solve, cholesky, eigh, solve_triangular

from psl_memory.readout import (Readout, State, check_positive, state_array, state_bool,
                                state_count, state_positive)

PRECISION_MIN = 1e-12      # estimated alpha and beta stay within [PRECISION_MIN, PRECISION_MAX]
PRECISION_MAX = 1e12
EVIDENCE_MIN_SAMPLES = 2   # fewer samples leave no degree of freedom for the noise estimate


class BayesianLinearRegression(Readout):
    """Bayesian linear regression readout (eq. 2.12-2.14), optional evidence maximisation.

    Args:
        n_hidden: hidden states N_H.
        n_out: outputs F.
        prior_precision: alpha (> 0); the initial value when `estimate` is True.
        noise_precision: beta = 1 / sigma^2 (> 0); the initial value when `estimate` is True.
        estimate: re-estimate alpha and beta by evidence maximisation after every update.
        tolerance: relative change of alpha and beta that ends the evidence iteration.
        max_iterations: cap on evidence iterations per update (the last iterate is kept).
    """

    name = 'bayes'

    def __init__(self, n_hidden: int, n_out: int, prior_precision: float = 1e-6,
                 noise_precision: float = 1.0, estimate: bool = False, *,
                 tolerance: float = 1e-6, max_iterations: int = 100):
        super().__init__(n_hidden, n_out)
        self.alpha = check_positive('prior_precision', prior_precision)     # alpha of eq. 2.12
        self.beta = check_positive('noise_precision', noise_precision)      # beta of eq. 2.12
        if not isinstance(estimate, (bool, np.bool_)):
            raise ValueError(f'estimate must be a bool, got {estimate!r}')
        self.estimate = bool(estimate)
        self.tolerance = check_positive('tolerance', tolerance)
        if isinstance(max_iterations, bool) or not isinstance(max_iterations, (int, np.integer)) \
                or max_iterations < 1:
            raise ValueError(f'max_iterations must be an integer >= 1, got {max_iterations!r}')
        self.max_iterations = int(max_iterations)
        self._hth = np.zeros((self.n_hidden, self.n_hidden))    # (N_H, N_H) H^T H
        self._hty = np.zeros((self.n_hidden, self.n_out))       # (N_H, F) H^T Y
        self._yty = 0.0                                          # sum of squared targets
        self._w, self._chol = posterior(self._hth, self._hty, self.alpha, self.beta)

    @classmethod
    def from_config(cls, n_hidden: int, n_out: int, config) -> 'BayesianLinearRegression':
        """The readout a `SkillConfig` asks for: prior precision = its regularization."""
        return cls(n_hidden, n_out, prior_precision=config.regularization,
                   noise_precision=config.noise_precision, estimate=config.estimate_precisions)

    def predict_variance(self, h: np.ndarray) -> np.ndarray:
        """Predictive variance 1/beta + h^T S_N h (eq. 2.14): (F,) for h (N_H,), (n, F) for
        h (n, N_H); equal for all outputs."""
        hs, single = self._check_inputs(h)                                  # (n, N_H)
        v = solve_triangular(self._chol, hs.T, lower=True)                  # (N_H, n) C^{-1} h
        var = 1.0 / self.beta + np.sum(v * v, axis=0)                       # (n,) h^T S_N h
        out = np.repeat(var[:, None], self.n_out, axis=1)                   # (n, F)
        return out[0] if single else out

    def _compute_update(self, hs: np.ndarray, ys: np.ndarray) -> dict[str, Any]:
        hth = self._hth + hs.T @ hs                 # (N_H, N_H)
        hty = self._hty + hs.T @ ys                 # (N_H, F)
        yty = self._yty + float(np.sum(ys * ys))
        n = self._n + hs.shape[0]
        alpha, beta = self.alpha, self.beta
        if self.estimate:
            alpha, beta = evidence_maximisation(hth, hty, yty, n, alpha, beta,
                                                self.tolerance, self.max_iterations)
        w, chol = posterior(hth, hty, alpha, beta)
        return {'_hth': hth, '_hty': hty, '_yty': yty, '_n': n, 'alpha': alpha, 'beta': beta,
                '_w': w, '_chol': chol}

    def get_state(self) -> State:
        return {**self._header(), 'alpha': self.alpha, 'beta': self.beta,
                'estimate': self.estimate, 'tolerance': self.tolerance,
                'max_iterations': self.max_iterations, 'hth': self._hth.copy(),
                'hty': self._hty.copy(), 'yty': self._yty}

    def _parse_state(self, state: State) -> dict[str, Any]:
        hth = state_array(state, 'hth', (self.n_hidden, self.n_hidden))
        hty = state_array(state, 'hty', (self.n_hidden, self.n_out))
        yty = float(state_array(state, 'yty', ()))
        if yty < 0.0:
            raise ValueError(f'state yty must be >= 0, got {yty}')
        alpha, beta = state_positive(state, 'alpha'), state_positive(state, 'beta')
        w, chol = posterior(hth, hty, alpha, beta)
        return {'_hth': hth, '_hty': hty, '_yty': yty, '_n': state_count(state, 'num_samples'),
                'alpha': alpha, 'beta': beta, 'estimate': state_bool(state, 'estimate'),
                'tolerance': state_positive(state, 'tolerance'),
                'max_iterations': state_count(state, 'max_iterations', minimum=1),
                '_w': w, '_chol': chol}


def posterior(hth: np.ndarray, hty: np.ndarray, alpha: float,
              beta: float) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mean M (N_H, F) and lower Cholesky factor C of S_N^{-1} = C C^T (eq. 2.12).

    Args:
        hth: H^T H, (N_H, N_H).
        hty: H^T Y, (N_H, F).
        alpha: prior precision.
        beta: noise precision.
    """
    s_inv = alpha * np.eye(hth.shape[0]) + beta * hth              # (N_H, N_H) S_N^{-1}
    chol = cholesky(s_inv, lower=True)                               # (N_H, N_H)
    mean = beta * cho_solve((chol, True), hty)                       # (N_H, F) beta S_N H^T Y
    return mean, chol


def evidence_maximisation(hth: np.ndarray, hty: np.ndarray, yty: float, n: int, alpha: float,
                          beta: float, tolerance: float,
                          max_iterations: int) -> tuple[float, float]:
    """Alpha and beta maximising the evidence (Bishop 2006, eq. 3.91-3.95, F outputs).

    Iterates the re-estimation equations from (alpha, beta) until the relative change of both is
    below `tolerance`, at most `max_iterations` times, and returns the last iterate. Returns the
    given (alpha, beta) unchanged when the data cannot support an estimate (see module doc).

    Args:
        hth: H^T H, (N_H, N_H).
        hty: H^T Y, (N_H, F).
        yty: sum of squared targets.
        n: number of samples N.
        alpha, beta: current prior and noise precisions, the starting point.
        tolerance: relative change that counts as converged.
        max_iterations: iteration cap.
    """
    if n < EVIDENCE_MIN_SAMPLES:
        return alpha, beta
    n_out = hty.shape[1]
    eig, q = eigh(hth)                                  # (N_H,), (N_H, N_H) H^T H = Q E Q^T
    eig = np.clip(eig, 0.0, None)                       # H^T H is PSD; drop rounding negatives
    proj = q.T @ hty                                    # (N_H, F) Q^T H^T Y
    ssr_floor = 1e3 * np.finfo(float).eps * yty         # below that, cancellation dominates
    a, b = alpha, beta
    for _ in range(max_iterations):
        lam = b * eig                                   # (N_H,) eigenvalues of beta H^T H
        gamma = float(np.sum(lam / (a + lam)))
        coef = b / (a + lam)                            # (N_H,) M = Q diag(coef) Q^T H^T Y
        m_rot = coef[:, None] * proj                    # (N_H, F) Q^T M
        m_norm2 = float(np.sum(m_rot * m_rot))          # ||M||_F^2
        # sum ||y - M^T h||^2 = sum y^2 - 2 tr(M^T H^T Y) + tr(M^T H^T H M)
        ssr = yty - 2.0 * float(np.sum(m_rot * proj)) + float(np.sum(eig[:, None] * m_rot**2))
        dof = n * n_out - n_out * gamma                 # N F - F gamma
        if m_norm2 <= 0.0 or ssr <= ssr_floor or dof <= 0.0:
            return alpha, beta
        a_new, b_new = n_out * gamma / m_norm2, dof / ssr
        if not all(PRECISION_MIN <= v <= PRECISION_MAX for v in (a_new, b_new)):
            return alpha, beta
        converged = abs(a_new - a) <= tolerance * a and abs(b_new - b) <= tolerance * b
        a, b = a_new, b_new
        if converged:
            break
    return a, b
