"""The skill's interchangeable parts by name: readouts and associative memories.

Each registry maps the name a `SkillConfig` (and the skill_memory node's parameters) uses to
the class; every class builds itself from a config (``from_config``), so adding a readout or a
memory is one class and one entry here. Imports no ROS.
"""
from __future__ import annotations

from psl_memory.aelm import AELM
from psl_memory.arbf import ARBF
from psl_memory.associative_memory import AssociativeMemory
from psl_memory.bayesian_linear_regression import BayesianLinearRegression
from psl_memory.hopfield import Hopfield
from psl_memory.incremental_ridge import IncrementalRidge
from psl_memory.rbm import RBM
from psl_memory.readout import Readout
from psl_memory.recursive_least_squares import RecursiveLeastSquares
from psl_memory.ridge_regression import RidgeReadout

READOUTS: dict[str, type[Readout]] = {cls.name: cls for cls in (
    RidgeReadout, RecursiveLeastSquares, IncrementalRidge, BayesianLinearRegression)}

# the parameterized skill memories (PSM) of the chapter, and the textbook baselines beside them
# (coarser completion: docs/benchmarks.md, psl bench memories)
ASSOCIATIVE: dict[str, type[AssociativeMemory]] = {'aelm': AELM, 'arbf': ARBF}
BASELINE_ASSOCIATIVE: dict[str, type[AssociativeMemory]] = {'rbm': RBM, 'hopfield': Hopfield}
ASSOCIATIVE_MEMORIES = {**ASSOCIATIVE, **BASELINE_ASSOCIATIVE}


def make_readout(name: str, n_hidden: int, n_out: int, **options) -> Readout:
    """The readout called `name` with its constructor's keyword `options` (e.g.
    ``regularization``, ``forgetting``, ``prior_precision``).

    Raises:
        ValueError: unknown name, or an invalid option value.
        TypeError: an option the readout does not take.
    """
    if name not in READOUTS:
        raise ValueError(f'unknown readout {name!r}; known: {", ".join(sorted(READOUTS))}')
    return READOUTS[name](n_hidden, n_out, **options)
