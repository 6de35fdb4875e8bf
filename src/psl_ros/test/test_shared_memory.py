"""Stale Fast DDS shared-memory files go; those of live owners, young ones, links stay."""
import fcntl
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from psl_ros.shared_memory import SHM_DIR, remove_stale

HOLD = ('import fcntl, os, sys, time; fd = os.open(sys.argv[1], os.O_RDWR); '
        'fcntl.flock(fd, fcntl.LOCK_EX); print("held", flush=True); time.sleep(60)')


def read_line(process: subprocess.Popen, timeout: float) -> str:
    """The next line the process writes to its stdout pipe, or AssertionError after `timeout` s
    (a process that hangs before it prints fails the test instead of blocking it)."""
    ready, _, _ = select.select([process.stdout], [], [], timeout)
    assert ready, f'no line from pid {process.pid} within {timeout} s'
    return process.stdout.readline().strip()


@pytest.fixture
def started():
    """The processes a test starts (append each one at once); ended by PID whatever happens:
    SIGINT (a node leaves its shared memory in order), then SIGKILL."""
    processes: list[subprocess.Popen] = []
    try:
        yield processes
    finally:
        for process in processes:
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        for process in processes:
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            if process.stdout is not None:
                process.stdout.close()


def _participant(directory: Path, name: str) -> list[Path]:
    files = [directory / f'fastrtps_{name}', directory / f'fastrtps_{name}_el',
             directory / f'sem.fastrtps_{name}_mutex']
    for path in files:
        path.write_bytes(b'\0' * 64)
    return files


def test_only_files_whose_lock_nobody_holds_are_removed(tmp_path):
    stale = _participant(tmp_path, 'dead0001')
    alive = _participant(tmp_path, 'live0001')
    young = _participant(tmp_path, 'young001')
    outside = tmp_path / 'elsewhere'
    outside.write_bytes(b'keep')
    (tmp_path / 'fastrtps_link_el').symlink_to(outside)
    other = tmp_path / 'unrelated_el'
    other.write_bytes(b'')
    old = time.time() - 60
    for path in stale + alive + [other]:
        os.utime(path, (old, old))
    holder = subprocess.Popen([sys.executable, '-c', HOLD, str(alive[1])],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert read_line(holder, 30.0) == 'held'
        removed = remove_stale(tmp_path, min_age=10.0)
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    assert removed == sorted(p.name for p in stale)
    assert not any(p.exists() for p in stale)
    assert all(p.exists() for p in alive + young + [other, outside])
    assert (tmp_path / 'fastrtps_link_el').is_symlink()
    # once its holder has gone, the live one is stale too (the young one still is young)
    assert remove_stale(tmp_path, min_age=10.0) == sorted(p.name for p in alive)
    assert remove_stale(tmp_path / 'missing') == []


MIN_AGE = 1.0    # [s] files younger than this stay
NODE = ('import rclpy, time; rclpy.init(); node = rclpy.create_node("shm_test"); '
        'print("up", flush=True); time.sleep(60)')


def _start_node(started: list[subprocess.Popen]) -> tuple[subprocess.Popen, set[str]]:
    """A node process (in `started` before anything can fail) and the shared-memory segments
    it made: those whose lock file it holds (/proc/locks). Not new files in /dev/shm (on two
    workers another test's graph makes segments at the same time), nor the segments it maps
    (a participant maps those of the participants it hears too: seen, the live node's
    segment counted as the killed one's, and stayed)."""
    process = subprocess.Popen([sys.executable, '-c', NODE], stdout=subprocess.PIPE, text=True,
                               start_new_session=True)
    started.append(process)
    assert read_line(process, 30.0) == 'up'
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        segments = _own_segments(process.pid)
        if segments:
            return process, segments
        time.sleep(0.1)
    raise AssertionError('the node made no shared-memory segment')


def _own_segments(pid: int) -> set[str]:
    """The Fast DDS data segments (not the port segments) whose lock file `pid` holds."""
    held = set()
    with open('/proc/locks') as locks:
        for line in locks:
            fields = line.split()      # N: FLOCK ADVISORY WRITE PID MAJ:MIN:INODE START END
            if len(fields) >= 6 and fields[1] == 'FLOCK' and fields[4] == str(pid):
                held.add(int(fields[5].rsplit(':', 1)[1]))
    found = set()
    for name in os.listdir(SHM_DIR):
        if name.startswith('fastrtps_') and not name.startswith('fastrtps_port') \
                and name.endswith('_el'):
            try:
                if os.stat(SHM_DIR / name).st_ino in held:
                    found.add(name[:-len('_el')])
            except FileNotFoundError:
                pass
    return found


def _older_than(paths: list[Path], age: float) -> bool:
    """Every file's modification time (what remove_stale ages lock files by) lies more than
    `age` s back (a file removed meanwhile, by another run's cleanup, counts as old)."""
    now = time.time()

    def old(path: Path) -> bool:
        try:
            return now - path.stat().st_mtime > age
        except FileNotFoundError:
            return True
    return all(old(path) for path in paths)


def test_a_killed_nodes_segment_is_removed_a_live_ones_stays(started):
    live, live_segments = _start_node(started)
    killed, killed_segments = _start_node(started)
    killed.send_signal(signal.SIGKILL)
    killed.wait()
    assert all((SHM_DIR / s).exists() for s in killed_segments)     # left behind
    # until its lock files are MIN_AGE old, remove_stale leaves them alone (as it does those
    # of a participant starting now elsewhere): wait for that age, not for a guessed time
    locks = [SHM_DIR / f'{s}_el' for s in killed_segments]
    deadline = time.monotonic() + MIN_AGE + 30.0
    while not _older_than(locks, MIN_AGE):
        assert time.monotonic() < deadline, 'the lock files do not age'
        time.sleep(0.05)
    removed = remove_stale(min_age=MIN_AGE)
    # gone: removed by this call, or by the cleanup of a graph another test started meanwhile
    # (the suite runs on two workers; every graph start cleans up)
    assert not any((SHM_DIR / s).exists() for s in killed_segments)
    assert all((SHM_DIR / s).exists() for s in live_segments)
    assert not set(removed) & live_segments
    assert live.poll() is None
    fd = os.open(SHM_DIR / f'{next(iter(live_segments))}_el', os.O_RDWR)
    try:                                    # its owner still holds its lock
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            raise AssertionError('the live node does not hold its lock')
        except BlockingIOError:
            pass
    finally:
        os.close(fd)
