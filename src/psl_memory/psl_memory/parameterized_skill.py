"""A parameterized skill PS: tau -> theta (eq. 2.1-2.14) with an associative memory beside it.

`ParameterizedSkill` composes:
- `ELMFeatures` on tau (fixed random hidden layer, eq. 2.2) and one of the readouts
  (`psl_memory.registry.READOUTS`: ridge, rls, incremental_ridge, bayes) learning normalised
  theta from h(tau);
- an associative memory over v = [tau, theta] (AELM, eq. 2.20-2.21, or ARBF, eq. 2.22; the
  baselines RBM, eq. 2.17-2.19, and Hopfield, eq. 2.15-2.16) that completes a partial pattern
  in either direction (tau -> theta, theta -> tau);
- the samples themselves, so the skill can be saved, inspected and refitted.

Normalisation: tau by its ranges (the task YAML's, or around the first sample for a skill
created ad hoc); theta around a reference vector (the task's default theta, or the first
sample) with one common spread (the largest magnitude in the reference, at least 1), since all
entries of theta share their units. Range policy (`check_tau`, `check_theta`), the same for a
query, a sample and the known entries of a completion: a skill with a task's ranges refuses a
tau more than TAU_MARGIN of its range outside it; any skill refuses absurd magnitudes (tau
MAX_SPREADS ranges away, theta THETA_SPREADS spreads from its reference) and NaN or inf.
Imports no ROS.
"""
from __future__ import annotations

import numpy as np

from psl_memory.elm import ELMFeatures, RangeScaler
from psl_memory.registry import ASSOCIATIVE_MEMORIES, READOUTS
from psl_memory.skill_config import SkillConfig

# The range policy, one rule for query, add and complete (known entries):
TAU_MARGIN = 0.5       # a skill created with ranges (a task's): tau may lie this share of its
                       # range outside it
MAX_SPREADS = 1e6      # a skill created by its first sample: tau this many ranges away is a
                       # units error
THETA_SPREADS = 100.0  # theta this many spreads from the skill's reference is a units error




def scaler_around(reference: np.ndarray) -> RangeScaler:
    """reference +- one common spread (the largest magnitude in it, at least 1)."""
    reference = np.asarray(reference, dtype=float)
    spread = max(1.0, float(np.max(np.abs(reference)))) if reference.size else 1.0
    return RangeScaler(reference - spread, reference + spread)


