"""Bad input to ``psl``: one line on stderr, a non-zero exit code, never a traceback; the same
when no graph is up (the line names what is missing) and when stdout is a closed pipe.

Every command runs as its own process (``python -m psl_cli.main``), on files this test makes.
The memory-node cases start one skill_memory process (the session's ROS_DOMAIN_ID, conftest.py,
and a namespace of its own; ended by PID); the no-graph cases use a namespace nothing serves;
the recorder case publishes from a node of its own in this process (its own rclpy context).
"""
import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from psl_ros.graph import Graph

PSL = [sys.executable, '-m', 'psl_cli.main']
NOBODY = f'nobody_{os.getpid()}'           # a namespace no node serves
MEMORY_NS = f'cli_input_{os.getpid()}'     # the namespace of this module's memory node
MEMORY_ONLY = (('skill_memory', 'psl_memory', 'skill_memory'),)


def run(args, cwd, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run(PSL + [str(a) for a in args], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)


def assert_one_line(done: subprocess.CompletedProcess, *words: str) -> str:
    """A non-zero exit, exactly one line on stderr (containing `words`), no traceback."""
    lines = done.stderr.splitlines()
    assert done.returncode != 0, done
    assert 'Traceback' not in done.stderr, done.stderr
    assert len(lines) == 1 and lines[0].strip(), done.stderr
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def files(tmp_path):
    """Bad theta files and a plain file, in tmp_path."""
    (tmp_path / 'garbage.txt').write_text('garbage 1.0 2.0\n')
    np.savez(tmp_path / 'theta.npz', theta=np.ones(24))
    (tmp_path / 'folder').mkdir()
    (tmp_path / 'plain_file').write_text('not a folder\n')
    return tmp_path


THETA_FILES = [('garbage.txt', 'garbage'), ('theta.npz', '.npz archive'),
               ('folder', 'is a directory'), ('missing.txt', 'no such file')]


@pytest.mark.parametrize('name, words', THETA_FILES)
@pytest.mark.parametrize('command', [['rollout'], ['memory', 'add', '--skill', 's', '--tau',
                                                   '0.5']])
def test_a_bad_theta_file_is_one_line(files, command, name, words):
    done = run(command + ['--theta-file', name, '--namespace', NOBODY], cwd=files)
    assert done.returncode == 2
    assert_one_line(done, name, words)


def test_memory_add_without_theta_is_one_line(tmp_path):
    done = run(['memory', 'add', '--skill', 's', '--tau', '1'], cwd=tmp_path)
    assert done.returncode == 2
    assert_one_line(done, '--theta')


@pytest.mark.parametrize('out, words', [
    ('plain_file', ['plain_file', 'is a file']),
    ('plain_file/run', ['cannot be created', 'plain_file is a file']),
    ('x' * 300, ['cannot be created', 'too long']),
])
def test_learn_refuses_an_output_folder_it_cannot_make(files, out, words):
    for flag in ('--out', '-o'):
        done = run(['learn', '--tasks', '1', flag, out], cwd=files)
        assert done.returncode == 2
        assert_one_line(done, 'psl learn', *words)


@pytest.mark.parametrize('args, words', [
    (['--tasks', '-5'], ['--tasks', '1 or more', '-5']),
    (['--tasks', '0'], ['--tasks', '1 or more']),
    (['--test-tasks', '0'], ['--test-tasks', '1 or more']),
    (['--budget', '-1'], ['--budget', '0 or more']),
    (['--tasks', 'many'], ['--tasks', 'not a whole number']),
    (['--seed', '5000000000'], ['--seed', 'below 2^32']),          # not wrapped to 705032704
    (['--seed', '-1'], ['--seed', '0 or more']),
    (['--mode', 'graph', '--seed', '-1'], ['--seed', '0 or more']),
])
def test_learn_refuses_bad_counts_before_learning(tmp_path, args, words):
    done = run(['learn', '--out', tmp_path / 'run'] + args, cwd=tmp_path)
    assert done.returncode == 2
    assert_one_line(done, *words)
    assert not (tmp_path / 'run').exists()


def test_budget_zero_is_the_default_budget(tmp_path):
    """--budget 0 means the default budget (as max_rollouts_per_task = 0 over ROS): the
    session records the same settings as --budget 200 (SearchSettings.max_rollouts)."""
    import json

    from psl_optimizer.policy_search import SearchSettings

    runs = {}
    for budget in ('0', str(SearchSettings.max_rollouts)):
        out = tmp_path / f'budget{budget}'
        done = run(['learn', '--tasks', '1', '--test-tasks', '1', '--budget', budget, '-o',
                    out], cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        runs[budget] = json.loads((out / 'metrics.json').read_text())
    zero, default = runs.values()
    assert zero['settings']['search']['max_rollouts'] == SearchSettings.max_rollouts
    assert zero['settings'] == default['settings']


def test_learn_never_does_nothing_in_a_folder_of_another_or_a_finished_session(tmp_path):
    """psl learn run twice with the same --out: a finished session is refused (not reprinted
    with exit 0); another session's checkpoint (another seed, a continuation) is refused in
    one line naming what differs; a memory to continue inside the session's own folder is
    refused; more tasks than the session holds go on from its checkpoint."""
    out = tmp_path / 'run'
    quick = ['--test-tasks', '1', '--budget', '5', '-o', out]
    done = run(['learn', '--tasks', '2'] + quick, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    before = (out / 'metrics.json').read_text()
    for args, words in (
            (['--tasks', '2'], [str(out), 'finished session', '--out']),
            (['--tasks', '1'], [str(out), 'finished session', '--out']),
            (['--tasks', '3', '--seed', '1'], [str(out), 'another session',
                                               'seed 0 there, 1 here', '--out']),
            (['--tasks', '3', '--continue-from', out / 'memory.npz'],
             ['lies in the session folder', '--out']),
            (['--tasks', '3', '--continue-from', tmp_path / 'elsewhere.npz'],
             ['another session', 'continue_from none there', '--out'])):
        if 'elsewhere.npz' in str(args):
            (tmp_path / 'elsewhere.npz').write_bytes((out / 'memory.npz').read_bytes())
        refused = run(['learn'] + args + quick, cwd=tmp_path)
        assert refused.returncode == 2, refused
        assert_one_line(refused, 'psl learn', *words)
        assert (out / 'metrics.json').read_text() == before     # nothing changed
    longer = run(['learn', '--tasks', '3'] + quick, cwd=tmp_path)
    assert longer.returncode == 0, longer.stderr
    assert 'rollouts over 3 tasks' in longer.stdout
    assert len(json.loads((out / 'metrics.json').read_text())['tasks']) == 3


def test_learn_progress_is_one_plain_line_per_task_when_stderr_is_no_terminal(tmp_path):
    done = run(['learn', '--tasks', '2', '--test-tasks', '1', '--budget', '5', '-o',
                tmp_path / 'run'], cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 2, done.stderr
    assert all(line.startswith(f'task {k}/2 ') and 'best reward' in line
               for k, line in enumerate(lines, 1)), done.stderr
    assert '\r' not in done.stderr
    assert 'rollouts over 2 tasks' in done.stdout


@pytest.mark.parametrize('args, words', [
    (['memory', 'info', '--timeout', '2'], [f'/{NOBODY}/skill_memory/info', 'not available']),
    (['query', '--skill', 's', '--tau', '0.5', '--timeout', '2'],
     [f'/{NOBODY}/skill_memory/query']),
    (['rollout', '--timeout', '1'], [f'/{NOBODY}', 'not up', 'execute_rollout']),
    (['learn', '--mode', 'graph', '--tasks', '1', '--timeout', '2'],
     ['learn_skill', 'not available']),
])
def test_without_a_graph_a_command_names_what_is_missing(tmp_path, args, words):
    done = run(args + ['--namespace', NOBODY, *(['-o', tmp_path / 'run'] if args[0] == 'learn'
                                               else [])], cwd=tmp_path)
    assert done.returncode == 1
    assert_one_line(done, *words)


def closed_pipe_run(args, cwd) -> subprocess.CompletedProcess:
    """`psl args` with stdout a pipe whose reading end is closed before it starts (as after
    ``| head -c 10`` has exited)."""
    read, write = os.pipe()
    os.close(read)
    try:
        process = subprocess.Popen(PSL + args, stdout=write, stderr=subprocess.PIPE,
                                   text=True, cwd=cwd)
    finally:
        os.close(write)
    try:
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:            # timed out (or interrupted): ended by PID
            process.kill()
            process.wait()
    return subprocess.CompletedProcess(process.args, process.returncode, '', stderr)


def test_a_closed_pipe_ends_quietly(tmp_path):
    """Exit code 141 (128 + SIGPIPE), nothing on stderr but the progress lines."""
    done = closed_pipe_run(['learn', '--tasks', '1', '--test-tasks', '1', '--budget', '5',
                            '-o', str(tmp_path / 'run')], tmp_path)
    assert done.returncode == 141, done.stderr
    assert done.stderr.startswith('task 1/1 ') and len(done.stderr.splitlines()) == 1, \
        done.stderr


@pytest.fixture(scope='module')
def memory_folder(tmp_path_factory):
    """A skill_memory process (memory files in the folder returned), ended by PID."""
    folder = tmp_path_factory.mktemp('memory_files')
    graph = Graph(nodes=MEMORY_ONLY, namespace=MEMORY_NS,
                  log_dir=tmp_path_factory.mktemp('memory_logs'),
                  extra_params={'skill_memory': {'memory_dir': str(folder)}})
    try:
        graph.start()
        yield folder
    finally:
        graph.stop()
        assert not [p.name for p in graph.processes if p.process.poll() is None]


def test_loading_a_directory_says_it_is_one(memory_folder):
    (memory_folder / 'a_folder').mkdir()
    done = run(['memory', 'load', 'a_folder', '--namespace', MEMORY_NS, '--timeout', '30'],
               cwd=memory_folder)
    assert done.returncode == 1
    assert_one_line(done, 'psl memory load', 'a_folder', 'directory')


def test_an_answer_into_a_closed_pipe_ends_quietly(memory_folder):
    done = closed_pipe_run(['memory', 'info', '--namespace', MEMORY_NS, '--timeout', '30',
                            '--json'], memory_folder)
    assert done.returncode == 141 and done.stderr == '', done.stderr


@pytest.fixture
def broken_task(tmp_path):
    """reach_over_obstacle with a goal posture outside joint2's range [-3, 3]."""
    import shutil

    import yaml
    from psl_task.task import EMBEDDED_TASKS
    data = yaml.safe_load((EMBEDDED_TASKS / 'reach_over_obstacle.yaml').read_text())
    data['goal_posture'] = [0.639, -3.5, -1.495]
    data['demonstration']['positions'][-1] = [0.639, -3.5, -1.495]
    shutil.copy(EMBEDDED_TASKS / data['model'], tmp_path / data['model'])
    path = tmp_path / 'broken.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize('command', [['up'], ['learn', '--tasks', '2'], ['render']])
def test_a_broken_task_is_one_line_naming_the_joint(broken_task, command, tmp_path):
    """psl up refuses before starting any node; the others before doing anything."""
    extra = {'up': ['--namespace', NOBODY], 'learn': ['-o', tmp_path / 'out'],
             'render': ['-o', tmp_path / 'out.gif']}[command[0]]
    done = run(command + ['--task', broken_task] + extra, tmp_path, timeout=60)
    assert_one_line(done, "joint 'joint2'", 'outside its range [-3, 3]')
    assert done.returncode == 2
    assert 'started' not in done.stdout


def test_a_node_that_cannot_start_says_why_in_one_line(broken_task, tmp_path):
    """A node started on its own with a task it refuses: one line on stderr, exit code 1."""
    done = subprocess.run([sys.executable, '-c',
                           'from psl_sim.sim_node import main; main()', '--ros-args', '-r',
                           f'__ns:=/{NOBODY}', '-p', f'task:={broken_task}'],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert_one_line(done, 'SimNode: cannot start', "joint 'joint2'")


RECORDED = 25          # messages the recorder test publishes


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_psl_record_ends_with_a_complete_bag_on_a_signal_even_from_a_script(tmp_path, sig):
    """A recorder a script starts in the background inherits SIGINT ignored; Ctrl-C (SIGINT)
    and SIGTERM both end it normally, with the bag's metadata written and every message it
    has received in the bag (and in its report)."""
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    from psl_ros.bag_recorder import read_bag_summary

    topic, bag = f'/psl_record_test_{os.getpid()}', tmp_path / 'bag'
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = process = None
    try:
        # latched messages, there before the recorder: it takes them when it subscribes
        node = rclpy.create_node(f'psl_record_test_{os.getpid()}', context=context)
        publisher = node.create_publisher(String, topic, QoSProfile(
            depth=RECORDED, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        for k in range(RECORDED):
            publisher.publish(String(data=f'message {k}'))
        # as a shell script's background job: SIGINT ignored (trap ''), through exec
        process = subprocess.Popen(['sh', '-c', 'trap "" INT; exec "$@"', 'sh', *PSL,
                                    'record', '-o', str(bag), topic],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        # the recorder is ready once it has subscribed (it sets its signal handlers before
        # it makes the bag, which it does before it subscribes) and has acknowledged every
        # message: what its subscription holds is in the bag however it ends
        deadline = time.monotonic() + 60
        while publisher.get_subscription_count() < 1:
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, 'the recorder did not subscribe'
            time.sleep(0.02)
        assert publisher.wait_for_all_acked(Duration(seconds=30)), 'messages not acknowledged'
        process.send_signal(sig)
        out, err = process.communicate(timeout=30)
    finally:
        if process is not None and process.poll() is None:
            process.kill()
            process.wait()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    assert process.returncode == 0, err
    assert (bag / 'metadata.yaml').is_file()
    assert read_bag_summary(bag) == {topic: ('std_msgs/msg/String', RECORDED)}, err
    assert re.search(rf'^{re.escape(topic)}\s+{RECORDED}$', out, re.MULTILINE), out


def test_the_views_port_is_given_else_the_environments_else_the_foxglove_default(monkeypatch):
    from psl_cli import options
    from psl_ros.view_parameters import DEFAULT_PORT

    monkeypatch.delenv(options.VIEW_PORT_VARIABLE, raising=False)
    assert options.view_port(None) == options.view_port(options.THE_DEFAULT_PORT) == DEFAULT_PORT
    monkeypatch.setenv(options.VIEW_PORT_VARIABLE, '9123')
    assert options.view_port(None) == options.view_port(options.THE_DEFAULT_PORT) == 9123
    assert options.view_port(0) == 0 and options.view_port(8000) == 8000     # given wins
    for bad in ('x', '-2', '70000', ''):
        monkeypatch.setenv(options.VIEW_PORT_VARIABLE, bad)
        with pytest.raises(ValueError, match=options.VIEW_PORT_VARIABLE):
            options.view_port(None)


@pytest.mark.parametrize('command', [['up', '--view'], ['view']])
def test_a_bad_view_port_in_the_environment_is_one_line(tmp_path, command):
    done = subprocess.run(PSL + command, capture_output=True, text=True, cwd=tmp_path,
                          timeout=120, env=dict(os.environ, PSL_VIEW_PORT='eighty'))
    assert_one_line(done, 'PSL_VIEW_PORT', "'eighty'")
    assert done.returncode == 2


@pytest.mark.parametrize('args, words', [
    (['nothing', 'sim'], ["no package 'nothing'", 'psl_sim']),
    (['psl_sim', 'nothing'], ["no executable 'nothing'", 'sim, standard_robot'])])
def test_psl_run_names_what_it_cannot_find(tmp_path, args, words):
    assert_one_line(run(['run', *args], tmp_path), *words)


def test_psl_run_runs_the_packages_executable_with_its_arguments(tmp_path):
    # the simulator node itself answers: it read the task its arguments gave it
    done = run(['run', 'psl_sim', 'sim', '--ros-args', '-r', f'__ns:=/{NOBODY}',
                '-p', 'task:=no_such_task'], tmp_path)
    assert done.returncode != 0
    assert "SimNode: cannot start: unknown task 'no_such_task'" in done.stdout + done.stderr
