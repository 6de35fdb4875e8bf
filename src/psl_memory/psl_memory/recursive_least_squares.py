"""Recursive least squares readout with exponential forgetting (eq. 2.5-2.6).

Per sample (h (N_H,), y (F,)), with forgetting factor ``0 < lam <= 1``:

    k      = P h / (lam + h^T P h)                 Kalman gain, eq. 2.5
    W     <- W + k (y - W^T h)^T                   innovation y - W^T h, eq. 2.5
    P     <- (P - k h^T P) / lam                   eq. 2.6

With ``P(0) = I / g`` this is exact: ``P(N)^{-1} = lam^N g I + sum_i lam^(N-i) h_i h_i^T`` and
``W(N)`` minimises ``sum_i lam^(N-i) ||y_i - W^T h_i||^2 + lam^N g ||W||^2``; for ``lam = 1`` that
is the ridge solution of eq. 2.8. Each sample costs O(N_H^2 + N_H F), independent of N; a chunk
is processed sample by sample. With ``lam < 1`` the matrix P grows in directions the data do not
excite (covariance wind-up), as for any exponentially forgetting RLS.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from psl_memory.readout import (Readout, State, check_positive, state_array, state_count,
                                state_positive)


class RecursiveLeastSquares(Readout):
    """RLS readout (eq. 2.5-2.6).

    Args:
        n_hidden: hidden states N_H.
        n_out: outputs F.
        forgetting: lam in (0, 1]; 1 keeps all samples with equal weight.
        regularization: g > 0, giving P(0) = I / g.
    """

    name = 'rls'

    @classmethod
    def from_config(cls, n_hidden: int, n_out: int, config) -> 'RecursiveLeastSquares':
        """The readout a `SkillConfig` asks for."""
        return cls(n_hidden, n_out, forgetting=config.forgetting,
                   regularization=config.regularization)

    def __init__(self, n_hidden: int, n_out: int, forgetting: float = 1.0,
                 regularization: float = 1e-6):
        super().__init__(n_hidden, n_out)
        self.forgetting = _check_forgetting(forgetting)
        self.regularization = check_positive('regularization', regularization)
        self._p = np.eye(self.n_hidden) / self.regularization   # (N_H, N_H) P(0) = I / g

    def _compute_update(self, hs: np.ndarray, ys: np.ndarray) -> dict[str, Any]:
        lam = self.forgetting
        w, p = self._w.copy(), self._p.copy()                # (N_H, F), (N_H, N_H)
        for h, y in zip(hs, ys):                             # h (N_H,), y (F,)
            ph = p @ h                                       # (N_H,) P(k) h
            gain = ph / (lam + h @ ph)                       # (N_H,) Kalman gain, eq. 2.5
            w += np.outer(gain, y - h @ w)                   # (N_H, F) eq. 2.5
            p -= np.outer(gain, ph)                          # P - k h^T P (P symmetric)
            p = 0.5 * (p + p.T) / lam                        # eq. 2.6, kept symmetric
        return {'_w': w, '_p': p, '_n': self._n + hs.shape[0]}

    def get_state(self) -> State:
        return {**self._header(), 'forgetting': self.forgetting,
                'regularization': self.regularization,
                'weights': self._w.copy(), 'p': self._p.copy()}

    def _parse_state(self, state: State) -> dict[str, Any]:
        shape_p = (self.n_hidden, self.n_hidden)
        return {'forgetting': _check_forgetting(state_positive(state, 'forgetting')),
                'regularization': state_positive(state, 'regularization'),
                '_n': state_count(state, 'num_samples'),
                '_w': state_array(state, 'weights', (self.n_hidden, self.n_out)),
                '_p': state_array(state, 'p', shape_p)}


def _check_forgetting(forgetting: float) -> float:
    forgetting = check_positive('forgetting', forgetting)
    if forgetting > 1.0:
        raise ValueError(f'forgetting must be in (0, 1], got {forgetting}')
    return forgetting