class ParameterizedSkill:
    """theta = PS(tau) with predictive variance, learned one sample at a time."""

    def __init__(self, name: str, tau_scaler: RangeScaler, theta_scaler: RangeScaler,
                 config: SkillConfig = SkillConfig(), bounded: bool = False):
        self.name, self.config, self.bounded = name, config, bool(bounded)
        self.tau_scaler, self.theta_scaler = tau_scaler, theta_scaler
        self.features = ELMFeatures(tau_scaler, config.n_hidden, config.seed, config.alpha)
        self.readout = READOUTS[config.readout].from_config(config.n_hidden, theta_scaler.dim,
                                                            config)
        v_scaler = RangeScaler(np.r_[tau_scaler.low, theta_scaler.low],
                               np.r_[tau_scaler.high, theta_scaler.high])
        self.associative = ASSOCIATIVE_MEMORIES[config.associative].from_config(
            v_scaler, (tau_scaler.dim, theta_scaler.dim), config)
        self._taus: list[np.ndarray] = []               # N x (E,)
        self._thetas: list[np.ndarray] = []             # N x (F,)

    @property
    def tau_dim(self) -> int:
        return self.tau_scaler.dim

    @property
    def theta_dim(self) -> int:
        return self.theta_scaler.dim

    @property
    def num_samples(self) -> int:
        return len(self._taus)

    def _vector(self, value, size: int, name: str) -> np.ndarray:
        array = np.asarray(value, dtype=float)
        if array.ndim != 1 or array.size != size:
            raise ValueError(f'skill {self.name!r} takes {name} with {size} entries, got '
                             f'{array.size}')
        if not np.all(np.isfinite(array)):
            raise ValueError(f'{name} contains NaN or inf')
        return array

    def check_tau(self, tau, entries=None) -> np.ndarray:
        """tau (E,) as floats, or ValueError naming the entry and the range (see the range
        policy in the module docstring); `entries` (a mask) limits the range check."""
        tau = self._vector(tau, self.tau_dim, 'tau')
        unit = np.abs(self.tau_scaler.to_unit(tau))
        limit = 1.0 + 2.0 * TAU_MARGIN if self.bounded else MAX_SPREADS
        bad = np.flatnonzero((unit > limit) & (True if entries is None else entries))
        if bad.size:
            i = int(bad[0])
            low, high = self.tau_scaler.low[i], self.tau_scaler.high[i]
            allowed = (f'more than {100 * TAU_MARGIN:.0f} % of it' if self.bounded else
                       f'{MAX_SPREADS:g} ranges away: a units or scaling error')
            raise ValueError(f'tau[{i}] = {tau[i]:g} lies outside the range [{low:g}, {high:g}] '
                             f'of skill {self.name!r} by {allowed}')
        return tau

    def check_theta(self, theta, entries=None) -> np.ndarray:
        """theta (F,) as floats, or ValueError: an entry THETA_SPREADS spreads or more from the
        skill's reference (`entries`, a mask, limits the check)."""
        theta = self._vector(theta, self.theta_dim, 'theta')
        unit = np.abs(self.theta_scaler.to_unit(theta))
        bad = np.flatnonzero((unit > THETA_SPREADS) & (True if entries is None else entries))
        if bad.size:
            i = int(bad[0])
            centre = 0.5 * (self.theta_scaler.low[i] + self.theta_scaler.high[i])
            spread = 0.5 * (self.theta_scaler.high[i] - self.theta_scaler.low[i])
            raise ValueError(f'theta[{i}] = {theta[i]:g} lies more than {THETA_SPREADS:g} '
                             f'spreads ({spread:g}) from the reference {centre:g} of skill '
                             f'{self.name!r}: a units or scaling error')
        return theta

    def add(self, tau, theta) -> int:
        """Consolidate one sample (eq. 2.5-2.11 depending on the readout); returns the number
        of samples. Raises ValueError and changes nothing for a bad sample (range policy:
        `check_tau`, `check_theta`)."""
        tau, theta = self.check_tau(tau), self.check_theta(theta)
        unit = self.theta_scaler.to_unit(theta)
        self.readout.update(self.features.transform(tau), unit)
        self.associative.add(np.r_[tau, theta])
        self._taus.append(tau)
        self._thetas.append(theta)
        return self.num_samples

    @property
    def taus(self) -> np.ndarray:
        """The samples' task parameters (N, E)."""
        return np.array(self._taus).reshape(-1, self.tau_dim)

    @property
    def thetas(self) -> np.ndarray:
        """The samples' policy parameters (N, F)."""
        return np.array(self._thetas).reshape(-1, self.theta_dim)

    def query(self, tau) -> tuple[np.ndarray, np.ndarray | None]:
        """theta = PS(tau) (eq. 2.1) and its per-dimension predictive variance (eq. 2.14) in
        theta's units, or None when the readout has none. With no sample yet, theta is the
        centre of the theta range (the task's default policy). Raises ValueError for a tau
        the range policy refuses (`check_tau`)."""
        tau = self.check_tau(tau)
        h = self.features.transform(tau)
        theta = self.theta_scaler.from_unit(self.readout.predict(h))
        var = self.readout.predict_variance(h)
        return theta, (None if var is None else self.theta_scaler.variance_from_unit(var))

    def complete(self, pattern, known):
        """Associative completion of v = [tau, theta] with the known dimensions clamped,
        iterated until no entry moves more than the configured tolerance or the iteration cap
        (the result says which)."""
        if self.num_samples == 0:
            raise ValueError(f'skill {self.name!r} has no samples to complete from')
        pattern = self._vector(pattern, self.tau_dim + self.theta_dim, 'pattern')
        mask = np.asarray(known)
        if mask.shape == pattern.shape and mask.dtype == bool:   # else the memory says why
            e = self.tau_dim
            self.check_tau(pattern[:e], mask[:e])
            self.check_theta(pattern[e:], mask[e:])
        return self.associative.complete(pattern, known, tol=self.config.completion_tolerance,
                                         max_iter=self.config.completion_max_iterations)

    def refitted(self, config: SkillConfig) -> 'ParameterizedSkill':
        """A skill with the same ranges and another configuration (e.g. another readout), fed
        this skill's samples in their order."""
        other = ParameterizedSkill(self.name, self.tau_scaler, self.theta_scaler, config,
                                   self.bounded)
        for tau, theta in zip(self.taus, self.thetas):
            other.add(tau, theta)
        return other

    # -- persistence --------------------------------------------------------------------------
    def get_state(self) -> dict[str, np.ndarray]:
        """Everything that makes this skill, as named numpy arrays (see memory_file)."""
        state = {'tau_low': self.tau_scaler.low, 'tau_high': self.tau_scaler.high,
                 'theta_low': self.theta_scaler.low, 'theta_high': self.theta_scaler.high,
                 'w_inp': self.features.w_inp, 'bias': self.features.bias,
                 'taus': self.taus, 'thetas': self.thetas, 'bounded': np.array(self.bounded)}
        state.update({f'readout.{k}': np.asarray(v) for k, v in self.readout.get_state().items()})
        state.update({f'associative.{k}': np.asarray(v)
                      for k, v in self.associative.get_state().items()})
        return state

    @classmethod
    def from_state(cls, name: str, config: SkillConfig, state: dict) -> 'ParameterizedSkill':
        """Rebuild a skill saved with get_state. Raises ValueError if anything disagrees."""
        skill = cls(name, RangeScaler(state['tau_low'], state['tau_high']),
                    RangeScaler(state['theta_low'], state['theta_high']), config,
                    bounded=bool(state.get('bounded', False)))   # files before the policy: no
        if not (np.array_equal(skill.features.w_inp, state['w_inp'])
                and np.array_equal(skill.features.bias, state['bias'])):
            raise ValueError(f'skill {name!r}: the saved random weights differ from those of '
                             f'seed {config.seed} (saved by another numpy version?)')
        skill.readout.set_state({k[8:]: v for k, v in state.items() if k.startswith('readout.')})
        skill.associative.set_state({k[12:]: v for k, v in state.items()
                                     if k.startswith('associative.')})
        skill._taus = list(np.asarray(state['taus'], dtype=float).reshape(-1, skill.tau_dim))
        skill._thetas = list(np.asarray(state['thetas'], dtype=float).reshape(-1,
                                                                              skill.theta_dim))
        if not len(skill._taus) == len(skill._thetas) == skill.readout.num_samples:
            raise ValueError(f'skill {name!r}: {len(skill._taus)} samples stored but the '
                             f'readout learned {skill.readout.num_samples}')
        return skill
