"""Associative skill memory (PSM, section "AELM and ARBF as Parameterized Skill Memories").

An associative memory stores patterns ``v = [tau, theta]`` (E + F dimensions) and learns an
auto-associative map ``v -> v_hat`` (eq. 2.20-2.21 for the AELM, eq. 2.22 for the ARBF). Recall
turns the map into a dynamical system, ``v_{t+1} <- v_hat(v_t)``, whose stable attractors lie on
the stored data; clamping the known dimensions after every step completes a partial pattern in
either direction (tau -> theta and theta -> tau).

Every memory works in normalised coordinates ``u = scaler.to_unit(v)`` (each dimension of v
mapped from its range to [-1, 1]), so that dimensions with different units weigh alike and the
convergence tolerance is one number. Imports no ROS.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Callable

import numpy as np

from psl_memory.elm import RangeScaler


def modality_slices(modality_sizes: tuple[int, ...] | None, dim: int) -> list[slice]:
    """Slices of v for each modality; None means one modality over all ``dim`` entries.

    Raises:
        ValueError: sizes that are not positive integers or do not add up to ``dim``.
    """
    if modality_sizes is None:
        return [slice(0, dim)]
    sizes = tuple(modality_sizes)
    if not sizes or any(int(s) != s or s < 1 for s in sizes):
        raise ValueError(f'modality_sizes must be positive integers, got {modality_sizes}')
    if sum(sizes) != dim:
        raise ValueError(f'modality_sizes {sizes} must add up to the pattern size {dim}')
    bounds = np.cumsum((0,) + sizes)
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def state_arrays(state: dict, shapes: dict[str, tuple]) -> dict[str, np.ndarray]:
    """Finite float copies of ``state[key]`` for each key of `shapes`, each of its shape (an
    entry None: any length), for `AssociativeMemory.set_state`.

    Raises:
        ValueError: a key is missing, or an array has another shape or non-finite values.
    """
    arrays = {}
    for key, shape in shapes.items():
        if key not in state:
            raise ValueError(f'state lacks {key!r}')
        value = np.array(state[key], dtype=float)
        if value.ndim != len(shape) or any(s is not None and s != t
                                           for s, t in zip(shape, value.shape)):
            raise ValueError(f'state[{key!r}] has shape {value.shape}, expected {shape}')
        if not np.all(np.isfinite(value)):
            raise ValueError(f'state[{key!r}] is not finite')
        arrays[key] = value
    return arrays


@dataclass(frozen=True, eq=False)
class CompletionResult:
    """Outcome of :meth:`AssociativeMemory.complete`.

    Attributes:
        pattern: completed pattern in the caller's units, (D,); the known entries are the
            caller's values, bit for bit.
        converged: True if the last step moved no free dimension by ``tol`` or more.
        iterations: number of recall steps taken, 1 <= iterations <= max_iter.
        residual: max |u_{t+1} - u_t| of the last step, in normalised units.
    """

    pattern: np.ndarray
    converged: bool
    iterations: int
    residual: float


def clamped_recall(step: Callable[[np.ndarray], np.ndarray], u0: np.ndarray,
                   known: np.ndarray, tol: float, max_iter: int
                   ) -> tuple[np.ndarray, bool, int, float]:
    """Iterate ``u <- step(u)`` with the ``known`` entries of ``u0`` clamped after every step.

    The shared recall loop of all associative memories (network dynamics ``v_{t+1} <- v_hat_t``
    with fixed modalities or dimensions). Runs until the largest change of a free entry is
    below ``tol`` or ``max_iter`` steps are taken. Inputs are not validated here.

    Args:
        step: one step of the memory, (D,) -> (D,), in normalised units.
        u0: start state (D,); its known entries stay fixed, the others are the initial guess.
        known: boolean mask (D,).
        tol: convergence threshold on max |u_{t+1} - u_t|.
        max_iter: largest number of steps (>= 1).

    Returns:
        (u, converged, iterations, residual) with u (D,) the final state.
    """
    u = np.array(u0, dtype=float)                  # (D,)
    clamp = u[known].copy()                        # (n_known,)
    residual = np.inf
    iterations = 0
    while iterations < max_iter:
        u_next = np.asarray(step(u), dtype=float)  # (D,)
        u_next[known] = clamp
        residual = float(np.max(np.abs(u_next - u)))
        u = u_next
        iterations += 1
        if residual < tol:
            break
    return u, bool(residual < tol), iterations, residual


class AssociativeMemory(ABC):
    """Base class: pattern checks, one-step prediction and clamped recall in normalised units.

    Subclasses implement the one-step map :meth:`_step_unit` (eq. 2.21 / 2.22) and the
    bookkeeping of :meth:`add`, :attr:`num_patterns`, :meth:`get_state`, :meth:`set_state`.

    Args:
        scaler: ranges of the D = E + F entries of v; every entry is normalised to [-1, 1].
    """

    def __init__(self, scaler: RangeScaler):
        if not isinstance(scaler, RangeScaler):
            raise ValueError(f'scaler must be a RangeScaler, got {type(scaler).__name__}')
        self.scaler = scaler

    @property
    def dim(self) -> int:
        """D = E + F, the number of entries of a pattern v."""
        return self.scaler.dim

    @property
    @classmethod
    @abstractmethod
    def from_config(cls, scaler: RangeScaler, modality_sizes: tuple[int, int],
                    config) -> 'AssociativeMemory':
        """The memory a `psl_memory.skill_config.SkillConfig` asks for, over v = [tau, theta]
        with the given ranges and modality sizes (E, F)."""

    @abstractmethod
    def num_patterns(self) -> int:
        """Number of stored training patterns."""

    @abstractmethod
    def add(self, v: np.ndarray) -> None:
        """Store one pattern v (D,) or several (n, D) and update the map."""

    @abstractmethod
    def get_state(self) -> dict:
        """Everything learned, as numpy arrays and Python scalars."""

    @abstractmethod
    def set_state(self, state: dict) -> None:
        """Restore :meth:`get_state` into a memory built with the same constructor arguments."""

    @abstractmethod
    def _step_unit(self, u: np.ndarray) -> np.ndarray:
        """One step v_hat(v) in normalised units: (n, D) -> (n, D). Memory is non-empty."""

    # -- checks ---------------------------------------------------------------------------------
    def _check_patterns(self, v, name: str = 'pattern') -> np.ndarray:
        """v as a float array (n, D); ValueError on a wrong size or non-finite entries."""
        v = np.asarray(v, dtype=float)
        if v.ndim not in (1, 2) or v.shape[-1] != self.dim or v.size == 0:
            raise ValueError(f'{name} must have shape ({self.dim},) or (n, {self.dim}), '
                             f'got {v.shape}')
        if not np.all(np.isfinite(v)):
            raise ValueError(f'{name} must be finite, got {v}')
        return np.atleast_2d(v)

    def _require_patterns(self) -> None:
        if self.num_patterns == 0:
            raise RuntimeError(f'{type(self).__name__} is empty: add patterns before recall')

    # -- recall ---------------------------------------------------------------------------------
    def predict(self, v: np.ndarray) -> np.ndarray:
        """One step of the network, v_hat(v) (eq. 2.21 / 2.22), in the caller's units.

        Args:
            v: pattern (D,) or patterns (n, D).

        Returns:
            v_hat of the same shape.

        Raises:
            ValueError: wrong size or non-finite input.
            RuntimeError: no pattern stored yet.
        """
        single = np.ndim(v) == 1
        v2 = self._check_patterns(v)                          # (n, D)
        self._require_patterns()
        v_hat = self.scaler.from_unit(self._step_unit(self.scaler.to_unit(v2)))  # (n, D)
        return v_hat[0] if single else v_hat

    def complete(self, pattern: np.ndarray, known, tol: float = 1e-6,
                 max_iter: int = 200) -> CompletionResult:
        """Complete a partial pattern by clamped recall, ``v_{t+1} <- v_hat(v_t)``.

        Starts from ``pattern`` (its unknown entries are the initial guess), clamps the known
        entries after every step and stops once max |u_{t+1} - u_t| < tol (normalised units)
        or after ``max_iter`` steps. The known entries of the result equal the given ones
        exactly.

        Args:
            pattern: (D,) start pattern in the caller's units.
            known: boolean mask (D,), True where the entry is given and held fixed.
            tol: convergence threshold (> 0), normalised units.
            max_iter: largest number of steps (>= 1).

        Returns:
            :class:`CompletionResult`.

        Raises:
            ValueError: pattern of the wrong size or non-finite, mask of the wrong length or not
                boolean, no known entry, tol <= 0 or max_iter < 1.
            RuntimeError: no pattern stored yet.
        """
        pattern = np.asarray(pattern, dtype=float)
        if pattern.shape != (self.dim,):
            raise ValueError(f'pattern must have shape ({self.dim},), got {pattern.shape}')
        if not np.all(np.isfinite(pattern)):
            raise ValueError(f'pattern must be finite, got {pattern}')
        known = np.asarray(known)
        if known.shape != (self.dim,):
            raise ValueError(f'known must be a boolean mask of length {self.dim}, '
                             f'got shape {known.shape}')
        if known.dtype != bool:
            raise ValueError(f'known must be a boolean mask, got dtype {known.dtype}')
        if not np.any(known):
            raise ValueError('known must mark at least one entry of the pattern as given')
        if not (np.isfinite(tol) and tol > 0):
            raise ValueError(f'tol must be > 0, got {tol}')
        if not float(max_iter).is_integer() or max_iter < 1:
            raise ValueError(f'max_iter must be an integer >= 1, got {max_iter}')
        self._require_patterns()

        def step(u: np.ndarray) -> np.ndarray:                 # (D,) -> (D,)
            return self._step_unit(u[None, :])[0]

        u, converged, iterations, residual = clamped_recall(
            step, self.scaler.to_unit(pattern), known, float(tol), int(max_iter))
        result = self.scaler.from_unit(u)                       # (D,)
        result[known] = pattern[known]                          # exact, no round trip
        return CompletionResult(result, converged, iterations, residual)

    # -- persistence helpers --------------------------------------------------------------------
    def _scaler_state(self) -> dict:
        return {'scaler_low': self.scaler.low.copy(), 'scaler_high': self.scaler.high.copy()}

    def _check_state_matches(self, state: dict, expected: dict) -> None:
        """ValueError unless ``state`` has every key of ``expected`` with an equal value."""
        expected = {**self._scaler_state(), **expected}
        for key, value in expected.items():
            if key not in state:
                raise ValueError(f'state lacks {key!r}')
            if not np.array_equal(np.asarray(state[key]), np.asarray(value)):
                raise ValueError(f'state was saved with {key}={state[key]!r}, this memory has '
                                 f'{value!r}; build it with the same constructor arguments')
