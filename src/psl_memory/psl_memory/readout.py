"""Linear readouts ``PS(tau) = W_out^T h(tau)`` of the parameterized skill (eq. 2.1, 2.3-2.4).

Every readout learns the weights ``W`` (N_H, F) that map hidden states ``h`` (N_H,) of the ELM
(`psl_memory.elm.ELMFeatures`) to outputs (F,). They share one interface, `Readout`:

- ``update(h, y)`` adds one sample (``h`` (N_H,), ``y`` (F,)) or a chunk (``h`` (n, N_H),
  ``y`` (n, F)). Inputs are validated first; an update either completes or raises and leaves the
  readout exactly as it was.
- ``predict(h)`` gives (F,) for one hidden state or (n, F) for a chunk; ``predict_variance(h)``
  the per-output predictive variance in the same shape, or None when the readout has none.
- ``get_state()`` / ``set_state(state)`` round-trip the learned state exactly; the dict holds only
  numpy arrays and Python scalars, so ``numpy.savez`` can store it (0-d arrays read back from
  such a file are accepted where a scalar is expected).

The implementations (batch ridge, recursive least squares, incremental ridge, Bayesian linear
regression) live in their own modules, each with ``from_config`` (the readout a `SkillConfig`
asks for); `psl_memory.registry.READOUTS` names them. Imports no ROS.
"""
from __future__ import annotations

import abc
from typing import Any, ClassVar

import numpy as np

State = dict[str, 'np.ndarray | float | int']


