"""Every ``psl`` command that reads a file, given that file damaged: one line on stderr that
names the file and says what is wrong, a non-zero exit code, never a traceback (issue 46).

The files: a bag (``psl teach``), a session's checkpoint.json (``psl learn -o``), a task YAML
and the robot model it names, a skill memory file (``--continue-from``, ``--into``, the memory
node's ``load``), a theta file, a tau file, a session's metrics.json (``psl plot``). The
damages: empty, cut short, random bytes, content of the wrong kind, a directory where the file
is expected, unreadable (skipped when the tests run as root, whom permissions do not stop).

The whole command x file x damage matrix runs in this process through `psl_cli.main.main` (a
traceback reaches the user exactly when an exception leaves `main`); each file kind also runs
as its own process (``python -m psl_cli.main``), as do the cases the issue saw fail: three
damaged bags, a damaged checkpoint and a Ray address with no cluster. The memory node is one
process of its own (ended by PID).
"""
import io
import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from psl_ros.graph import Graph

PSL = [sys.executable, '-m', 'psl_cli.main']
TASK = 'reach_over_obstacle'
TAU = ['0.6', '0.15']
NOBODY = f'nobody_{os.getpid()}'            # a namespace no node serves
MEMORY_NS = f'damaged_files_{os.getpid()}'  # the namespace of this module's memory node
ROOT = os.geteuid() == 0                    # permissions do not stop root's reads


