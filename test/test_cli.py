"""The psl command line: `psl up` owns its processes; `psl rollout` talks to the graph."""
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from psl_msgs.msg import LearningProgress
from psl_ros.client import RosClient
from psl_ros.graph import NODES, NodeHandle

PSL = [sys.executable, '-m', 'psl_cli.main']


class Up:
    """`psl up` in its own session, its output in a log file, and the nodes it printed."""

    def __init__(self, log_path, *options):
        self.log_path = log_path
        self.nodes: dict[str, NodeHandle] = {}
        self.expected = len(NODES) + ('--view' in options)     # the view node: one more
        with open(log_path, 'w') as log:
            self.proc = subprocess.Popen(PSL + ['up', *options], stdout=log,
                                         stderr=subprocess.STDOUT, start_new_session=True)

    def output(self) -> str:
        return self.log_path.read_text()

    def wait_for_nodes(self, timeout: float = 30.0) -> dict[str, NodeHandle]:
        """Hold every node psl up prints as started (NodeHandle, at once); {name: handle}."""
        deadline = time.monotonic() + timeout
        while True:
            ended = self.proc.poll() is not None    # then its output is complete
            for name, pid in re.findall(r'started (\S+)\s+pid (\d+)\n', self.output()):
                if name not in self.nodes:
                    self.nodes[name] = NodeHandle(name, int(pid), self.proc.pid)
            if len(self.nodes) == self.expected:
                return self.nodes
            assert not ended and time.monotonic() < deadline, f'psl up printed: {self.output()}'
            time.sleep(0.05)

    def wait_for_line(self, text: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while True:
            ended = self.proc.poll() is not None    # then its output is complete
            if text in self.output():
                return
            assert not ended and time.monotonic() < deadline, \
                f'{text!r} not printed; psl up printed: {self.output()}'
            time.sleep(0.05)

    def alive_nodes(self) -> list[str]:
        return [name for name, node in self.nodes.items() if node.alive()]

    def end(self) -> None:
        """Whatever a test did, leave nothing behind: psl up ends its nodes on SIGTERM (those
        it has not printed yet too), else SIGKILL for its session and every node held."""
        try:
            if self.proc.poll() is None:
                self.proc.send_signal(signal.SIGTERM)
                try:
                    self.proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    os.killpg(self.proc.pid, signal.SIGKILL)    # not reaped: still its group
                    self.proc.wait()
        finally:
            for node in self.nodes.values():
                node.kill()
                node.close()


@pytest.fixture
def start_up(tmp_path):
    """start_up(*options): `psl up` (Up) with all its nodes held; ended after the test by PID
    whatever happens, also when the start fails."""
    started = []

    def start(*options) -> Up:
        up = Up(tmp_path / f'up{len(started)}.log', *options)
        started.append(up)
        up.wait_for_nodes()
        return up
    try:
        yield start
    finally:
        for up in started:
            up.end()


def test_up_serves_rollouts_and_a_view_and_ends_its_processes_on_sigterm(start_up):
    """psl up --view: the graph serves rollouts and queries, the view node starts with it,
    psl up says where it serves, a Foxglove viewer sees the graph's channels there, and
    SIGTERM ends every node, the view as well."""
    from psl_bench.foxglove_client import FoxgloveClient

    up = start_up('--view', '0')
    assert 'view' in up.nodes
    up.wait_for_line('graph ready')
    assert not set(up.nodes) - set(up.alive_nodes())
    url = re.search(r'view: (ws://\S+)', up.output())[1]
    with FoxgloveClient(url) as viewer:
        assert viewer.wait_channels(['/scene', '/joint_states', '/learning_progress'], 30.0)
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
    up.proc.send_signal(signal.SIGTERM)
    assert up.proc.wait(timeout=30) == 0
    assert not up.alive_nodes()


def wait_for_checkpoint(learn: subprocess.Popen, out, timeout: float = 120.0) -> None:
    """Until the session running in `learn` has written its first checkpoint (a task done)."""
    deadline = time.monotonic() + timeout
    while not (out / 'checkpoint.json').is_file():
        assert learn.poll() is None, f'psl learn ended ({learn.returncode}) before a checkpoint'
        assert time.monotonic() < deadline, f'no checkpoint within {timeout:g} s'
        time.sleep(0.05)


def test_learn_in_graph_mode_cancels_on_ctrl_c_and_resumes(start_up, tmp_path):
    """`psl learn --mode graph` runs the session in the graph's learner node (with the
    command's --test-tasks, its progress from the node's feedback); Ctrl-C cancels the goal
    (finished tasks stay in the checkpoint), the same command resumes it, and the result is
    batch mode's: rollouts through the graph give the batch rewards to 1e-9, so CMA-ES takes
    the same path (the same instances, rollouts, fulfilled tasks, best and held-out
    rewards)."""
    up = start_up()
    out = tmp_path / 'graph'
    learn = PSL + ['learn', '--mode', 'graph', '--tasks', '3', '--budget', '12', '--seed', '3',
                   '--test-tasks', '1', '--out', str(out)]
    up.wait_for_line('graph ready')
    first = subprocess.Popen(learn, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    try:
        wait_for_checkpoint(first, out)
        first.send_signal(signal.SIGINT)
        _, stderr = first.communicate(timeout=120)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert first.returncode == 1 and 'cancelled after' in stderr, stderr
    kept = json.loads((out / 'checkpoint.json').read_text())['tasks']
    assert 1 <= len(kept) < 3
    again = subprocess.run(learn, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    # its progress lines come from the learner's feedback, the last task's too
    assert 'task 3/3 ' in again.stderr, again.stderr
    up.end()
    graph = json.loads((out / 'metrics.json').read_text())
    assert graph['tasks'][:len(kept)] == kept
    # the session tested --test-tasks held-out instances, not the learner node's default
    assert len(graph['summary']['test_rewards']) == 1
    batch = subprocess.run(PSL + ['learn', '--tasks', '3', '--budget', '12', '--seed', '3',
                                  '--test-tasks', '1', '--out', str(tmp_path / 'batch')],
                           capture_output=True, text=True, timeout=300)
    assert batch.returncode == 0, batch.stderr
    batch = json.loads((tmp_path / 'batch' / 'metrics.json').read_text())
    assert [t['rollouts'] for t in graph['tasks']] == [t['rollouts'] for t in batch['tasks']]
    assert [t['fulfilled'] for t in graph['tasks']] == [t['fulfilled'] for t in batch['tasks']]
    assert [t['tau'] for t in graph['tasks']] == [t['tau'] for t in batch['tasks']]
    assert [t['best_reward'] for t in graph['tasks']] == pytest.approx(
        [t['best_reward'] for t in batch['tasks']], abs=1e-9)
    assert graph['summary']['test_rewards'] == pytest.approx(
        batch['summary']['test_rewards'], abs=1e-9)


def test_where_a_session_runs_and_how_its_rollouts_run_are_two_choices(start_up, tmp_path,
                                                                       wait_until):
    """--learner here --mode graph: the session in this process, its rollouts through the
    graph's workers; --learner node --mode batch: the session in the learner node, its
    rollouts in-process there. Both learn what batch mode here learns (graph rollouts give
    the batch rewards). Both publish the learning curve on the graph; a batch session in this
    process does not."""
    up = start_up()
    session = ['--tasks', '2', '--budget', '6', '--seed', '5', '--test-tasks', '1']
    up.wait_for_line('graph ready')
    results, curves = {}, {}
    with RosClient() as watcher:          # the learning curve the sessions publish
        curve, lock = [], threading.Lock()

        def keep(msg):
            with lock:
                curve.append(msg)
        watcher.node.create_subscription(
            LearningProgress, '/learning_progress', keep,
            QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE))
        for label, options in (('here_graph', ['--learner', 'here', '--mode', 'graph']),
                               ('node_batch', ['--learner', 'node', '--mode', 'batch']),
                               ('here_batch', [])):
            out = tmp_path / label
            done = subprocess.run(PSL + ['learn', *options, *session, '--out', str(out)],
                                  capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, (label, done.stderr)
            results[label] = json.loads((out / 'metrics.json').read_text())
            total = sum(t['rollouts'] for t in results[label]['tasks'])
            # the session's last point has arrived (its held-out test ran after it)
            assert label == 'here_batch' or wait_until(
                lambda: curve and curve[-1].rollout == total, 30.0), label
            with lock:
                curves[label], curve[:] = list(curve), []
    up.end()
    want = results['here_batch']['tasks']
    for label in ('here_graph', 'node_batch'):
        got = results[label]['tasks']
        assert [t['rollouts'] for t in got] == [t['rollouts'] for t in want], label
        assert [t['fulfilled'] for t in got] == [t['fulfilled'] for t in want], label
        assert [t['best_reward'] for t in got] == pytest.approx(
            [t['best_reward'] for t in want], abs=1e-9), label
    # a session with the graph publishes its curve (the learner node's publisher is matched
    # before the session: every point; a psl learn process's may miss the first ones before
    # it is matched); one without the graph publishes none
    total = sum(t['rollouts'] for t in want)
    assert [m.rollout for m in curves['node_batch']] == list(range(1, total + 1))
    rollouts = [m.rollout for m in curves['here_graph']]
    assert rollouts == list(range(rollouts[0], total + 1))
    assert all(m.task == 'reach_over_obstacle' and m.strategy == 'bootstrap'
               for m in curves['here_graph'] + curves['node_batch'])
    assert curves['here_batch'] == []


# how long psl learn may take to notice that the learner has gone: a deadline for the event
# (it notices within seconds: the server unseen for 2 s, a Fast DDS lease of 4 s), far below
# the session's own timeout that a client waiting forever would run into
NOTICE_DEADLINE = 60.0      # s


def test_learn_in_graph_mode_ends_when_the_graph_dies(start_up, tmp_path):
    """SIGKILL a node mid-session: psl up reports the dead node and ends the others, and
    psl learn notices that the learner has gone (no wait forever) and says so."""
    up = start_up()
    out = tmp_path / 'graph'
    up.wait_for_line('graph ready')        # psl up watches the graph it has started
    learn = subprocess.Popen(PSL + ['learn', '--mode', 'graph', '--tasks', '20', '--out',
                                    str(out)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        wait_for_checkpoint(learn, out)
        pid = up.nodes['pd_controller'].pid
        assert up.nodes['pd_controller'].kill(), 'pd_controller had ended before the kill'
        try:
            _, stderr = learn.communicate(timeout=NOTICE_DEADLINE)
        except subprocess.TimeoutExpired:
            raise AssertionError(f'psl learn did not notice within {NOTICE_DEADLINE:g} s '
                                 'that the graph had died') from None
    finally:
        if learn.poll() is None:
            learn.kill()
            learn.wait()
    assert learn.returncode == 1, stderr
    assert 'has gone' in stderr and 'learn_skill' in stderr, stderr
    assert up.proc.wait(timeout=30) == 1
    assert f"pd_controller (pid {pid}) ended with signal SIGKILL" in up.output()
    assert not up.alive_nodes()


@pytest.mark.parametrize('args, words', [
    (['rollout', '--tau', '0.7'], ['2 task parameters']),
    (['rollout', '--theta-file', '/nonexistent.txt'], ['nonexistent']),
])
def test_rollout_cli_refuses_bad_input_before_sending(args, words):
    out = subprocess.run(PSL + args, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    for word in words:
        assert word in out.stderr


def test_memory_files_go_to_the_memory_dir_and_a_session_continues_from_one(start_up,
                                                                             tmp_path):
    """psl up --memory-dir DIR: psl memory save NAME writes DIR/NAME; psl learn
    --continue-from starts from that memory's skill (batch mode here: a path)."""
    memory_dir = tmp_path / 'memories'
    up = start_up('--memory-dir', str(memory_dir))
    up.wait_for_line('graph ready')
    saved = subprocess.run(PSL + ['memory', 'save', 'mine.npz'], capture_output=True,
                           text=True, timeout=60)
    assert saved.returncode == 0, saved.stderr
    assert (memory_dir / 'mine.npz').is_file()
    outside = subprocess.run(PSL + ['memory', 'save', str(tmp_path / 'elsewhere.npz')],
                             capture_output=True, text=True, timeout=60)
    assert outside.returncode == 1 and 'outside the memory folder' in outside.stderr
    assert not (tmp_path / 'elsewhere.npz').exists()
    up.end()
    first, second = tmp_path / 'first', tmp_path / 'second'
    for out, extra in ((first, []), (second, ['--continue-from', str(first / 'memory.npz')])):
        done = subprocess.run(PSL + ['learn', '--tasks', '3', '--budget', '30', '--test-tasks',
                                     '3', '-o', str(out), *extra],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
    from psl_memory.skill_memory import SkillMemory
    from psl_optimizer.learning import CORRECTION_SUFFIX
    kept = SkillMemory.read(first / 'memory.npz').get('reach_over_obstacle').num_samples
    goes_on = SkillMemory.read(second / 'memory.npz')
    added = sum(t['fulfilled'] for t in json.loads((second / 'metrics.json').read_text())['tasks'])
    # continued the residual way: the skill it started from unchanged, the new solutions
    # taught to its correction (psl_optimizer.learning)
    assert kept > 0 and goes_on.get('reach_over_obstacle').num_samples == kept
    assert goes_on.get('reach_over_obstacle' + CORRECTION_SUFFIX).num_samples == added
