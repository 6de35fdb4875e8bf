"""Gaussian-Bernoulli restricted Boltzmann machine (eq. 2.17-2.19) as an associative memory.

Visible units are Gaussian with unit variance, hidden units Bernoulli. The visibles are the
entries of ``v = [tau, theta]`` normalised twice: first by the memory's ranges to
``u = scaler.to_unit(v)`` (as for every associative memory), then standardised with the mean and
standard deviation of the stored patterns, ``z = (u - mean) / std`` (std at least ``min_std``),
so that unit variance fits the data (real skill data spread over a few hundredths of the range),
and scaled per modality (see ``modality_sizes``).
With ``sigma = 1`` in the standardised units::

    E(z, h) = ||z - b_v||^2 / 2 - b_h^T h - z^T W h                      (eq. 2.17)
    P(h_j = 1 | z) = sigmoid(b_h,j + z^T W[:, j])                        (eq. 2.18)
    P(z_i | h) = N(b_v,i + W[i, :] h, 1)                                 (eq. 2.19)

Training: contrastive divergence CD-k [Hinton 2002], full batch over the stored patterns (or a
seeded random batch of ``batch_size`` of them once more are stored), learning rate ``rate`` and
weight decay. The negative phase samples the hiddens and uses the mean of the visibles (eq. 2.19
without the noise, as recommended for Gaussian visibles), so the gradient is less noisy.
Incremental: adding a pattern stores it, updates the standardisation and continues training for
``epochs_per_add`` CD updates; the cost per added pattern is bounded by
``epochs_per_add * min(N, batch_size)`` pattern updates. Adding n patterns at once equals adding
them one by one (each add trains on the patterns stored so far), and the random streams are
derived from (seed, number of stored patterns, CD updates so far), so a restored memory keeps
learning exactly like the original.

Recall (the step of the shared clamped loop): one deterministic mean-field pass
``z -> h = P(h = 1 | z) -> z_hat = b_v + W h`` (eq. 2.18, then the mean of eq. 2.19), back to
normalised units. Means instead of samples make the recall a deterministic map that settles at
a fixed point (or stops at the iteration cap), like the AELM and ARBF recall; a sampled Gibbs
chain would never converge in the sense of ``complete``. Imports no ROS.
"""
from __future__ import annotations

import numpy as np

from psl_memory.associative_memory import AssociativeMemory, modality_slices, state_arrays
from psl_memory.elm import RangeScaler

# Tags that separate the random streams of one seed: initial weights, CD training.
_INIT_STREAM = 0x2B3
_TRAIN_STREAM = 0xCD


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))           # no overflow warnings for large |x|


