"""The options several ``psl`` commands share, each defined once, and the checks of their values.

Every bad value is refused by argparse (one usage line and one error line, exit code 2) or by
a ``ValueError`` whose message is the one line the command prints (`fail`). This module imports
nothing heavy: the parser of every command is built from it.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from psl_task import DEFAULT_TASK  # noqa: F401 - light: psl_task's __init__ imports nothing


# -- values -----------------------------------------------------------------------------------
def _integer(text: str, low: int, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a whole number') from None
    if value < low:
        raise argparse.ArgumentTypeError(f'must be {what}, got {value}')
    return value


def positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1 (a count of tasks, seeds, runs)."""
    return _integer(text, 1, '1 or more')


def non_negative_int(text: str) -> int:
    """An argparse type: a whole number >= 0."""
    return _integer(text, 0, '0 or more')


SEED_LIMIT = 2**32      # a seed travels as uint32 (LearnSkill.seed) and seeds numpy as such


def seed(text: str) -> int:
    """An argparse type: a seed, a whole number in [0, 2^32) (one that cannot be represented
    is refused, not wrapped)."""
    value = _integer(text, 0, '0 or more')
    if value >= SEED_LIMIT:
        raise argparse.ArgumentTypeError(f'must be below 2^32 = {SEED_LIMIT}, got {value}')
    return value


def k_of_n(text: str) -> tuple[int, int]:
    """An argparse type: K/N, whole numbers with 1 <= K <= N (K of N rollouts)."""
    k, sep, n = text.partition('/')
    if not (sep and k.isdigit() and n.isdigit() and 1 <= int(k) <= int(n)):
        raise argparse.ArgumentTypeError(f'give K/N with whole numbers 1 <= K <= N, got '
                                         f'{text!r}')
    return int(k), int(n)


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0 (a timeout in seconds)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if not 0.0 < value < float('inf'):
        raise argparse.ArgumentTypeError(f'must be a number > 0, got {text}')
    return value


def non_negative_float(text: str) -> float:
    """An argparse type: a finite number >= 0 (a rate, 0 = unlimited)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if not 0.0 <= value < float('inf'):
        raise argparse.ArgumentTypeError(f'must be a finite number >= 0, got {text}')
    return value


def port(text: str) -> int:
    """An argparse type: a TCP port, 0..65535 (0 = a free one)."""
    value = _integer(text, 0, '0 or more')
    if value > 65535:
        raise argparse.ArgumentTypeError(f'a TCP port is 0..65535, got {value}')
    return value


VIEW_PORT_VARIABLE = 'PSL_VIEW_PORT'    # environment: the view's port when none is given
THE_DEFAULT_PORT = -1                   # `--view` without a value: resolved by `view_port`


def view_port(given: int | None) -> int:
    """The view's TCP port: `given`, else ``$PSL_VIEW_PORT``, else the Foxglove app's default
    (8765). Two graphs on one machine keep apart by ``ROS_DOMAIN_ID`` and this variable.

    Raises:
        ValueError: ``$PSL_VIEW_PORT`` is no TCP port
    """
    from psl_ros.view_parameters import DEFAULT_PORT

    if given is not None and given != THE_DEFAULT_PORT:
        return given
    text = os.environ.get(VIEW_PORT_VARIABLE)
    if text is None:
        return DEFAULT_PORT
    try:
        return port(text)
    except argparse.ArgumentTypeError as exc:
        raise ValueError(f'${VIEW_PORT_VARIABLE}={text!r}: {exc}') from None


def output_folder(path: str | Path) -> Path:
    """The folder `path` (absolute), created with its parents if missing.

    Raises:
        ValueError: `path` or one of its parents is a file, or the folder cannot be created
        (the message says which and why).
    """
    folder = Path(path).expanduser().resolve()
    try:
        existing = next(p for p in (folder, *folder.parents) if p.exists())
        if not existing.is_dir():
            what = ('is a file' if existing == folder
                    else f'cannot be created: {existing} is a file')
            raise ValueError(f'the folder {folder} {what}')
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f'the folder {folder} cannot be created: '
                         f'{exc.strerror or exc}') from None
    return folder


def output_file(path: str | Path) -> Path:
    """The file `path` (absolute) to write, in a folder that exists.

    Raises:
        ValueError: `path` is a folder, or its folder is missing or a file.
    """
    file = Path(path).expanduser().resolve()
    try:
        if file.is_dir():
            raise ValueError(f'{file} is a folder, not a file')
        if not file.parent.is_dir():
            state = 'is a file' if file.parent.exists() else 'does not exist'
            raise ValueError(f'cannot write {file}: the folder {file.parent} {state}')
    except OSError as exc:
        raise ValueError(f'cannot write {file}: {exc.strerror or exc}') from None
    return file


def fail(command: str, message: object, code: int) -> int:
    """Print `message` as the one line ``<command>: <message>`` on stderr; return `code`."""
    text = ' '.join(str(message).split()) or type(message).__name__
    print(f'{command}: {text}', file=sys.stderr, flush=True)
    return code


# -- options ----------------------------------------------------------------------------------
def add_task(parser: argparse.ArgumentParser, default: str = DEFAULT_TASK) -> None:
    """``--task``: a task name or a task YAML path."""
    parser.add_argument('--task', default=default,
                        help=f'task name or YAML path (default {default})')


def add_tau(parser: argparse.ArgumentParser, required: bool = False) -> None:
    """``--tau``: the task parameters."""
    parser.add_argument('--tau', type=float, nargs='+', required=required,
                        help='task parameters' + ('' if required else
                                                  ' (default: the task defaults)'))


def add_theta_file(parser: argparse.ArgumentParser,
                   default: str = "the demonstration's fit") -> None:
    """``--theta-file``: a policy vector in a file (`psl_cli.vectors.load_vector`)."""
    parser.add_argument('--theta-file', metavar='FILE',
                        help='theta from a .npy, a .json list or whitespace-separated text'
                        + (f'; default: {default}' if default else ''))


def add_out(parser: argparse.ArgumentParser, help: str, default: str | None = None) -> None:
    """``-o/--out``: where a command writes (a folder or a file, as `help` says)."""
    parser.add_argument('-o', '--out', default=default, help=help)


def add_graph(parser: argparse.ArgumentParser, timeout: float, waits_for: str) -> None:
    """``--namespace`` and ``--timeout`` of a command that talks to the running graph."""
    parser.add_argument('--namespace', default='',
                        help="the graph's namespace (as given to psl up; default: none)")
    parser.add_argument('--timeout', type=positive_float, default=timeout,
                        help=f'seconds to wait for {waits_for}, default {timeout:g}; with no '
                        'graph up the command ends after it, naming what is missing')
