"""``psl init`` (psl_cli.init) as a user runs it: a published arm's URDF by its package://
URL becomes a task file that psl check passes; bad input gets one line and exit code 2, and
nothing is written."""
import subprocess
import sys

import pytest

from psl_task.task import load_task

PSL = [sys.executable, '-m', 'psl_cli.main']
XARM = 'package://example-robot-data/robots/xarm_description/urdf/xarm7.urdf'


def run(args, cwd) -> subprocess.CompletedProcess:
    return subprocess.run(PSL + [str(a) for a in args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def test_psl_init_writes_a_task_psl_check_passes(tmp_path):
    done = run(['init', XARM, '--end-effector', 'link7', '-o', 'xarm7.yaml'], tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith('wrote xarm7.yaml: 7 driven joints')
    assert load_task(str(tmp_path / 'xarm7.yaml')).n_joints == 7
    check = run(['check', '--task', 'xarm7.yaml', '--strict'], tmp_path)
    assert check.returncode == 0 and 'no warnings' in check.stdout, check.stdout
    again = run(['init', XARM, '--end-effector', 'link7', '-o', 'xarm7.yaml'], tmp_path)
    assert again.returncode == 2 and 'exists' in again.stderr      # never overwritten unasked


@pytest.mark.parametrize('args, words', [
    ([XARM, '--end-effector', 'hand'], ('no such link', 'link7')),
    ([XARM, '--end-effector', 'link2', '--base', 'link4'], ('not below',)),
    ([XARM, '--end-effector', 'link_base'], ('nothing to drive',)),
    (['no_such_arm.urdf', '--end-effector', 'link7'], ('no such file',)),
    ([XARM, '--end-effector', 'link7', '--posture', '0', '1'], ('--posture needs 7 values',)),
])
def test_bad_input_gets_one_line_and_exit_code_2(tmp_path, args, words):
    done = run(['init', *args, '-o', 'task.yaml'], tmp_path)
    lines = done.stderr.splitlines()
    assert done.returncode == 2, done
    assert 'Traceback' not in done.stderr and len(lines) == 1, done.stderr
    assert lines[0].startswith('psl init: ')
    for word in words:
        assert word in lines[0], lines[0]
    assert not (tmp_path / 'task.yaml').exists()


def test_the_cli_offers_the_kinds_the_generator_writes():
    """psl init's --kind choices are written out (the CLI does not import MuJoCo to build its
    parser): they must be the generator's."""
    from psl_cli.init import KINDS
    from psl_optimizer.task_generator import KINDS as GENERATED
    assert KINDS == GENERATED
