"""Batch ridge regression readout (eq. 2.7-2.8), the reference the incremental readouts match.

``W = (H^T H + g I)^{-1} H^T Y`` (eq. 2.8) minimises ``||H W - Y||^2 + g ||W||^2`` (eq. 2.7).
The solve uses a Cholesky factorisation of the symmetric positive definite ``H^T H + g I``; no
inverse is formed. This readout keeps every sample and refits from all of them at each update,
so an update costs O(N N_H^2 + N_H^3) and grows with the number of samples N: it is the batch
baseline, not a readout for long online runs.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from psl_memory.readout import (Readout, State, check_positive, state_array, state_count,
                                state_positive)


def ridge_solve(gram: np.ndarray, rhs: np.ndarray, regularization: float) -> np.ndarray:
    """Solution of ``(gram + g I) W = rhs`` (eq. 2.8) by Cholesky.

    Args:
        gram: H^T H, (N_H, N_H), symmetric positive semi-definite.
        rhs: H^T Y, (N_H, F).
        regularization: g > 0.
    Returns:
        W, (N_H, F).
    """
    a = gram + regularization * np.eye(gram.shape[0])            # (N_H, N_H)
    return cho_solve(cho_factor(a, lower=True), rhs)


class RidgeReadout(Readout):
    """Batch ridge regression, refitted from all stored samples at every update (eq. 2.8).

    Args:
        n_hidden: hidden states N_H.
        n_out: outputs F.
        regularization: g > 0 of eq. 2.7.
    """

    name = 'ridge'

    @classmethod
    def from_config(cls, n_hidden: int, n_out: int, config) -> 'RidgeReadout':
        """The readout a `SkillConfig` asks for."""
        return cls(n_hidden, n_out, regularization=config.regularization)

    def __init__(self, n_hidden: int, n_out: int, regularization: float = 1e-6):
        super().__init__(n_hidden, n_out)
        self.regularization = check_positive('regularization', regularization)
        self._hs = np.zeros((0, self.n_hidden))     # (N, N_H) all hidden states seen
        self._ys = np.zeros((0, self.n_out))        # (N, F) all targets seen

    def _compute_update(self, hs: np.ndarray, ys: np.ndarray) -> dict[str, Any]:
        all_h = np.concatenate([self._hs, hs])      # (N, N_H)
        all_y = np.concatenate([self._ys, ys])      # (N, F)
        w = ridge_solve(all_h.T @ all_h, all_h.T @ all_y, self.regularization)   # eq. 2.8
        return {'_hs': all_h, '_ys': all_y, '_n': all_h.shape[0], '_w': w}

    def get_state(self) -> State:
        return {**self._header(), 'regularization': self.regularization,
                'hidden': self._hs.copy(), 'targets': self._ys.copy()}

    def _parse_state(self, state: State) -> dict[str, Any]:
        n = state_count(state, 'num_samples')
        all_h = state_array(state, 'hidden', (n, self.n_hidden))
        all_y = state_array(state, 'targets', (n, self.n_out))
        regularization = state_positive(state, 'regularization')
        w = ridge_solve(all_h.T @ all_h, all_h.T @ all_y, regularization)
        return {'regularization': regularization, '_hs': all_h, '_ys': all_y, '_n': n, '_w': w}
