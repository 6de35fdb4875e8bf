"""Associative radial basis function network, ARBF (eq. 2.22), as a parameterized skill memory.

The hidden layer is a normalised RBF layer whose centres ``c_j`` are the stored patterns in
normalised units (vector quantisation with one prototype per pattern)::

    h_j(v) = exp(-sum_m beta(m) ||v(m) - c_j(m)||^2) / sum_k exp(-sum_m beta(m) ||v(m) - c_k(m)||^2)

(eq. 2.22) and ``v_hat = W_out h`` as in eq. 2.21, ``W_out`` by ridge regression on the targets
``v_j``. The modality factors balance the modalities: by default ``beta(m) = 1 / (2 width^2
dim(m))``, i.e. each modality counts by its mean squared per-entry distance, so a one-dimensional
tau weighs as much as a ten-dimensional theta. Adding a pattern adds a centre and refits W_out
(O(N^3); fine for N up to a few hundred). Imports no ROS.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import solve

from psl_memory.associative_memory import AssociativeMemory, modality_slices, state_arrays
from psl_memory.elm import RangeScaler


class ARBF(AssociativeMemory):
    """Associative normalised-RBF network over ``v = [tau, theta]`` (eq. 2.22).

    Args:
        scaler: ranges of the D entries of v.
        modality_sizes: sizes of the modalities, e.g. ``(E, F)``, adding up to D. None: one
            modality over the whole pattern.
        beta: the factors beta(m) of eq. 2.22, one per modality (> 0), in normalised units;
            None: ``1 / (2 width^2 dim(m))``.
        width: RBF width in normalised units (RMS distance per entry) for the default beta; not
            used when beta is given. Of the order of a few pattern spacings: narrower widths
            make every stored pattern its own basin and completion between patterns snaps to
            the nearest one (20 patterns over [-1, 1]: 0.3 measured best, 0.1 gives 0.17 error).
        regularization: ridge factor of the readout (> 0).

    Raises:
        ValueError: invalid argument.
    """

    @classmethod
    def from_config(cls, scaler: RangeScaler, modality_sizes: tuple[int, int],
                    config) -> 'ARBF':
        """The memory a `SkillConfig` asks for: one centre per sample."""
        return cls(scaler, modality_sizes=modality_sizes)

    def __init__(self, scaler: RangeScaler, modality_sizes: tuple[int, ...] | None = None,
                 beta: tuple[float, ...] | None = None, width: float = 0.3,
                 regularization: float = 1e-6):
        super().__init__(scaler)
        self.modalities = modality_slices(modality_sizes, self.dim)
        self.modality_sizes = tuple(s.stop - s.start for s in self.modalities)
        if not (np.isfinite(width) and width > 0):
            raise ValueError(f'width must be > 0, got {width}')
        if beta is None:
            beta_arr = 1.0 / (2.0 * width**2 * np.array(self.modality_sizes, dtype=float))
        else:
            beta_arr = np.atleast_1d(np.asarray(beta, dtype=float))
            if beta_arr.shape != (len(self.modalities),):
                raise ValueError(f'beta needs one factor per modality '
                                 f'({len(self.modalities)}), got {beta}')
            if not np.all(np.isfinite(beta_arr) & (beta_arr > 0)):
                raise ValueError(f'beta must be finite and > 0, got {beta}')
        if not (np.isfinite(regularization) and regularization > 0):
            raise ValueError(f'regularization must be > 0, got {regularization}')
        self.width = float(width)
        self.beta = beta_arr                                        # (M,)
        self.regularization = float(regularization)
        # per-entry factor: beta(m) repeated over the entries of modality m
        self._beta_per_entry = np.concatenate(
            [np.full(s.stop - s.start, b) for s, b in zip(self.modalities, beta_arr)])  # (D,)
        self._patterns = np.zeros((0, self.dim))                   # (N, D), caller's units
        self._centres = np.zeros((0, self.dim))                    # (N, D), normalised
        self._w_out = np.zeros((0, self.dim))                      # (N, D)

    @property
    def num_patterns(self) -> int:
        return self._patterns.shape[0]

    @property
    def w_out(self) -> np.ndarray:
        """Readout W_out (N, D), mapping h to v_hat in normalised units."""
        return self._w_out.copy()

    def _hidden(self, u: np.ndarray) -> np.ndarray:
        """Eq. 2.22 on normalised inputs: (n, D) -> H (n, N), rows summing to 1."""
        diff = u[:, None, :] - self._centres[None, :, :]           # (n, N, D)
        energy = (diff**2) @ self._beta_per_entry                  # (n, N)
        # shift by the smallest energy: exp never underflows to an all-zero row far from data
        act = np.exp(-(energy - energy.min(axis=1, keepdims=True)))
        return act / act.sum(axis=1, keepdims=True)

    def _step_unit(self, u: np.ndarray) -> np.ndarray:
        return self._hidden(u) @ self._w_out                       # (n, D)

    def add(self, v: np.ndarray) -> None:
        """Store pattern(s) v (D,) or (n, D) as new centres and refit W_out.

        Raises:
            ValueError: wrong size or non-finite entries.
        """
        v = self._check_patterns(v, 'v')                            # (n, D)
        self._patterns = np.vstack([self._patterns, v])
        self._centres = self.scaler.to_unit(self._patterns)
        h = self._hidden(self._centres)                             # (N, N)
        a = h.T @ h + self.regularization * np.eye(h.shape[1])
        self._w_out = solve(a, h.T @ self._centres, assume_a='pos')  # ridge, (N, D)

    # -- persistence ----------------------------------------------------------------------------
    def _constructor_state(self) -> dict:
        return {'modality_sizes': np.array(self.modality_sizes), 'beta': self.beta.copy(),
                'regularization': self.regularization}

    def get_state(self) -> dict:
        """Constructor arguments (for checking), stored patterns and W_out."""
        return {**self._scaler_state(), **self._constructor_state(),
                'patterns': self._patterns.copy(), 'w_out': self._w_out.copy()}

    def set_state(self, state: dict) -> None:
        """Restore :meth:`get_state`; predictions afterwards are bit-identical.

        Raises:
            ValueError: state saved by a memory with other constructor arguments, missing keys
                or arrays of the wrong shape.
        """
        self._check_state_matches(state, self._constructor_state())
        arrays = state_arrays(state, {'patterns': (None, self.dim), 'w_out': (None, self.dim)})
        patterns, w_out = arrays['patterns'], arrays['w_out']
        if w_out.shape != patterns.shape:
            raise ValueError(f'state patterns {patterns.shape} and w_out {w_out.shape} must both '
                             f'have shape (N, {self.dim})')
        self._patterns, self._w_out = patterns, w_out
        self._centres = self.scaler.to_unit(patterns)
