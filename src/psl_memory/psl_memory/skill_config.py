"""Hyper-parameters of a parameterized skill, one dataclass: every default in one place.

The skill_memory node declares its ROS parameters from these fields; memory files store them.
Imports no ROS.
"""
from __future__ import annotations

import dataclasses

from psl_memory.registry import ASSOCIATIVE_MEMORIES, READOUTS


@dataclasses.dataclass(frozen=True)
class SkillConfig:
    """Hyper-parameters of a skill (the skill_memory node's ROS parameters)."""

    readout: str = 'bayes'          # a name of psl_memory.registry.READOUTS
    n_hidden: int = 100
    regularization: float = 1e-3     # ridge factor; the Bayesian prior precision alpha
    forgetting: float = 1.0          # RLS only, 0 < lambda <= 1
    seed: int = 0
    alpha: float = 1.0               # slope of the hidden sigmoid (eq. 2.2), not a precision
    # aelm: O(1) per sample; arbf: one centre per sample; rbm, hopfield: baselines
    # (docs/benchmarks.md, psl bench memories)
    associative: str = 'aelm'
    # bayes: evidence maximisation of alpha and beta. Off by default: with few samples it
    # shrinks PS towards the default policy (docs/benchmarks.md, psl bench learn)
    estimate_precisions: bool = False
    noise_precision: float = 1.0     # bayes: beta (the initial value when estimated)
    completion_tolerance: float = 1e-6    # recall stops when no entry moves more (normalised)
    completion_max_iterations: int = 200

    def __post_init__(self):
        if self.readout not in READOUTS:
            raise ValueError(f'unknown readout {self.readout!r}; known: {", ".join(READOUTS)}')
        if self.associative not in ASSOCIATIVE_MEMORIES:
            raise ValueError(f'unknown associative memory {self.associative!r}; known: '
                             f'{", ".join(ASSOCIATIVE_MEMORIES)}')
        if not 0.0 < self.forgetting <= 1.0:
            raise ValueError(f'forgetting must be in (0, 1], got {self.forgetting}')
        if int(self.n_hidden) < 1:
            raise ValueError('n_hidden must be >= 1')

