"""Stale Fast DDS shared-memory files: found by their lock, removed when nobody holds it.

Fast DDS's shared-memory transport keeps, per participant and per listening port, a segment
``/dev/shm/fastrtps_<name>``, a lock file ``fastrtps_<name>_el`` that its owner holds with an
exclusive ``flock`` for as long as it lives, and for ports a mutex ``sem.fastrtps_<name>_mutex``.
A process that ends without shutting its participant down (SIGKILL, a crash, a node killed
mid-run) leaves them behind, about 0.5 MB each, in RAM until the machine restarts; Fast DDS
only removes them through its ``fastdds shm clean`` tool, which the wheels do not ship.
`remove_stale` does what that tool does: a lock file that can be locked has no live owner, so
it and the files of its name go. Only regular files of this user's that are older than
``min_age`` are touched (not symlinks, devices or FIFOs; a participant that is starting has
made its lock file but may not hold it yet). ``Graph.start`` calls it before every graph it
starts. Imports no ROS.
"""
from __future__ import annotations

import fcntl
import os
import re
import stat
import time
from pathlib import Path

SHM_DIR = Path('/dev/shm')
LOCK_FILE = re.compile(r'fastrtps_[A-Za-z0-9_]+_el')
MIN_AGE = 10.0      # [s] a lock file younger than this may belong to a participant starting


def _own_regular_file(path: Path) -> bool:
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        return False
    return stat.S_ISREG(info.st_mode) and info.st_uid == os.getuid()


def remove_stale(directory: Path | str = SHM_DIR, min_age: float = MIN_AGE) -> list[str]:
    """Remove the Fast DDS shared-memory files in `directory` whose lock no process holds.

    Returns:
        The names removed (lock files, segments, mutexes), sorted; none if the directory does
        not exist.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    removed = []
    now = time.time()
    for entry in sorted(os.listdir(directory)):
        lock_path = directory / entry
        if not LOCK_FILE.fullmatch(entry) or not _own_regular_file(lock_path):
            continue
        try:
            fd = os.open(lock_path, os.O_RDWR | os.O_NOFOLLOW | os.O_NONBLOCK)
        except OSError:
            continue
        try:
            if now - os.fstat(fd).st_mtime < min_age:
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue                          # a live participant holds it
            name = entry[:-len('_el')]
            # held while the files go, so that no participant takes the name meanwhile
            for victim in (name, f'sem.{name}_mutex', entry):
                path = directory / victim
                if _own_regular_file(path):
                    try:
                        path.unlink()
                        removed.append(victim)
                    except OSError:                # gone meanwhile, or not ours to remove
                        pass
        finally:
            os.close(fd)
    return sorted(removed)