def check_positive(name: str, value: float) -> float:
    """``value`` as a float, or ValueError when it is not finite and > 0."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a number, got {value!r}') from None
    if not (np.isfinite(value) and value > 0.0):
        raise ValueError(f'{name} must be finite and > 0, got {value}')
    return value


class Readout(abc.ABC):
    """Common interface and input checks of the linear readouts.

    Args:
        n_hidden: number of hidden states N_H (inputs of the readout).
        n_out: number of outputs F.

    Subclasses compute an update as a dict of new attribute values (`_compute_update`) which is
    committed only after every array in it was found finite, so a failed update changes nothing.
    """

    name: ClassVar[str]

    @classmethod
    @abc.abstractmethod
    def from_config(cls, n_hidden: int, n_out: int, config) -> 'Readout':
        """The readout with the hyper-parameters of a `psl_memory.skill_config.SkillConfig`."""

    def __init__(self, n_hidden: int, n_out: int):
        self.n_hidden = _check_size('n_hidden', n_hidden)
        self.n_out = _check_size('n_out', n_out)
        self._w = np.zeros((self.n_hidden, self.n_out))    # (N_H, F) readout weights
        self._n = 0                                          # samples seen

    # ------------------------------------------------------------------ public interface
    @property
    def num_samples(self) -> int:
        """Number of training samples seen so far."""
        return self._n

    @property
    def weights(self) -> np.ndarray:
        """Copy of the current readout weights W (N_H, F); ``predict(h) = h @ W``."""
        return self._w.copy()

    def update(self, h: np.ndarray, y: np.ndarray) -> None:
        """Learn from one sample (h (N_H,), y (F,)) or a chunk (h (n, N_H), y (n, F)).

        Raises:
            ValueError: shapes do not fit, values are not finite, or the update itself produced
                non-finite numbers. The state is unchanged in every case.
        """
        hs, ys = self._check_samples(h, y)       # (n, N_H), (n, F)
        self._commit(self._compute_update(hs, ys), 'update')

    def predict(self, h: np.ndarray) -> np.ndarray:
        """Predictive mean (F,) for h (N_H,), or (n, F) for h (n, N_H) (eq. 2.1)."""
        hs, single = self._check_inputs(h)       # (n, N_H)
        out = hs @ self._w                       # (n, F)
        return out[0] if single else out

    def predict_variance(self, h: np.ndarray) -> np.ndarray | None:
        """Per-output predictive variance in the shape of `predict`, or None if the readout has
        no probabilistic model. The input is validated either way."""
        self._check_inputs(h)
        return None

    @abc.abstractmethod
    def get_state(self) -> State:
        """Everything learned, as numpy arrays and Python scalars (copies)."""

    def set_state(self, state: State) -> None:
        """Restore a state from `get_state` of a readout of the same kind and sizes.

        Raises:
            ValueError: keys missing or unknown, sizes or shapes differ, values invalid. The
                state is unchanged in that case.
        """
        if not isinstance(state, dict):
            raise ValueError(f'state must be a dict, got {type(state).__name__}')
        expected = set(self.get_state())
        missing, unknown = expected - set(state), set(state) - expected
        if missing or unknown:
            raise ValueError(f'{self.name} state: missing keys {sorted(missing)}, '
                             f'unknown keys {sorted(unknown)}')
        for key, own in (('n_hidden', self.n_hidden), ('n_out', self.n_out)):
            if _as_int(state, key) != own:
                raise ValueError(f'state has {key}={state[key]}, this readout has {own}')
        self._commit(self._parse_state(state), 'set_state')

    # ------------------------------------------------------------------ for subclasses
    @abc.abstractmethod
    def _compute_update(self, hs: np.ndarray, ys: np.ndarray) -> dict[str, Any]:
        """New attribute values after learning hs (n, N_H), ys (n, F); must not modify self."""

    @abc.abstractmethod
    def _parse_state(self, state: State) -> dict[str, Any]:
        """New attribute values from a validated-key state dict; must not modify self."""

    def _header(self) -> State:
        return {'n_hidden': self.n_hidden, 'n_out': self.n_out, 'num_samples': self._n}

    def _commit(self, new: dict[str, Any], what: str) -> None:
        for key, value in new.items():
            if isinstance(value, np.ndarray) and not np.all(np.isfinite(value)):
                raise ValueError(f'{self.name} {what} produced non-finite values in {key}; '
                                 'state left unchanged')
        for key, value in new.items():
            setattr(self, key, value)

    def _check_inputs(self, h: np.ndarray) -> tuple[np.ndarray, bool]:
        """h as (n, N_H) floats and whether it was a single sample."""
        hs = _as_float_array('h', h)
        single = hs.ndim == 1
        if hs.ndim not in (1, 2) or hs.shape[-1] != self.n_hidden:
            raise ValueError(f'h must have shape ({self.n_hidden},) or (n, {self.n_hidden}), '
                             f'got {hs.shape}')
        if not np.all(np.isfinite(hs)):
            raise ValueError('h contains NaN or inf')
        return (hs[None, :] if single else hs), single

    def _check_samples(self, h: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """h (n, N_H) and y (n, F) as float arrays, with n >= 1 and all values finite."""
        hs, single = self._check_inputs(h)
        ys = _as_float_array('y', y)
        if single:
            if ys.shape != (self.n_out,):
                raise ValueError(f'for a single h of shape ({self.n_hidden},) y must have shape '
                                 f'({self.n_out},), got {ys.shape}')
            ys = ys[None, :]
        elif ys.shape != (hs.shape[0], self.n_out):
            raise ValueError(f'for h of shape {hs.shape} y must have shape '
                             f'({hs.shape[0]}, {self.n_out}), got {ys.shape}')
        if hs.shape[0] == 0:
            raise ValueError('a chunk needs at least one sample')
        if not np.all(np.isfinite(ys)):
            raise ValueError('y contains NaN or inf')
        return hs, ys


# ---------------------------------------------------------------------- state helpers
def state_array(state: State, key: str, shape: tuple[int, ...]) -> np.ndarray:
    """Finite float copy of ``state[key]`` with the given shape, else ValueError."""
    value = _as_float_array(key, state[key]).copy()
    if value.shape != shape:
        raise ValueError(f'state {key} must have shape {shape}, got {value.shape}')
    if not np.all(np.isfinite(value)):
        raise ValueError(f'state {key} contains NaN or inf')
    return value


def state_positive(state: State, key: str) -> float:
    """``state[key]`` (a Python or 0-d numpy number) as a finite float > 0."""
    return check_positive(f'state {key}', _as_scalar(state, key))


def state_count(state: State, key: str, minimum: int = 0) -> int:
    """``state[key]`` as an int >= minimum."""
    value = _as_int(state, key)
    if value < minimum:
        raise ValueError(f'state {key} must be >= {minimum}, got {value}')
    return value


def state_bool(state: State, key: str) -> bool:
    value = _as_scalar(state, key)
    if value not in (0, 1):
        raise ValueError(f'state {key} must be a bool, got {value!r}')
    return bool(value)


def _as_scalar(state: State, key: str) -> Any:
    value = state[key]
    if isinstance(value, np.ndarray):
        if value.shape != ():
            raise ValueError(f'state {key} must be a scalar, got shape {value.shape}')
        value = value.item()
    return value


def _as_int(state: State, key: str) -> int:
    value = _as_scalar(state, key)
    if isinstance(value, (bool, np.bool_)) or not float(value).is_integer():
        raise ValueError(f'state {key} must be an integer, got {value!r}')
    return int(value)


def _as_float_array(name: str, value: Any) -> np.ndarray:
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be numeric, got {type(value).__name__}') from None


def _check_size(name: str, value: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or value < 1:
        raise ValueError(f'{name} must be an integer >= 1, got {value!r}')
    return int(value)
