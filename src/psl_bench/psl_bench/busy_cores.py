"""Load for the benchmarks: cores kept busy by spinning processes, ended by PID. Imports no
ROS."""
from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def busy_cores(count: int) -> Iterator[list[int]]:
    """`count` processes that each keep a core busy (``while True: pass``); yields their PIDs
    and ends exactly those (SIGKILL by PID) on leaving."""
    processes = []
    try:
        for _ in range(count):
            processes.append(subprocess.Popen([sys.executable, '-c', 'while True: pass']))
        yield [p.pid for p in processes]
    finally:
        for process in processes:
            process.kill()
            process.wait()
