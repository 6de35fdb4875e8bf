"""Reading a rosbag2 bag with ``rosbags``: a bag that cannot be read is one `BagError` naming it.

A bag cut short (a recorder killed before it wrote the MCAP footer), damaged on disk, empty,
or not a bag at all makes ``rosbags`` and the MCAP and CDR parsers below it raise many kinds
of exception (``ReaderError``, ``struct.error``, ``OverflowError``, ``MemoryError`` for a
length field read from random bytes, ...). `open_bag` turns each into a `BagError` (a
``ValueError``: the command line prints it as one line) that names the bag and says what was
wrong, so no reader of bags (``psl teach``, `psl_optimizer.teaching`, the recorder's summary)
ends in a traceback. Imports no ROS: the pure readers use it.
"""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator


class BagError(ValueError):
    """A bag that cannot be read, or not as asked (no such topic, a topic of another type);
    the message names the bag."""


def why(exc: BaseException) -> str:
    """One line of what reading raised: its message, its kind where the message alone does not
    say (``MemoryError`` has none)."""
    text = ' '.join(str(exc).split())
    if type(exc).__name__ == 'ReaderError':         # rosbags' own: its message says it
        return text or 'ReaderError'
    return f'{type(exc).__name__}: {text}' if text else type(exc).__name__


@contextlib.contextmanager
def open_bag(path: str | Path) -> Iterator:
    """``rosbags.rosbag2.Reader`` of the bag folder `path`, open for the block. Whatever opening
    or reading it raises inside the block becomes one `BagError` naming the bag (a `BagError`
    raised inside passes unchanged: raise those for refusals of your own).

    Raises:
        BagError: no such bag, not a bag folder, or a bag that is damaged, cut short or empty.
    """
    from rosbags.rosbag2 import Reader

    bag = Path(path)
    try:
        if not bag.exists():
            raise BagError(f'{bag}: no such bag')
        with Reader(bag) as reader:
            yield reader
    except BagError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags and its MCAP/CDR parsers raise many kinds
        raise BagError(f'{bag}: not a readable rosbag2 bag, damaged, cut short or empty '
                       f'({why(exc)})') from exc
