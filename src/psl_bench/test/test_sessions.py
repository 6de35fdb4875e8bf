"""A sweep's sessions as Ray tasks (psl_bench.sessions): the same records as one after the other
in this process, bit for bit; a worker killed mid-session, and the session run again; a
session that fails twice named in the report while the rest of the table comes out."""
import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest

from psl_bench import learn as bench_learn
from psl_bench import sessions

TASK = 'reach_over_obstacle'
SWEEP = dict(task_name=TASK, strategies=('scratch', 'bootstrap'), seeds=(0, 1), num_tasks=3,
             budget=25, num_test=3, after=1)
# what depends on the clock or on where it ran, not on the session's settings
TIMED = {'train_seconds', 'session_seconds', 'simulation_share', 'ik_share', 'ik_ms_per_path',
         'folder', 'reused', 'summary', 'ran_on'}


def decisions_and_numbers(report: dict) -> dict:
    return {seed: {row: {k: v for k, v in record.items() if k not in TIMED}
                   for row, record in by_row.items()}
            for seed, by_row in report['runs'].items()}


def metrics_without_seconds(folder: Path) -> dict:
    metrics = json.loads((folder / 'metrics.json').read_text())
    for task in metrics['tasks']:
        task.pop('seconds')
    for key in ('seconds', 'train_seconds', 'test_seconds'):
        (metrics.get('summary') or {}).pop(key, None)
    return metrics


@pytest.fixture(scope='module')
def serial(tmp_path_factory):
    out = tmp_path_factory.mktemp('serial')
    return out, bench_learn.run(out=out, runner='serial', **SWEEP)


def test_ray_gives_the_records_of_a_serial_run_bit_for_bit(serial, tmp_path, ray_cluster):
    out, report = serial
    on_ray = bench_learn.run(out=tmp_path, runner='ray', **SWEEP)
    assert on_ray['runner'].startswith('ray') and report['runner'] == 'serial'
    assert on_ray['missing'] == [] and sum(on_ray['nodes'].values()) == 4
    assert decisions_and_numbers(on_ray) == decisions_and_numbers(report)
    pids = {record['ran_on']['pid'] for by_row in on_ray['runs'].values()
            for record in by_row.values()}
    assert os.getpid() not in pids                   # they ran in Ray's worker processes
    for folder in out.iterdir():
        assert metrics_without_seconds(tmp_path / folder.name) == \
            metrics_without_seconds(folder), folder.name


def _status(pid: int) -> tuple[str, int]:
    """(the process's title: its command line's first word, its parent's PID)."""
    title = Path(f'/proc/{pid}/cmdline').read_bytes().split(b'\0')[0].decode(errors='replace')
    with open(f'/proc/{pid}/status') as f:
        parent = int(next(line for line in f if line.startswith('PPid:')).split()[1])
    return title, parent


def started_here(pid: int) -> bool:
    """Whether this process is among `pid`'s ancestors: a process this one started, or one
    started by such a process (a worker of the Ray cluster this process's ray.init started:
    its parent is that cluster's raylet, whose parent is this process)."""
    me = os.getpid()
    while pid > 1:
        try:
            pid = _status(pid)[1]
        except (OSError, StopIteration):
            return False
        if pid == me:
            return True
    return False


def my_ray_workers(name: str = 'ray::_run') -> list[int]:
    """PIDs of the Ray worker processes executing a session now (Ray names the process after
    the task it runs) of the cluster this process started: never another test's sweep, nor
    another run's."""
    found = []
    for entry in Path('/proc').iterdir():
        if entry.name.isdigit():
            try:
                title = _status(int(entry.name))[0]
            except (OSError, StopIteration):
                continue
            if title.startswith(name) and started_here(int(entry.name)):
                found.append(int(entry.name))
    return found