class RBM(AssociativeMemory):
    """Gaussian-Bernoulli RBM over ``v = [tau, theta]`` (eq. 2.17-2.19), trained by CD-k.

    Args:
        scaler: ranges of the D entries of v.
        n_hidden: hidden (Bernoulli) units N_H.
        seed: seed of the initial weights and of the CD sampling.
        cd_steps: k of CD-k (>= 1).
        epochs_per_add: CD updates after each added pattern (>= 0; 0: store only, see `train`).
        rate: learning rate (> 0).
            The defaults were measured on reach_over_obstacle seed 0 (E = 2, F = 24, 29 stored
            patterns, 10 held out, ranges fitted to the data; nRMSE tau -> theta / theta ->
            tau, as in ``psl bench memories``): defaults 0.36 / 0.36; 100 epochs per add
            0.70 / 0.89; rate 0.02 0.75 / 0.65; rate 0.1, or 256 hidden units, diverge.
        weight_decay: L2 factor on W (>= 0).
        batch_size: most patterns per CD update (>= 1); beyond it a seeded random batch.
        min_std: smallest standard deviation of the standardisation, normalised units (> 0);
            also the one used while fewer than two patterns are stored.
        modality_sizes: sizes of the modalities, e.g. ``(E, F)``, adding up to D. The entries of
            modality m are scaled by ``sqrt(max size / size(m))`` after standardisation, so a
            2-D tau weighs in the energy as much as a 24-D theta (as beta(m) does for the ARBF;
            without it, on the data above: 0.95 / 0.31, tau -> theta no better than the mean).
            None: one modality.

    Raises:
        ValueError: invalid argument.
    """

    @classmethod
    def from_config(cls, scaler: RangeScaler, modality_sizes: tuple[int, int],
                    config) -> 'RBM':
        """The memory a `SkillConfig` asks for: the skill's seed."""
        return cls(scaler, seed=config.seed, modality_sizes=modality_sizes)

    def __init__(self, scaler: RangeScaler, n_hidden: int = 64, seed: int = 0,
                 cd_steps: int = 1, epochs_per_add: int = 400, rate: float = 0.05,
                 weight_decay: float = 1e-4, batch_size: int = 256, min_std: float = 0.01,
                 modality_sizes: tuple[int, ...] | None = None):
        super().__init__(scaler)
        self.modalities = modality_slices(modality_sizes, self.dim)
        self.modality_sizes = tuple(s.stop - s.start for s in self.modalities)
        # modality balance: entries of modality m scaled by sqrt(largest size / size(m))
        largest = max(self.modality_sizes)
        self._gain = np.concatenate([np.full(n, np.sqrt(largest / n))
                                     for n in self.modality_sizes])                # (D,)
        for name, value, low in (('n_hidden', n_hidden, 1), ('cd_steps', cd_steps, 1),
                                 ('epochs_per_add', epochs_per_add, 0),
                                 ('batch_size', batch_size, 1)):
            if not float(value).is_integer() or value < low:
                raise ValueError(f'{name} must be an integer >= {low}, got {value}')
        if not (np.isfinite(rate) and rate > 0):
            raise ValueError(f'rate must be > 0, got {rate}')
        if not (np.isfinite(weight_decay) and weight_decay >= 0):
            raise ValueError(f'weight_decay must be >= 0, got {weight_decay}')
        if not (np.isfinite(min_std) and min_std > 0):
            raise ValueError(f'min_std must be > 0, got {min_std}')
        self.n_hidden, self.seed, self.cd_steps = int(n_hidden), int(seed), int(cd_steps)
        self.epochs_per_add, self.batch_size = int(epochs_per_add), int(batch_size)
        self.rate, self.weight_decay = float(rate), float(weight_decay)
        self.min_std = float(min_std)
        rng = np.random.default_rng([self.seed, _INIT_STREAM])
        self._w = rng.normal(0.0, 0.01, size=(self.dim, self.n_hidden))    # (D, N_H)
        self._b_v = np.zeros(self.dim)                                       # (D,)
        self._b_h = np.zeros(self.n_hidden)                                  # (N_H,)
        self._patterns = np.zeros((0, self.dim))                             # (N, D), caller's
        self._mean = np.zeros(self.dim)                                      # (D,), normalised
        self._std = self.min_std / self._gain                                 # (D,)
        self._updates = 0                                                    # CD updates so far

    @property
    def num_patterns(self) -> int:
        return self._patterns.shape[0]

    @property
    def weights(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Copies of (W (D, N_H), b_v (D,), b_h (N_H,)) in standardised units."""
        return self._w.copy(), self._b_v.copy(), self._b_h.copy()

    # -- the network ------------------------------------------------------------------------------
    def _hidden_prob(self, z: np.ndarray) -> np.ndarray:
        """Eq. 2.18: (n, D) -> P(h = 1 | z) (n, N_H)."""
        return sigmoid(self._b_h + z @ self._w)

    def _visible_mean(self, h: np.ndarray) -> np.ndarray:
        """Mean of eq. 2.19: (n, N_H) -> (n, D)."""
        return self._b_v + h @ self._w.T

    def _step_unit(self, u: np.ndarray) -> np.ndarray:
        z = (u - self._mean) / self._std                                     # (n, D)
        return self._mean + self._std * self._visible_mean(self._hidden_prob(z))

    def reconstruction_error(self) -> float:
        """RMS of one mean-field pass over the stored patterns, standardised units."""
        self._require_patterns()
        z = self._standardised(self._patterns)
        return float(np.sqrt(np.mean((self._visible_mean(self._hidden_prob(z)) - z)**2)))

    def free_energy(self, v: np.ndarray) -> np.ndarray:
        """Free energy F(z) = ||z - b_v||^2 / 2 - sum_j softplus(b_h,j + z^T W[:, j]) of eq.
        2.17 with the hiddens summed out, of pattern(s) v in the caller's units: (n,) or ()."""
        single = np.ndim(v) == 1
        z = self._standardised(self._check_patterns(v, 'v'))
        f = 0.5 * np.sum((z - self._b_v)**2, axis=1) - np.sum(
            np.logaddexp(0.0, self._b_h + z @ self._w), axis=1)
        return f[0] if single else f

    def _standardised(self, v: np.ndarray) -> np.ndarray:
        return (self.scaler.to_unit(v) - self._mean) / self._std

    # -- learning -------------------------------------------------------------------------------
    def add(self, v: np.ndarray) -> None:
        """Store pattern(s) v (D,) or (n, D); after each, restandardise and train
        ``epochs_per_add`` CD updates on the stored patterns.

        Raises:
            ValueError: wrong size or non-finite entries.
            RuntimeError: the training diverged (see `train`); the memory is as before.
        """
        v = self._check_patterns(v, 'v')                                     # (n, D)
        before = self.get_state()
        try:
            for v_i in v:
                self._patterns = np.vstack([self._patterns, v_i])
                self._restandardise()
                self.train(self.epochs_per_add)
        except RuntimeError:
            self.set_state(before)                                           # nothing changed
            raise

    def _restandardise(self) -> None:
        u = self.scaler.to_unit(self._patterns)                              # (N, D)
        self._mean = u.mean(axis=0)
        std = u.std(axis=0) if len(u) > 1 else np.zeros(self.dim)
        self._std = np.maximum(std, self.min_std) / self._gain

    def train(self, epochs: int) -> None:
        """Run ``epochs`` CD-k updates on the stored patterns (full batch up to batch_size).

        Raises:
            ValueError: epochs not an integer >= 0.
            RuntimeError: no pattern stored yet, or the weights became non-finite (learning
                rate too large); the weights are then those before this call.
        """
        if not float(epochs).is_integer() or epochs < 0:
            raise ValueError(f'epochs must be an integer >= 0, got {epochs}')
        self._require_patterns()
        rng = np.random.default_rng([self.seed, _TRAIN_STREAM, self.num_patterns, self._updates])
        z_all = self._standardised(self._patterns)                           # (N, D)
        saved = self._w.copy(), self._b_v.copy(), self._b_h.copy()
        with np.errstate(over='ignore', invalid='ignore'):   # divergence is checked below
            for _ in range(int(epochs)):
                z0 = z_all if len(z_all) <= self.batch_size else z_all[
                    rng.choice(len(z_all), self.batch_size, replace=False)]     # (n, D)
                h0 = self._hidden_prob(z0)                                       # (n, N_H)
                h, z, hk = h0, z0, h0
                for _ in range(self.cd_steps):
                    h_sample = (rng.random(h.shape) < h).astype(float)
                    z = self._visible_mean(h_sample)                             # mean visibles
                    hk = h = self._hidden_prob(z)
                n = len(z0)
                self._w += self.rate * ((z0.T @ h0 - z.T @ hk) / n - self.weight_decay * self._w)
                self._b_v += self.rate * (z0 - z).mean(axis=0)
                self._b_h += self.rate * (h0 - hk).mean(axis=0)
        if not (np.all(np.isfinite(self._w)) and np.all(np.isfinite(self._b_v))
                and np.all(np.isfinite(self._b_h))):
            self._w, self._b_v, self._b_h = saved
            raise RuntimeError(f'CD training diverged (rate {self.rate}); use a smaller rate')
        self._updates += int(epochs)

    # -- persistence ----------------------------------------------------------------------------
    def _constructor_state(self) -> dict:
        return {'n_hidden': self.n_hidden, 'seed': self.seed, 'cd_steps': self.cd_steps,
                'epochs_per_add': self.epochs_per_add, 'rate': self.rate,
                'weight_decay': self.weight_decay, 'batch_size': self.batch_size,
                'min_std': self.min_std, 'modality_sizes': np.array(self.modality_sizes)}

    def get_state(self) -> dict:
        """Constructor arguments (for checking), patterns, standardisation, weights and the
        number of CD updates (it seeds the next training)."""
        return {**self._scaler_state(), **self._constructor_state(),
                'patterns': self._patterns.copy(), 'mean': self._mean.copy(),
                'std': self._std.copy(), 'w': self._w.copy(), 'b_v': self._b_v.copy(),
                'b_h': self._b_h.copy(), 'updates': self._updates}

    def set_state(self, state: dict) -> None:
        """Restore :meth:`get_state`; predictions and further learning are bit-identical.

        Raises:
            ValueError: state saved by a memory with other constructor arguments, missing keys,
                arrays of the wrong shape or non-finite values.
        """
        self._check_state_matches(state, self._constructor_state())
        d, n_h = self.dim, self.n_hidden
        arrays = state_arrays(state, {'patterns': (None, d), 'mean': (d,), 'std': (d,),
                                      'w': (d, n_h), 'b_v': (d,), 'b_h': (n_h,)})
        if 'updates' not in state:
            raise ValueError("state lacks 'updates'")
        updates = float(np.asarray(state['updates']))
        if not updates.is_integer() or updates < 0:
            raise ValueError(f"state['updates'] must be an integer >= 0, got {updates}")
        if np.any(arrays['std'] <= 0):
            raise ValueError("state['std'] must be > 0")
        self._patterns, self._mean, self._std = arrays['patterns'], arrays['mean'], arrays['std']
        self._w, self._b_v, self._b_h = arrays['w'], arrays['b_v'], arrays['b_h']
        self._updates = int(updates)
