"""Associative extreme learning machine, AELM (eq. 2.20-2.21), as a parameterized skill memory.

``h = sigmoid(alpha (W_inp v_n + b))`` (eq. 2.20, the ELM hidden layer of eq. 2.2 over the whole
pattern ``v = [tau, theta]``) and ``v_hat = W_out h`` (eq. 2.21), with ``v_hat`` in normalised
units. ``W_out`` is fitted by ridge regression; stable attractors at the stored patterns are
imprinted with synthesized inputs that point towards the training data (Figure 2.3b).

Synthesized data, per modality. During recall one modality is clamped and another is free, so
the readout of a modality must pull that modality back to the data *given the other modalities*.
For each stored pattern ``v_i`` and each modality ``m`` the memory draws ``n_synthetic`` inputs
``v_i + eps`` with ``eps ~ N(0, noise^2)`` on the entries of ``m`` and zero elsewhere, target
``v_i``. The readout columns of modality ``m`` are regressed on the stored patterns plus the
inputs that perturb ``m`` only. Perturbing every dimension at once (or using one regression for
all outputs) also teaches the free modality to predict *itself*; along the data manifold that
makes the clamped dynamics nearly neutral (measured on a 1-D tau, 6-D theta toy: Jacobian
eigenvalue 0.84-1.0 along the data, tau -> theta completion 0.3-1.6 away from it in normalised
units, while theta -> tau worked), which is the "exponential number of samples" problem the
chapter mentions. With one modality (``modality_sizes=None``) this reduces to the
classic scheme of isotropic perturbations of the whole pattern.

Incremental: the memory keeps, per modality, the sufficient statistics ``H^T H`` (N_H, N_H) and
``H^T V`` (N_H, D_m), so adding a pattern and its synthesized neighbours costs the same however
many patterns are stored. Imports no ROS.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import solve

from psl_memory.associative_memory import AssociativeMemory, modality_slices, state_arrays
from psl_memory.elm import ELMFeatures, RangeScaler

# Tag that separates the synthetic-noise streams from the ELM weight stream of the same seed.
_NOISE_STREAM = 0x5E1F




class AELM(AssociativeMemory):
    """Associative ELM over ``v = [tau, theta]`` (eq. 2.20-2.21).

    Args:
        scaler: ranges of the D entries of v.
        n_hidden: hidden neurons N_H.
        seed: seed of the random input weights and of the synthesized perturbations.
        alpha: slope of the logistic hidden units.
        regularization: ridge factor of the readout (> 0).
        n_synthetic: synthesized inputs per stored pattern and modality (>= 0).
        noise: standard deviation of the synthesized perturbations, normalised units (> 0).
        modality_sizes: sizes of the modalities, e.g. ``(E, F)``, adding up to D; completion in
            both directions needs the split. None: one modality (isotropic perturbations).

    Raises:
        ValueError: invalid argument.
    """

    @classmethod
    def from_config(cls, scaler: RangeScaler, modality_sizes: tuple[int, int],
                    config) -> 'AELM':
        """The memory a `SkillConfig` asks for: at least 100 hidden neurons (the skill's N_H if larger)."""
        return cls(scaler, n_hidden=max(config.n_hidden, 100), seed=config.seed,
                   modality_sizes=modality_sizes)

    def __init__(self, scaler: RangeScaler, n_hidden: int = 200, seed: int = 0,
                 alpha: float = 1.0, regularization: float = 1e-3, n_synthetic: int = 20,
                 noise: float = 0.1, modality_sizes: tuple[int, ...] | None = None):
        super().__init__(scaler)
        if not (np.isfinite(regularization) and regularization > 0):
            raise ValueError(f'regularization must be > 0, got {regularization}')
        if not float(n_synthetic).is_integer() or n_synthetic < 0:
            raise ValueError(f'n_synthetic must be an integer >= 0, got {n_synthetic}')
        if not (np.isfinite(noise) and noise > 0):
            raise ValueError(f'noise must be > 0, got {noise}')
        self.features = ELMFeatures(scaler, n_hidden, seed, alpha)
        self.seed = int(seed)
        self.regularization = float(regularization)
        self.n_synthetic = int(n_synthetic)
        self.noise = float(noise)
        self.modalities = modality_slices(modality_sizes, self.dim)
        self.modality_sizes = tuple(s.stop - s.start for s in self.modalities)
        n_h = self.features.n_hidden
        self._patterns = np.zeros((0, self.dim))                       # (N, D), caller's units
        self._hth = np.zeros((len(self.modalities), n_h, n_h))         # (M, N_H, N_H)
        self._htv = np.zeros((n_h, self.dim))                          # (N_H, D), blocks by m
        self._w_out = np.zeros((n_h, self.dim))                        # (N_H, D)

    @property
    def num_patterns(self) -> int:
        return self._patterns.shape[0]

    @property
    def w_out(self) -> np.ndarray:
        """Readout W_out (N_H, D) of eq. 2.21, mapping h to v_hat in normalised units."""
        return self._w_out.copy()

    def _hidden(self, u: np.ndarray) -> np.ndarray:
        """Eq. 2.20 on normalised inputs: (n, D) -> H (n, N_H)."""
        return self.features.transform(self.scaler.from_unit(u))

    def _step_unit(self, u: np.ndarray) -> np.ndarray:
        return self._hidden(u) @ self._w_out                           # eq. 2.21, (n, D)

    def add(self, v: np.ndarray) -> None:
        """Store pattern(s) v (D,) or (n, D) with their synthesized neighbours; refit W_out.

        Raises:
            ValueError: wrong size or non-finite entries.
        """
        v = self._check_patterns(v, 'v')                                # (n, D)
        for v_i in v:
            self._accumulate(self.scaler.to_unit(v_i), index=self.num_patterns)
            self._patterns = np.vstack([self._patterns, v_i])
        self._solve()

    def _accumulate(self, u_i: np.ndarray, index: int) -> None:
        """Add pattern u_i (D,) and its synthesized inputs to the sufficient statistics."""
        rng = np.random.default_rng([self.seed, _NOISE_STREAM, index])
        h_i = self._hidden(u_i[None, :])                                # (1, N_H)
        for m, dims in enumerate(self.modalities):
            # inputs: u_i with modality m perturbed; targets: u_i (pointing back to the data)
            x = np.repeat(u_i[None, :], self.n_synthetic, axis=0)       # (n_syn, D)
            x[:, dims] += rng.normal(0.0, self.noise, size=x[:, dims].shape)
            h = np.vstack([h_i, self._hidden(x)])                      # (1 + n_syn, N_H)
            self._hth[m] += h.T @ h
            self._htv[:, dims] += h.sum(axis=0)[:, None] * u_i[None, dims]

    def _solve(self) -> None:
        """Ridge readout per modality, (H^T H + reg I) W = H^T V (Cholesky, no inverse)."""
        eye = self.regularization * np.eye(self.features.n_hidden)
        for m, dims in enumerate(self.modalities):
            self._w_out[:, dims] = solve(self._hth[m] + eye, self._htv[:, dims], assume_a='pos')

    # -- persistence ----------------------------------------------------------------------------
    def _constructor_state(self) -> dict:
        return {'n_hidden': self.features.n_hidden, 'seed': self.seed,
                'alpha': float(self.features.alpha), 'regularization': self.regularization,
                'n_synthetic': self.n_synthetic, 'noise': self.noise,
                'modality_sizes': np.array(self.modality_sizes)}

    def get_state(self) -> dict:
        """Constructor arguments (for checking), patterns, sufficient statistics and W_out."""
        return {**self._scaler_state(), **self._constructor_state(),
                'patterns': self._patterns.copy(), 'hth': self._hth.copy(),
                'htv': self._htv.copy(), 'w_out': self._w_out.copy()}

    def set_state(self, state: dict) -> None:
        """Restore :meth:`get_state`; predictions afterwards are bit-identical.

        Raises:
            ValueError: state saved by a memory with other constructor arguments, missing keys
                or arrays of the wrong shape.
        """
        self._check_state_matches(state, self._constructor_state())
        n_h, d, n_m = self.features.n_hidden, self.dim, len(self.modalities)
        arrays = state_arrays(state, {'patterns': (None, d), 'hth': (n_m, n_h, n_h),
                                      'htv': (n_h, d), 'w_out': (n_h, d)})
        self._patterns, self._hth = arrays['patterns'], arrays['hth']
        self._htv, self._w_out = arrays['htv'], arrays['w_out']
