"""The dynamics figure: commanded vs executed joint angles and torques of PD only, learned and
oracle on a held-out instance of a payload_transport run."""
import numpy as np
import pytest

from psl_bench.plot_dynamics import dynamics_rollouts, plot_dynamics
from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_task.task import load_task

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


@pytest.fixture(scope='module')
def run_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp('payload_run')
    settings = LearnSettings(strategy='bootstrap', num_tasks=3, seed=0, num_test=2,
                             search=SearchSettings(max_rollouts=40))
    task = load_task('payload_transport')
    Learner(task, settings, folder, BatchRollouts(task)).run()
    return folder


def test_writes_a_png(run_folder, tmp_path):
    out = plot_dynamics(run_folder, tmp_path / 'dynamics.png', test_index=1)
    assert out == tmp_path / 'dynamics.png'
    assert out.read_bytes()[:8] == PNG_MAGIC and out.stat().st_size > 10_000


def test_bad_test_index_raises(run_folder, tmp_path):
    with pytest.raises(ValueError, match='test_index'):
        plot_dynamics(run_folder, tmp_path / 'x.png', test_index=2)


def test_rollouts_share_the_commanded_path():
    task = load_task('payload_transport')
    theta = policy_for(task).default_theta
    rollouts = dynamics_rollouts(task, np.array([1.0]), theta)
    assert set(rollouts) == {'pd_only', 'learned', 'oracle'}
    q_refs = [result.q_ref for result in rollouts.values()]
    np.testing.assert_array_equal(q_refs[0], q_refs[1])
    np.testing.assert_array_equal(q_refs[0], q_refs[2])
    np.testing.assert_array_equal(rollouts['pd_only'].reference.u_ffwd, 0.0)


def test_a_task_without_feedforward_is_refused():
    task = load_task('reach_over_obstacle')
    with pytest.raises(ValueError, match='feed-forward'):
        dynamics_rollouts(task, task.tau_default, policy_for(task).default_theta)


def test_psl_plot_on_a_yaml_task_writes_both_figures(tmp_path):
    """A task from a YAML file of the user's (outside the search path, a name of its own):
    metrics.json names the task 'my_payload', which no search finds; psl plot loads it from
    the file it was learned from and writes the dynamics figure beside the learning one."""
    import shutil
    import subprocess
    import sys

    import yaml
    from psl_task.task import EMBEDDED_TASKS
    folder = tmp_path / 'mine'
    folder.mkdir()
    data = yaml.safe_load((EMBEDDED_TASKS / 'payload_transport.yaml').read_text())
    data['name'] = 'my_payload'
    shutil.copy(EMBEDDED_TASKS / data['model'], folder / data['model'])
    (folder / 'my_payload.yaml').write_text(yaml.safe_dump(data))
    task = load_task(str(folder / 'my_payload.yaml'))
    run = tmp_path / 'run'
    Learner(task, LearnSettings(strategy='bootstrap', num_tasks=1, seed=0, num_test=1,
                                search=SearchSettings(max_rollouts=4)),
            run, BatchRollouts(task)).run()
    done = subprocess.run([sys.executable, '-m', 'psl_cli.main', 'plot', str(run)],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [str(run / 'learning.png'), str(run / 'learning_dynamics.png')]
    for png in ('learning.png', 'learning_dynamics.png'):
        assert (run / png).read_bytes()[:8] == PNG_MAGIC
