"""Vectors (theta) from files, for the commands that take ``--theta-file``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def load_vector(path: str | Path) -> np.ndarray:
    """A flat vector from a .npy, a .json list or a whitespace-separated text file.

    Raises:
        OSError: the file cannot be read; ValueError: it holds no numbers.
    """
    file = Path(path)
    if file.suffix == '.npy':
        return np.load(file, allow_pickle=False).ravel().astype(float)
    if file.suffix == '.json':
        return np.asarray(json.loads(file.read_text()), dtype=float).ravel()
    return np.loadtxt(file, ndmin=1).ravel()