def kill_my_worker(pid: int, name: str = 'ray::_run') -> bool:
    """SIGKILL the worker `pid` if it is still one of `my_ray_workers`: checked while its
    process is held (a pidfd), so a PID reused once it has gone is never signalled."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return False
    try:
        try:
            if not (_status(pid)[0].startswith(name) and started_here(pid)):
                return False
            signal.pidfd_send_signal(fd, signal.SIGKILL)
        except (OSError, StopIteration):        # it ended meanwhile
            return False
        return True
    finally:
        os.close(fd)


def test_a_worker_of_another_sweep_is_not_mine():
    """A process titled as a session's worker that is not of this process's tree (another
    test's sweep, another run's: here one this test detached from itself, its parent gone)
    is never found among `my_ray_workers`, and never killed by `kill_my_worker`."""
    import subprocess
    detached = subprocess.run(
        ['bash', '-c', '(exec -a "ray::_run" sleep 60 </dev/null >/dev/null 2>&1 & echo $!)'],
        capture_output=True, text=True, check=True)
    other = int(detached.stdout)
    try:
        deadline = time.monotonic() + 10.0      # its title once bash has exec'd the sleep
        while _status(other)[0] != 'ray::_run' and time.monotonic() < deadline:
            time.sleep(0.01)
        assert _status(other)[0] == 'ray::_run' and not started_here(other)
        assert other not in my_ray_workers()
        assert not kill_my_worker(other)
        assert _status(other)[0] == 'ray::_run'               # still running
    finally:
        os.kill(other, signal.SIGKILL)


def test_a_worker_killed_mid_session_is_run_again_and_the_table_is_complete(serial, tmp_path,
                                                                             ray_cluster):
    out, report = serial
    sweep = {**SWEEP, 'num_tasks': 3}
    result, errors = {}, []

    def sweep_on_ray():
        try:
            result['report'] = bench_learn.run(out=tmp_path, runner='ray', **sweep)
        except Exception as exc:  # noqa: BLE001 - said by the assertion below
            errors.append(exc)
    thread = threading.Thread(target=sweep_on_ray, daemon=True)
    thread.start()
    killed = None
    deadline = time.monotonic() + 120
    try:
        # a session that has finished its first task (its checkpoint) and runs on
        while killed is None and time.monotonic() < deadline and thread.is_alive():
            running = my_ray_workers()
            if running and any((f / 'checkpoint.json').is_file() and
                               not (f / 'metrics.json').is_file()
                               for f in tmp_path.glob('*-seed*')):
                if kill_my_worker(running[0]):
                    killed = running[0]
            time.sleep(0.002)
    finally:
        thread.join(timeout=300)
    assert not thread.is_alive(), 'the sweep did not end'
    assert not errors, errors
    assert killed is not None, 'no session was caught mid-way'
    on_ray = result['report']
    assert on_ray['missing'] == []
    # the retried session resumed or restarted in its folder: every record as the serial run's
    assert decisions_and_numbers(on_ray) == decisions_and_numbers(report)
    assert killed not in {record['ran_on']['pid'] for by_row in on_ray['runs'].values()
                          for record in by_row.values()}


def failing_session(fail: bool) -> dict:
    """A session body defined in this test module: Ray's workers get it by value
    (`register_pickle_by_value` below), as they cannot import a test module."""
    if fail:
        raise RuntimeError('this session always fails')
    return {'summary': 'fine'}


@pytest.mark.parametrize('runner', sessions.RUNNERS)
def test_a_session_that_fails_twice_is_named_and_the_rest_comes_out(runner, request):
    import sys
    if runner == 'ray':
        request.getfixturevalue('ray_cluster')

    from ray import cloudpickle
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    plan = [sessions.Session(key=(k,), label=f'session {k}', function=failing_session,
                             kwargs={'fail': k == 1}) for k in range(3)]
    lines = []
    swept = sessions.run(plan, runner, progress=lines.append)
    assert sorted(swept.records) == [(0,), (2,)]
    assert swept.failed == {(1,): 'RuntimeError: this session always fails'}
    assert any('session 1: FAILED (RuntimeError: this session always fails)' == line
               for line in lines)
    assert sum(swept.nodes.values()) == 2

