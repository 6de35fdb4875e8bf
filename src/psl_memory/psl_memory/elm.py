"""Extreme learning machine hidden layer (eq. 2.1-2.2) and the range normalisation around it.

``h_j(x) = sigmoid(alpha * (W_inp x_n + b)_j)`` with fixed random input weights and biases drawn
from a seed, where ``x_n`` is the input scaled from its range to [-1, 1]. The readout
``PS(x) = W_out h(x)`` (eq. 2.1) is learned by one of the readouts in this package; the hidden
layer itself never learns. Imports no ROS.
"""
from __future__ import annotations

import numpy as np


class RangeScaler:
    """Affine map of each dimension from [low, high] to [-1, 1] and back."""

    def __init__(self, low, high):
        low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
        if low.shape != high.shape or low.ndim != 1:
            raise ValueError(f'low {low.shape} and high {high.shape} must be vectors of one size')
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise ValueError('ranges must be finite')
        if np.any(high <= low):
            raise ValueError('every range needs high > low')
        if not np.all(np.isfinite(high - low)):
            raise ValueError('a range wider than floating point holds (high - low overflows)')
        self.low, self.high = low, high
        self._center = 0.5 * (high + low)
        self._half = 0.5 * (high - low)

    @classmethod
    def fit(cls, samples: np.ndarray, margin: float = 0.1) -> 'RangeScaler':
        """Ranges from data (n, d), widened by `margin` of the spread on each side; a constant
        dimension gets a unit range around its value."""
        samples = np.atleast_2d(np.asarray(samples, dtype=float))
        low, high = samples.min(axis=0), samples.max(axis=0)
        spread = high - low
        pad = np.where(spread > 0, margin * spread, 0.5)
        return cls(low - pad, high + pad)

    @property
    def dim(self) -> int:
        return self.low.size

    def to_unit(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=float) - self._center) / self._half

    def from_unit(self, u: np.ndarray) -> np.ndarray:
        return np.asarray(u, dtype=float) * self._half + self._center

    def variance_from_unit(self, var_u: np.ndarray) -> np.ndarray:
        """Scale a variance computed in unit coordinates back to the original ones."""
        return np.asarray(var_u, dtype=float) * self._half**2

    def state(self) -> dict:
        return {'low': self.low.tolist(), 'high': self.high.tolist()}


class ELMFeatures:
    """Random sigmoid hidden layer of eq. 2.2 on inputs normalised by a RangeScaler.

    Args:
        scaler: input ranges (E dimensions).
        n_hidden: hidden neurons N_H.
        seed: seed of the random input weights and biases (numpy Generator).
        alpha: slope of the logistic function.
    """

    def __init__(self, scaler: RangeScaler, n_hidden: int, seed: int = 0, alpha: float = 1.0):
        if n_hidden < 1:
            raise ValueError('n_hidden must be >= 1')
        if not alpha > 0:
            raise ValueError('alpha must be > 0')
        self.scaler, self.n_hidden, self.seed, self.alpha = scaler, int(n_hidden), int(seed), alpha
        rng = np.random.default_rng(seed)
        # inputs live in [-1, 1]: weights of unit scale give neither saturated nor linear units
        self.w_inp = rng.normal(0.0, 1.0, size=(self.n_hidden, scaler.dim))   # (N_H, E)
        self.bias = rng.uniform(-1.0, 1.0, size=self.n_hidden)                # (N_H,)

    @property
    def n_inputs(self) -> int:
        return self.scaler.dim

    def transform(self, x: np.ndarray) -> np.ndarray:
        """Hidden states h (N_H,) for one input (E,), or H (n, N_H) for inputs (n, E)."""
        x = np.asarray(x, dtype=float)
        single = x.ndim == 1
        x2 = np.atleast_2d(x)
        if x2.shape[1] != self.n_inputs:
            raise ValueError(f'expected inputs with {self.n_inputs} entries, got {x2.shape[1]}')
        a = self.alpha * (self.scaler.to_unit(x2) @ self.w_inp.T + self.bias)
        h = 0.5 * (1.0 + np.tanh(0.5 * a))          # = 1 / (1 + exp(-a)), without overflow
        return h[0] if single else h
