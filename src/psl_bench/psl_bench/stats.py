"""Statistics over seeds, the same in every benchmark report."""
from __future__ import annotations

import statistics
from typing import Sequence

import numpy as np


def over_seeds(values: Sequence[float]) -> dict:
    """Mean, sample standard deviation (0 for one value), min, max and the values."""
    values = np.asarray(values, dtype=float)
    return {'mean': float(values.mean()),
            'sd': float(values.std(ddof=1)) if values.size > 1 else 0.0,
            'min': float(values.min()), 'max': float(values.max()),
            'values': values.tolist()}


def mean_sd(values: Sequence[float]) -> str:
    """'mean ± sd' with two decimals ('-' for no value, the value alone for one)."""
    values = [float(v) for v in values]
    if len(values) < 2:
        return f'{values[0]:.2f}' if values else '-'
    return f'{statistics.mean(values):.2f} ± {statistics.stdev(values):.2f}'
