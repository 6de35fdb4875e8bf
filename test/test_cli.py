"""The psl command line: `psl up` owns its processes; `psl rollout` talks to the graph."""
import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from psl_cli.graph import NODES, pid_alive

PSL = [sys.executable, '-m', 'psl_cli.main']


def start_up(tmp_path):
    """`psl up` in its own session; returns (process, {node: pid}) once all nodes started."""
    log = open(tmp_path / 'up.log', 'w+')
    proc = subprocess.Popen(PSL + ['up'], stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True, text=True)
    deadline = time.monotonic() + 30
    pids = {}
    while time.monotonic() < deadline and len(pids) < len(NODES):
        log.seek(0)
        pids = {m[0]: int(m[1]) for m in re.findall(r'started (\w+)\s+pid (\d+)', log.read())}
        time.sleep(0.1)
    assert len(pids) == len(NODES), f'psl up printed: {(tmp_path / "up.log").read_text()}'
    return proc, pids, log


def wait_for_line(log, text: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        log.seek(0)
        if text in log.read():
            return
        time.sleep(0.1)
    log.seek(0)
    raise AssertionError(f'{text!r} not printed; psl up printed: {log.read()}')


def end(proc, pids):
    """Whatever a test did, leave nothing behind (by PID)."""
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    for pid in pids.values():
        if pid_alive(pid):
            os.kill(pid, signal.SIGKILL)


def test_up_serves_rollouts_and_ends_its_processes_on_sigterm(tmp_path):
    proc, pids, log = start_up(tmp_path)
    try:
        wait_for_line(log, 'graph ready')
        assert all(pid_alive(pid) for pid in pids.values())
        out = subprocess.run(PSL + ['rollout', '--json', '--timeout', '60'],
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        evaluation = json.loads(out.stdout)
        assert evaluation['fulfilled'] and evaluation['components']['goal_error'] < 0.005
        bad = subprocess.run(PSL + ['rollout', '--task', 'nope'], capture_output=True,
                             text=True, timeout=60)
        assert bad.returncode == 2 and 'unknown task' in bad.stderr
        os.kill(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        assert not [name for name, pid in pids.items() if pid_alive(pid)]
    finally:
        end(proc, pids)


def test_up_reports_a_dead_node_and_ends_the_others(tmp_path):
    proc, pids, log = start_up(tmp_path)
    try:
        time.sleep(1.0)
        os.kill(pids['pd_controller'], signal.SIGKILL)
        assert proc.wait(timeout=30) == 1
        log.seek(0)
        text = log.read()
        assert f"pd_controller (pid {pids['pd_controller']}) ended with signal SIGKILL" in text
        assert not [name for name, pid in pids.items() if pid_alive(pid)]
    finally:
        end(proc, pids)


@pytest.mark.parametrize('args, words', [
    (['rollout', '--tau', '0.7'], ['2 task parameters']),
    (['rollout', '--theta-file', '/nonexistent.txt'], ['nonexistent']),
])
def test_rollout_cli_refuses_bad_input_before_sending(args, words):
    out = subprocess.run(PSL + args, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    for word in words:
        assert word in out.stderr
