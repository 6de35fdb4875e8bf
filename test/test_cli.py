"""The psl command line: `psl up` owns its processes; `psl rollout` talks to the graph."""
import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from psl_ros.graph import NODES, pid_alive

PSL = [sys.executable, '-m', 'psl_cli.main']


def start_up(tmp_path, *options):
    """`psl up` in its own session; returns (process, {node: pid}) once all nodes started."""
    log = open(tmp_path / 'up.log', 'w+')
    proc = subprocess.Popen(PSL + ['up', *options], stdout=log, stderr=subprocess.STDOUT,
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
        # psl up created the task's skill in the memory (which knows no tasks)
        query = subprocess.run(PSL + ['query', '--skill', 'reach_over_obstacle', '--tau', '0.6',
                                      '0.2', '--json'], capture_output=True, text=True,
                               timeout=60)
        assert query.returncode == 0, query.stderr
        assert len(json.loads(query.stdout)['theta']) == 24
        bad = subprocess.run(PSL + ['rollout', '--task', 'nope'], capture_output=True,
                             text=True, timeout=60)
        assert bad.returncode == 2 and 'unknown task' in bad.stderr
        os.kill(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        assert not [name for name, pid in pids.items() if pid_alive(pid)]
    finally:
        end(proc, pids)


def test_learn_in_graph_mode_cancels_on_ctrl_c_and_resumes(tmp_path):
    """`psl learn --mode graph` runs the session in the graph's learner node; Ctrl-C cancels
    the goal (finished tasks stay in the checkpoint), the same command resumes it, and the
    result equals batch mode's (graph rollouts give the batch rewards)."""
    proc, pids, log = start_up(tmp_path)
    out = tmp_path / 'graph'
    learn = PSL + ['learn', '--mode', 'graph', '--tasks', '3', '--budget', '12', '--seed', '3',
                   '--out', str(out)]
    try:
        wait_for_line(log, 'graph ready')
        first = subprocess.Popen(learn, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 text=True)
        try:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and not (out / 'checkpoint.json').is_file():
                time.sleep(0.05)
            os.kill(first.pid, signal.SIGINT)
            _, stderr = first.communicate(timeout=120)
        finally:
            if first.poll() is None:
                first.kill()
        assert first.returncode == 1 and 'cancelled after' in stderr, stderr
        kept = json.loads((out / 'checkpoint.json').read_text())['tasks']
        assert 1 <= len(kept) < 3
        again = subprocess.run(learn, capture_output=True, text=True, timeout=300)
        assert again.returncode == 0, again.stderr
    finally:
        end(proc, pids)
    graph = json.loads((out / 'metrics.json').read_text())
    assert graph['tasks'][:len(kept)] == kept
    batch = subprocess.run(PSL + ['learn', '--tasks', '3', '--budget', '12', '--seed', '3',
                                  '--out', str(tmp_path / 'batch')],
                           capture_output=True, text=True, timeout=300)
    assert batch.returncode == 0, batch.stderr
    batch = json.loads((tmp_path / 'batch' / 'metrics.json').read_text())
    assert [t['rollouts'] for t in graph['tasks']] == [t['rollouts'] for t in batch['tasks']]
    assert [t['best_reward'] for t in graph['tasks']] == pytest.approx(
        [t['best_reward'] for t in batch['tasks']], abs=1e-9)


def test_learn_in_graph_mode_ends_when_the_graph_dies(tmp_path):
    """SIGKILL a node mid-session: psl up ends the graph, and psl learn notices that the
    learner has gone within seconds (no wait forever) and says so."""
    proc, pids, log = start_up(tmp_path)
    out = tmp_path / 'graph'
    try:
        wait_for_line(log, 'graph ready')
        learn = subprocess.Popen(PSL + ['learn', '--mode', 'graph', '--tasks', '20', '--out',
                                        str(out)], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and not (out / 'checkpoint.json').is_file():
                time.sleep(0.05)
            killed = time.monotonic()
            os.kill(pids['pd_controller'], signal.SIGKILL)
            _, stderr = learn.communicate(timeout=60)
            waited = time.monotonic() - killed
        finally:
            if learn.poll() is None:
                learn.kill()
                learn.wait()
        assert learn.returncode == 1, stderr
        assert 'has gone' in stderr and 'learn_skill' in stderr, stderr
        assert waited < 30, f'psl learn took {waited:.1f} s to notice'
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


def test_memory_files_go_to_the_memory_dir_and_a_session_continues_from_one(tmp_path):
    """psl up --memory-dir DIR: psl memory save NAME writes DIR/NAME; psl learn
    --continue-from starts from that memory's skill (batch mode here: a path)."""
    memory_dir = tmp_path / 'memories'
    proc, pids, log = start_up(tmp_path, '--memory-dir', str(memory_dir))
    try:
        wait_for_line(log, 'graph ready')
        saved = subprocess.run(PSL + ['memory', 'save', 'mine.npz'], capture_output=True,
                               text=True, timeout=60)
        assert saved.returncode == 0, saved.stderr
        assert (memory_dir / 'mine.npz').is_file()
        outside = subprocess.run(PSL + ['memory', 'save', str(tmp_path / 'elsewhere.npz')],
                                 capture_output=True, text=True, timeout=60)
        assert outside.returncode == 1 and 'outside the memory folder' in outside.stderr
        assert not (tmp_path / 'elsewhere.npz').exists()
    finally:
        end(proc, pids)
    first, second = tmp_path / 'first', tmp_path / 'second'
    for out, extra in ((first, []), (second, ['--continue-from', str(first / 'memory.npz')])):
        done = subprocess.run(PSL + ['learn', '--tasks', '3', '--budget', '30', '--test-tasks',
                                     '3', '-o', str(out), *extra],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
    from psl_memory.skill_memory import SkillMemory
    kept = SkillMemory.read(first / 'memory.npz').get('reach_over_obstacle').num_samples
    goes_on = SkillMemory.read(second / 'memory.npz').get('reach_over_obstacle')
    added = sum(t['fulfilled'] for t in json.loads((second / 'metrics.json').read_text())['tasks'])
    assert kept > 0 and goes_on.num_samples == kept + added