# -- good files ------------------------------------------------------------------------------
def write_bag(folder, wrong_type: bool = False) -> None:
    """A rosbag2 (MCAP) bag as psl record writes it: the task's joint states at 500 Hz, at
    rest at the start posture, one minimum-jerk motion of 1 s away from it, at rest (a
    demonstration psl teach finds); `wrong_type`: /joint_states holds std_msgs/String."""
    from psl_task.arm_model import joint_names_of
    from psl_task.task import load_task
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    task = load_task(TASK)
    store = get_typestore(Stores.ROS2_JAZZY)
    msgtype = 'std_msgs/msg/String' if wrong_type else 'sensor_msgs/msg/JointState'
    t = np.arange(0.0, 2.0, 0.002)
    s = np.clip(t - 0.5, 0.0, 1.0)
    q = task.start_posture + np.outer(10 * s**3 - 15 * s**4 + 6 * s**5, [0.3, -0.2, 0.1])
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/joint_states', msgtype, typestore=store)
        for stamp, row in zip(t, q):
            ns = int(round(stamp * 1e9))
            if wrong_type:
                msg = store.types[msgtype](data='not a joint state')
            else:
                msg = store.types[msgtype](
                    header=store.types['std_msgs/msg/Header'](
                        stamp=store.types['builtin_interfaces/msg/Time'](
                            sec=ns // 10**9, nanosec=ns % 10**9), frame_id=''),
                    name=joint_names_of(task), position=row, velocity=np.zeros(0),
                    effort=np.zeros(0))
            writer.write(connection, ns, store.serialize_cdr(msg, msgtype))


def good_memory(path) -> None:
    from psl_memory.skill_memory import SkillMemory
    from psl_optimizer.learning import LearnSettings
    SkillMemory(LearnSettings().skill).save(path)


@pytest.fixture(scope='module')
def good(tmp_path_factory):
    """One good file of each kind, in a folder of this module (resolved: the paths the
    commands print)."""
    from psl_task.task import EMBEDDED_TASKS
    folder = tmp_path_factory.mktemp('good').resolve()
    write_bag(folder / 'bag')
    write_bag(folder / 'string_bag', wrong_type=True)
    shutil.copy(EMBEDDED_TASKS / f'{TASK}.yaml', folder / 'task.yaml')
    shutil.copy(EMBEDDED_TASKS / f'{TASK}.xml', folder / f'{TASK}.xml')
    good_memory(folder / 'memory.npz')
    (folder / 'theta.json').write_text(json.dumps([0.1] * 24))
    (folder / 'taus.txt').write_text(' '.join(TAU) + '\n')
    (folder / 'checkpoint.json').write_text(json.dumps({'task': TASK, 'tasks': []}))
    (folder / 'metrics.json').write_text(json.dumps({'task': TASK, 'tasks': []}))
    return folder


# -- damages ---------------------------------------------------------------------------------
def damage(good_file, target, how: str, wrong: bytes | None = None) -> None:
    """`target` made from `good_file` as `how` says: 'empty', 'truncated' (the first half),
    'corrupted' (its middle overwritten with random bytes, both ends kept), 'random bytes'
    (as long), 'wrong content' (`wrong`), 'directory', 'unreadable' (mode 000)."""
    data = good_file.read_bytes()
    noise = np.random.default_rng(46).bytes(max(len(data), 64))
    content = {'empty': b'', 'truncated': data[:len(data) // 2],
               'corrupted': data[:64] + noise[:max(0, len(data) - 128)] + data[-64:],
               'random bytes': noise, 'wrong content': wrong, 'unreadable': data}.get(how)
    if how == 'directory':
        target.mkdir()
        return
    target.write_bytes(content)
    if how == 'unreadable':
        target.chmod(0)


DAMAGES = ('empty', 'truncated', 'random bytes', 'wrong content', 'directory', 'unreadable')
AS_ROOT = pytest.mark.skipif(ROOT, reason='run as root: permissions do not stop its reads')


def _npz_of_another_kind() -> bytes:
    """An .npz that is no memory file: one array, no header."""
    buffer = io.BytesIO()
    np.savez(buffer, theta=np.ones(3))
    return buffer.getvalue()


class Kind:
    """A kind of file a command reads: its good file in the module's folder, what a file of
    the wrong kind holds, and where it lies (`place` 'run': as that name in a run folder,
    which the command is given)."""

    def __init__(self, good: str, wrong: bytes | str | None, place: str = ''):
        self.good, self.place = good, place
        self.wrong = wrong.encode() if isinstance(wrong, str) else wrong

    def make(self, good_folder: Path, tmp: Path, how: str) -> tuple[Path, Path]:
        """The damaged file in `tmp` and what the command is given for it."""
        if self.good == 'bag':              # the bag's MCAP file damaged, its metadata kept
            bag = tmp / 'bag'
            if how == 'directory':          # a folder that is no bag
                bag.mkdir()
            elif how == 'wrong content':
                shutil.copytree(good_folder / 'string_bag', bag)
            else:
                shutil.copytree(good_folder / 'bag', bag)
                (bag / 'bag.mcap').unlink()
                damage(good_folder / 'bag' / 'bag.mcap', bag / 'bag.mcap', how)
            return bag, bag
        folder = tmp / 'run' if self.place == 'run' else tmp
        folder.mkdir(exist_ok=True)
        path = folder / (self.good if self.place else f'damaged_{self.good}')
        damage(good_folder / self.good, path, how, self.wrong)
        if self.good == MODEL:              # given: a task YAML naming the model
            text = (good_folder / 'task.yaml').read_text()
            (tmp / 'task.yaml').write_text(text.replace(MODEL, str(path)))
            return path, tmp / 'task.yaml'
        return path, (folder if self.place else path)


MODEL = f'{TASK}.xml'
KINDS = {
    'bag': Kind('bag', None),
    'task': Kind('task.yaml', '[1, 2, 3]\n'),
    'model': Kind(MODEL, '<html><body>not a model</body></html>\n'),
    'memory': Kind('memory.npz', _npz_of_another_kind()),
    'theta': Kind('theta.json', '{"message": "ok"}'),
    'taus': Kind('taus.txt', 'obstacle_x obstacle_height\n'),
    'checkpoint': Kind('checkpoint.json', '[1, 2]', place='run'),
    'metrics': Kind('metrics.json', '[1, 2]', place='run'),
}


def commands(kind: str, given, good, tmp) -> dict[str, list]:
    """The commands that read a file of `kind` (given as `given`), each before it needs a
    graph; the other files they read are good."""
    bag, out = good / 'bag', tmp / 'out'
    return {
        'bag': {'teach': ['teach', '--task', TASK, given, '--tau', *TAU, '-o', out / 'm.npz']},
        'task': {
            'check': ['check', '--task', given],
            'demo': ['demo', '--task', given, '--out', out],
            'up': ['up', '--task', given, '--namespace', NOBODY],
            'rollout': ['rollout', '--task', given, '--namespace', NOBODY],
            'learn': ['learn', '--task', given, '--tasks', '1', '-o', out],
            'teach': ['teach', '--task', given, bag, '--tau', *TAU, '-o', out / 'm.npz'],
            'render': ['render', '--task', given, '-o', tmp / 'r.gif'],
            'bench learn': ['bench', 'learn', '--serial', '--task', given, '--seeds', '0',
                            '--tasks', '2', '--after', '1', '--budget', '2', '-o', out],
            'bench teach': ['bench', 'teach', '--serial', '--tasks', given, '--counts', '0',
                            '--seeds', '0', '-o', out]},
        'model': {'check': ['check', '--task', given]},
        'memory': {
            'learn --continue-from': ['learn', '--continue-from', given, '--tasks', '1',
                                      '-o', out],
            'teach --into': ['teach', '--task', TASK, bag, '--tau', *TAU, '--into', given,
                             '-o', out / 'm.npz']},
        'theta': {
            'memory add': ['memory', 'add', '--skill', TASK, '--tau', *TAU, '--theta-file',
                           given, '--namespace', NOBODY],
            'rollout': ['rollout', '--theta-file', given, '--namespace', NOBODY],
            'render': ['render', '--theta-file', given, '-o', tmp / 'r.gif']},
        'taus': {'teach --tau-file': ['teach', '--task', TASK, bag, '--tau-file', given,
                                      '-o', out / 'm.npz']},
        'checkpoint': {'learn': ['learn', '--tasks', '1', '--test-tasks', '1', '--budget',
                                 '2', '-o', given]},
        'metrics': {'plot': ['plot', given]},
    }[kind]


# a truncated list of numbers is a shorter list, no damage a reader can see
SKIP = {('taus', 'truncated')}
MATRIX = [pytest.param(kind, command, how, marks=[AS_ROOT] if how == 'unreadable' else [])
          for kind in KINDS for command in commands(kind, Path(), Path(), Path())
          for how in DAMAGES if (kind, how) not in SKIP]


def assert_one_line(code: int, err: str, *words) -> str:
    """A non-zero exit, one line on stderr containing `words`, no traceback."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert code != 0, err
    assert 'Traceback' not in err, err
    assert len(lines) == 1, err
    for word in words:
        assert str(word) in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize('kind, command, how', MATRIX)
def test_a_damaged_file_is_one_line_naming_it(good, tmp_path, capsys, kind, command, how):
    """In this process: `main` returns the exit code, the line names the file; nothing
    raises out of it (what a user would see as a traceback)."""
    from psl_cli.main import main

    path, given = KINDS[kind].make(good, tmp_path, how)
    capsys.readouterr()
    code = main([str(a) for a in commands(kind, given, good, tmp_path)[command]])
    err = capsys.readouterr().err
    assert code == 2, err
    assert_one_line(code, err, path)


def test_a_tau_file_with_a_value_that_is_not_finite_names_its_line(good, tmp_path, capsys):
    from psl_cli.main import main
    path = tmp_path / 'taus.txt'
    path.write_text('# obstacle_x obstacle_height\n0.6 nan\n')
    code = main(['teach', '--task', TASK, str(good / 'bag'), '--tau-file', str(path), '-o',
                 str(tmp_path / 'm.npz')])
    assert_one_line(code, capsys.readouterr().err, f'{path}, line 2: values that are not '
                                                   'finite')


@pytest.mark.parametrize('name', ['metrics.json', 'memory.npz'])
def test_learn_into_a_folder_where_a_session_file_is_a_directory_is_one_line(
        tmp_path, capsys, name):
    """A folder where psl learn writes a file: metrics.json refused before any work (it would
    be written last), memory.npz when the first task's checkpoint cannot be written."""
    from psl_cli.main import main
    out = tmp_path / 'run'
    (out / name).mkdir(parents=True)
    code = main(['learn', '--tasks', '1', '--test-tasks', '1', '--budget', '2', '-o',
                 str(out)])
    assert code == 2
    assert_one_line(code, capsys.readouterr().err, 'psl learn:', out / name)
    assert (out / name).is_dir()


@pytest.mark.parametrize('name', ['checkpoint.json', 'metrics.json'])
def test_bench_learn_refuses_a_run_folder_whose_session_file_is_a_directory(
        tmp_path, capsys, name):
    """Refused before any work (before: taken for an empty folder; each session ran and failed
    writing it, twice)."""
    from psl_cli.main import main
    run = tmp_path / f'{TASK}-scratch-seed0'
    (run / name).mkdir(parents=True)
    code = main(['bench', 'learn', '--serial', '--strategies', 'scratch', '--seeds', '0',
                 '--tasks', '2', '--after', '1', '--test-tasks', '1', '--budget', '2', '-o',
                 str(tmp_path)])
    assert code == 2
    assert_one_line(code, capsys.readouterr().err, 'psl bench learn:', run)
    assert sorted(p.name for p in run.iterdir()) == [name]


# -- as processes ----------------------------------------------------------------------------
def run(args, cwd, timeout: float = 180.0) -> subprocess.CompletedProcess:
    return subprocess.run(PSL + [str(a) for a in args], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)


@pytest.mark.parametrize('how', ['truncated', 'corrupted', 'empty'])
def test_psl_teach_on_a_damaged_bag_is_one_line(good, tmp_path, how):
    """The bags of issue 46: an MCAP file cut short, overwritten in its middle, empty (a
    ReaderError, an OverflowError or a MemoryError traceback before)."""
    bag = tmp_path / 'bag'
    shutil.copytree(good / 'bag', bag)
    damage(good / 'bag' / 'bag.mcap', bag / 'bag.mcap', how)
    done = run(['teach', '--task', TASK, bag, '--tau', *TAU, '-o', tmp_path / 'm.npz'],
               tmp_path)
    assert done.returncode == 2
    assert_one_line(done.returncode, done.stderr, f'psl teach: {bag}: not a readable rosbag2')
    assert not (tmp_path / 'm.npz').exists()


def test_psl_learn_on_a_damaged_checkpoint_is_one_line_naming_it(tmp_path):
    """A checkpoint.json cut short: refused naming the file (before: 'Unterminated string
    starting at: line 1 column 10 (char 9)', no file named), nothing written over. (Its other
    damages: the matrix above, and src/psl_optimizer/test/test_damaged_files.py.)"""
    content = '{"task": "reach_over'
    out = (tmp_path / 'run').resolve()
    out.mkdir()
    (out / 'checkpoint.json').write_text(content)
    done = run(['learn', '--tasks', '1', '--test-tasks', '1', '--budget', '2', '-o', out],
               tmp_path)
    assert done.returncode == 2
    assert_one_line(done.returncode, done.stderr, out / 'checkpoint.json', 'not JSON')
    assert (out / 'checkpoint.json').read_text() == content
    assert sorted(p.name for p in out.iterdir()) == ['checkpoint.json']


# one damage per kind the process tests above do not cover: random bytes
@pytest.mark.parametrize('kind', sorted(set(KINDS) - {'bag', 'checkpoint'}))
def test_a_file_of_random_bytes_is_one_line_from_the_process(good, tmp_path, kind):
    path, given = KINDS[kind].make(good, tmp_path, 'random bytes')
    command = next(iter(commands(kind, given, good, tmp_path).values()))
    done = run(command, tmp_path)
    assert done.returncode == 2
    assert_one_line(done.returncode, done.stderr, path)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def test_a_ray_address_with_no_cluster_is_one_line(tmp_path):
    """psl bench learn --address to where no cluster is (before: no word in 180 s; Ray
    retries for minutes): one line naming the address, exit code 1. The run's timeout is the
    backstop of the bound. ($RAY_ADDRESS: src/psl_bench/test/test_damaged_files.py.)"""
    address = f'127.0.0.1:{free_port()}'
    done = run(['bench', 'learn', '--strategies', 'scratch', '--seeds', '0', '--tasks', '2',
                '--after', '1', '--test-tasks', '1', '--budget', '2', '-o', tmp_path / 'runs',
                '--address', address], tmp_path, timeout=120)
    assert done.returncode == 1
    assert_one_line(done.returncode, done.stderr, 'psl bench learn: no Ray cluster at',
                    address)
    assert not any((tmp_path / 'runs').iterdir())


# -- the memory node's load ------------------------------------------------------------------
@pytest.fixture(scope='module')
def memory_folder(tmp_path_factory):
    """A skill_memory process (memory files in the folder returned), ended by PID."""
    folder = tmp_path_factory.mktemp('memory_files').resolve()
    graph = Graph(nodes=(('skill_memory', 'psl_memory', 'skill_memory'),),
                  namespace=MEMORY_NS, log_dir=tmp_path_factory.mktemp('memory_logs'),
                  extra_params={'skill_memory': {'memory_dir': str(folder)}})
    try:
        graph.start()
        yield folder
    finally:
        graph.stop()
        assert not [p.name for p in graph.processes if p.process.poll() is None]


def test_the_memory_node_answers_a_damaged_file_with_the_reason_and_keeps_serving(
        good, memory_folder):
    """psl memory load of each damage: exit code 1 and the node's reason naming the file in
    one line; the node answers the next call, its memory unchanged."""
    def memory(*args):
        return run(['memory', *args, '--namespace', MEMORY_NS, '--timeout', '30'],
                   memory_folder)
    before = memory('info', '--json')
    assert before.returncode == 0, before.stderr
    hows = [how for how in ('empty', 'truncated', 'random bytes', 'directory', 'unreadable')
            if not (how == 'unreadable' and ROOT)]
    for how in hows:
        name = f'{how.replace(" ", "_")}.npz'
        damage(good / 'memory.npz', memory_folder / name, how)
        done = memory('load', name)
        assert done.returncode == 1, done
        assert_one_line(done.returncode, done.stderr, 'psl memory load', name)
    (memory_folder / 'other.npz').write_bytes(KINDS['memory'].wrong)
    done = memory('load', 'other.npz')
    assert_one_line(done.returncode, done.stderr, 'other.npz', 'not a psl memory file')
    after = memory('info', '--json')
    assert after.returncode == 0 and after.stdout == before.stdout
