"""Hyper-parameters of a parameterized skill, one dataclass: every default in one place.

The skill_memory node declares its ROS parameters from these fields; memory files store them.
Imports no ROS.
"""
from __future__ import annotations

import dataclasses
from dataclasses import field

from psl_memory.registry import ASSOCIATIVE_MEMORIES, READOUTS


@dataclasses.dataclass(frozen=True)
class SkillConfig:
    """Hyper-parameters of a skill (the skill_memory node's ROS parameters)."""

    readout: str = field(default='bayes', metadata={'doc': (
        'the linear readout: ridge | rls | incremental_ridge | bayes (psl_memory.registry)')})
    n_hidden: int = field(default=100, metadata={'doc': 'hidden neurons of the ELM (eq. 2.2)'})
    regularization: float = field(default=1e-3, metadata={'doc': (
        'ridge factor; the Bayesian prior precision alpha')})
    forgetting: float = field(default=1.0, metadata={'doc': (
        'RLS forgetting factor lambda, 0 < lambda <= 1')})
    seed: int = field(default=0, metadata={'doc': 'seed of the random hidden layer'})
    alpha: float = field(default=1.0, metadata={'doc': (
        'slope of the hidden sigmoid (eq. 2.2), not a precision')})
    associative: str = field(default='aelm', metadata={'doc': (
        'associative completion of [tau, theta]: aelm (O(1) per sample) | arbf (one centre '
        'per sample); rbm | hopfield: baselines (docs/benchmarks.md, psl bench memories)')})
    estimate_precisions: bool = field(default=False, metadata={'doc': (
        'bayes: evidence maximisation of alpha and beta; off by default: with few samples it '
        'shrinks PS towards the default policy (docs/benchmarks.md, psl bench learn)')})
    noise_precision: float = field(default=1.0, metadata={'doc': (
        'bayes: the noise precision beta (the initial value when estimated)')})
    completion_tolerance: float = field(default=1e-6, metadata={'doc': (
        'recall stops when no entry moves more (normalised units)')})
    completion_max_iterations: int = field(default=200, metadata={'doc': (
        'recall iteration cap')})

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

