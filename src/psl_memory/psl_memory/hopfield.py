"""Classical Hopfield network (eq. 2.15-2.16) on binarised patterns: the textbook baseline.

Each entry of the normalised pattern ``u = scaler.to_unit(v)`` is coded by ``bits`` bipolar
neurons (+1 / -1) as a thermometer code: neuron k of an entry is +1 if the entry exceeds the
threshold ``t_k = -1 + 2 (k + 1/2) / bits`` and -1 otherwise, so N = D * bits neurons in all.
Decoding takes the mean of an entry's neurons, ``u = mean(s)``: ``bits + 1`` levels in [-1, 1],
quantisation error at most ``1 / bits`` inside the range (values outside saturate at +-1).

Weights by the Hebbian rule ``w_ij = (1 / P) sum_mu s_i^mu s_j^mu`` with a zero diagonal, no
thresholds (``alpha_i = 0``). The update of eq. 2.15 is applied asynchronously, one neuron at a
time in index order, ``s_i <- +1 if sum_j w_ij s_j >= alpha_i else -1``, which never raises the
energy of eq. 2.16, ``E = -1/2 s^T W s + alpha^T s`` (W symmetric with zero diagonal).

Recall (the step of the shared clamped loop): one asynchronous sweep over the free neurons, i.e.
those of the entries not given; the neurons of given entries hold the code of the given values
throughout. A sweep that flips no neuron is a fixed point: the step returns its input and the
loop reports convergence (the first sweep moves the free entries at least onto the code levels,
so a completion takes two sweeps or more). Capacity is about 0.14 N random patterns
[Hopfield 1982]; thermometer codes of nearby patterns are strongly correlated, so far fewer are
recalled without crosstalk, and completion between stored patterns snaps to a stored pattern or
a spurious mixture.
Adding patterns sums their outer products (integer counts), so one-by-one and batch adds are
identical. Imports no ROS.
"""
from __future__ import annotations

import numpy as np

from psl_memory.associative_memory import AssociativeMemory, CompletionResult, state_arrays
from psl_memory.elm import RangeScaler


def thermometer_thresholds(bits: int) -> np.ndarray:
    """Thresholds (bits,) in (-1, 1): the centres of ``bits`` equal cells of [-1, 1]."""
    return -1.0 + 2.0 * (np.arange(bits) + 0.5) / bits


def encode(u: np.ndarray, bits: int) -> np.ndarray:
    """Thermometer code: (n, D) normalised -> (n, D * bits) of +-1."""
    s = np.where(u[:, :, None] > thermometer_thresholds(bits), 1.0, -1.0)   # (n, D, bits)
    return s.reshape(len(u), -1)


def decode(s: np.ndarray, bits: int) -> np.ndarray:
    """Mean of each entry's neurons: (n, D * bits) -> (n, D) in [-1, 1]."""
    return s.reshape(len(s), -1, bits).mean(axis=2)


def energy(w: np.ndarray, s: np.ndarray, alpha: np.ndarray | None = None) -> float:
    """Eq. 2.16, ``-1/2 s^T W s + alpha^T s`` for one state s (N,)."""
    e = -0.5 * float(s @ w @ s)
    return e if alpha is None else e + float(alpha @ s)


def asynchronous_sweep(w: np.ndarray, s: np.ndarray, free: np.ndarray,
                       alpha: np.ndarray | None = None) -> np.ndarray:
    """One sweep of eq. 2.15 over the free neurons in index order; the others stay as they are.

    Args:
        w: weights (N, N), symmetric with zero diagonal.
        s: state (N,) of +-1.
        free: boolean mask (N,) of the neurons that may change.
        alpha: thresholds (N,); None: zero.

    Returns:
        The new state (N,); ``s`` itself is not changed.
    """
    s = np.array(s, dtype=float)
    for i in np.flatnonzero(free):
        field = float(w[i] @ s)
        s[i] = 1.0 if field >= (0.0 if alpha is None else alpha[i]) else -1.0
    return s


