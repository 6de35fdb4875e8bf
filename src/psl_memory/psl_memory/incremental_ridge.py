"""Incremental regularised least squares on chunks (eq. 2.9-2.11, Huynh and Won 2011).

For chunks (H_k (n_k, N_H), T_k (n_k, F)), a single sample being a chunk of one:

    L(0) = H_0^T H_0 + g I,        W(0) = L(0)^{-1} H_0^T T_0                   eq. 2.11
    L(k) = L(k-1) + H_k^T H_k                                                  eq. 2.10
    W(k) = W(k-1) + L(k)^{-1} H_k^T (T_k - H_k W(k-1))                          eq. 2.9

Starting from ``L = g I`` and ``W = 0``, eq. 2.9-2.10 applied to the first chunk give exactly
eq. 2.11, so every chunk takes the same path. Since ``L(k) W(k) = L(k-1) W(k-1) + H_k^T T_k``,
``W(k)`` equals the batch ridge solution (eq. 2.8) on all samples so far. ``L(k)^{-1}`` is applied
through a Cholesky factorisation, never formed; a chunk costs O(n_k N_H^2 + N_H^3 + N_H^2 F),
independent of the number of samples seen.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from psl_memory.readout import (Readout, State, check_positive, state_array, state_count,
                                state_positive)


class IncrementalRidge(Readout):
    """Chunk-wise ridge regression (eq. 2.9-2.11).

    Args:
        n_hidden: hidden states N_H.
        n_out: outputs F.
        regularization: g > 0 of eq. 2.11 (lambda there).
    """

    name = 'incremental_ridge'

    @classmethod
    def from_config(cls, n_hidden: int, n_out: int, config) -> 'IncrementalRidge':
        """The readout a `SkillConfig` asks for."""
        return cls(n_hidden, n_out, regularization=config.regularization)

    def __init__(self, n_hidden: int, n_out: int, regularization: float = 1e-6):
        super().__init__(n_hidden, n_out)
        self.regularization = check_positive('regularization', regularization)
        self._l = self.regularization * np.eye(self.n_hidden)     # (N_H, N_H) L before data

    def _compute_update(self, hs: np.ndarray, ys: np.ndarray) -> dict[str, Any]:
        l_new = self._l + hs.T @ hs                                # (N_H, N_H) eq. 2.10
        innovation = ys - hs @ self._w                             # (n, F) T_k - H_k W(k-1)
        step = cho_solve(cho_factor(l_new, lower=True), hs.T @ innovation)   # (N_H, F)
        return {'_l': l_new, '_w': self._w + step, '_n': self._n + hs.shape[0]}   # eq. 2.9

    def get_state(self) -> State:
        return {**self._header(), 'regularization': self.regularization,
                'weights': self._w.copy(), 'l': self._l.copy()}

    def _parse_state(self, state: State) -> dict[str, Any]:
        return {'regularization': state_positive(state, 'regularization'),
                '_n': state_count(state, 'num_samples'),
                '_w': state_array(state, 'weights', (self.n_hidden, self.n_out)),
                '_l': state_array(state, 'l', (self.n_hidden, self.n_hidden))}
