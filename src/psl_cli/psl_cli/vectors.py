"""Vectors (theta) from files, for the commands that take ``--theta-file``."""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

NPY_MAGIC = b'\x93NUMPY'        # the first bytes of an .npy file (numpy.lib.format)


def load_vector(path: str | Path) -> np.ndarray:
    """A flat vector of finite floats from a file: an .npy array (any shape, flattened); JSON
    (a list, nested lists flattened, or an object with a ``theta`` list: what ``psl query
    --json`` prints); ``psl query``'s text (its ``theta: [...]`` line); or whitespace-separated
    numbers (``#`` starts a comment). What the content is, not the name, decides: an .npz
    archive (several named arrays, `np.savez`) is refused.

    Raises:
        ValueError: the file is missing, a directory, unreadable, an .npz archive, not of its
            kind, empty or not all finite numbers; the message names the file and says which.
    """
    file = Path(path)
    data = read_bytes(file)
    if zipfile.is_zipfile(file):
        raise ValueError(f'{file} is an .npz archive (several named arrays); save the one '
                         'vector with np.save (.npy), as a .json list or as text')
    try:
        if data.startswith(NPY_MAGIC):
            vector = np.load(file, allow_pickle=False)
        elif file.suffix == '.npy':
            raise ValueError('not an .npy file (no NumPy header)')
        else:
            vector = _from_text(data.decode())
        vector = np.asarray(vector, dtype=float).ravel()
    except UnicodeDecodeError:
        raise ValueError(f'{file} is not text (and not an .npy file)') from None
    except (ValueError, TypeError, EOFError) as exc:
        raise ValueError(f'{file} holds no vector of numbers: {exc}') from None
    if vector.size == 0:
        raise ValueError(f'{file} holds no numbers')
    if not np.all(np.isfinite(vector)):
        raise ValueError(f'{file} holds values that are not finite (NaN or inf)')
    return vector


def read_bytes(path: str | Path) -> bytes:
    """The content of a file a command reads.

    Raises:
        ValueError: the file is missing, a directory or unreadable; the message names it.
    """
    file = Path(path)
    try:
        if file.is_dir():
            raise ValueError(f'{file} is a directory, not a file')
        with open(file, 'rb') as f:
            return f.read()
    except FileNotFoundError:
        raise ValueError(f'{file}: no such file') from None
    except OSError as exc:
        raise ValueError(f'{file} cannot be read: {exc.strerror or exc}') from None


def load_rows(path: str | Path) -> list[np.ndarray]:
    """The rows of numbers of a text file, one per line (whitespace-separated; blank lines
    and ``#`` comments skipped): ``psl teach --tau-file``'s task instances.

    Raises:
        ValueError: the file is missing, a directory, unreadable, not text, holds a word that
            is not a finite number (its line named) or no numbers at all; the message names
            the file.
    """
    file = Path(path)
    try:
        text = read_bytes(file).decode()
    except UnicodeDecodeError:
        raise ValueError(f'{file} is not text') from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        words = line.split('#', 1)[0].split()
        try:
            row = np.array([float(word) for word in words])
        except ValueError as exc:
            raise ValueError(f'{file}, line {number}: {exc}') from None
        if not np.all(np.isfinite(row)):
            raise ValueError(f'{file}, line {number}: values that are not finite (NaN or inf)')
        if words:
            rows.append(row)
    if not rows:
        raise ValueError(f'{file} holds no numbers')
    return rows


def _from_text(text: str):
    """The numbers of a text file (`load_vector`): JSON, psl query's ``theta:`` line, or
    whitespace-separated numbers."""
    stripped = text.strip()
    if stripped[:1] in ('[', '{'):
        value = json.loads(stripped)
        if isinstance(value, dict):
            if 'theta' not in value:
                raise ValueError(f"a JSON object without 'theta' (keys: {', '.join(value)})")
            value = value['theta']
        return value
    for line in text.splitlines():
        if line.startswith('theta:'):                 # psl query's text answer
            return json.loads(line.split(':', 1)[1])
    return [float(word) for line in text.splitlines()
            for word in line.split('#', 1)[0].split()]