class Hopfield(AssociativeMemory):
    """Hopfield network over the thermometer code of ``v = [tau, theta]`` (eq. 2.15-2.16).

    Args:
        scaler: ranges of the D entries of v.
        bits: neurons per entry (>= 1); resolution 2 / bits in normalised units.

    Raises:
        ValueError: invalid argument.
    """

    @classmethod
    def from_config(cls, scaler: RangeScaler, modality_sizes: tuple[int, int],
                    config) -> 'Hopfield':
        """The memory a `SkillConfig` asks for: one thermometer code for all of v (no modalities)."""
        return cls(scaler)

    def __init__(self, scaler: RangeScaler, bits: int = 16):
        super().__init__(scaler)
        if not float(bits).is_integer() or bits < 1:
            raise ValueError(f'bits must be an integer >= 1, got {bits}')
        self.bits = int(bits)
        n = self.dim * self.bits
        self._patterns = np.zeros((0, self.dim))          # (P, D), caller's units
        self._hebb = np.zeros((n, n))                     # sum of s s^T over patterns, (N, N)
        self._free_entries: np.ndarray | None = None      # (D,) during complete, else None

    @property
    def num_patterns(self) -> int:
        return self._patterns.shape[0]

    @property
    def num_neurons(self) -> int:
        return self.dim * self.bits

    @property
    def weights(self) -> np.ndarray:
        """W (N, N) = Hebbian sum / P, zero diagonal."""
        w = self._hebb / max(self.num_patterns, 1)
        np.fill_diagonal(w, 0.0)
        return w

    def add(self, v: np.ndarray) -> None:
        """Store pattern(s) v (D,) or (n, D): add the outer products of their codes.

        Raises:
            ValueError: wrong size or non-finite entries.
        """
        v = self._check_patterns(v, 'v')                            # (n, D)
        s = encode(self.scaler.to_unit(v), self.bits)               # (n, N)
        self._hebb += s.T @ s
        self._patterns = np.vstack([self._patterns, v])

    def _step_unit(self, u: np.ndarray) -> np.ndarray:
        """One asynchronous sweep per row; during `complete` only over the free entries'
        neurons, otherwise (predict) over all."""
        free_entries = (np.ones(self.dim, dtype=bool) if self._free_entries is None
                        else self._free_entries)
        free = np.repeat(free_entries, self.bits)                   # (N,)
        w = self.weights
        s = encode(u, self.bits)                                    # (n, N)
        s_new = np.array([asynchronous_sweep(w, row, free) for row in s])
        out = decode(s_new, self.bits)                              # (n, D)
        out[:, ~free_entries] = u[:, ~free_entries]                 # given entries as given
        return out

    def complete(self, pattern: np.ndarray, known, tol: float = 1e-6,
                 max_iter: int = 200) -> CompletionResult:
        """Clamped recall as in :meth:`AssociativeMemory.complete`, with the neurons of the
        known entries held at their code during every sweep (not only between sweeps).

        The first sweep quantises the free entries to the code levels; the recall converges
        when a sweep flips no free neuron.
        """
        known_mask = np.asarray(known)
        if known_mask.shape == (self.dim,) and known_mask.dtype == bool:
            self._free_entries = ~known_mask
        try:
            return super().complete(pattern, known, tol=tol, max_iter=max_iter)
        finally:
            self._free_entries = None

    # -- persistence ----------------------------------------------------------------------------
    def get_state(self) -> dict:
        """Code size (for checking), stored patterns and the Hebbian sum."""
        return {**self._scaler_state(), 'bits': self.bits, 'patterns': self._patterns.copy(),
                'hebb': self._hebb.copy()}

    def set_state(self, state: dict) -> None:
        """Restore :meth:`get_state`; recall afterwards is bit-identical.

        Raises:
            ValueError: other code size or ranges, missing keys, arrays of the wrong shape, or a
                Hebbian sum that is not that of the stored patterns.
        """
        self._check_state_matches(state, {'bits': self.bits})
        n = self.num_neurons
        arrays = state_arrays(state, {'patterns': (None, self.dim), 'hebb': (n, n)})
        patterns, hebb = arrays['patterns'], arrays['hebb']
        s = encode(self.scaler.to_unit(patterns), self.bits) if len(patterns) else None
        expected = s.T @ s if s is not None else np.zeros((n, n))
        if not np.array_equal(hebb, expected):
            raise ValueError('state hebb is not the Hebbian sum of the stored patterns')
        self._patterns, self._hebb = patterns, hebb
