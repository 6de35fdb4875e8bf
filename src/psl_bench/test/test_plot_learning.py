"""psl plot: figures of real (tiny) learning runs, the variance grid, bad folders, the CLI."""
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import yaml
from matplotlib.image import imread

from psl_bench.plot_learning import DPI, FIGSIZE, load_run, plot_runs, variance_grid
from psl_memory.skill_config import SkillConfig
from psl_memory.skill_memory import SkillMemory
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_task.task import EMBEDDED_TASKS, load_task

TASK = 'reach_over_obstacle'
NUM_TASKS = 12
GRID = 25
PNG_SHAPE = (round(FIGSIZE[1] * DPI), round(FIGSIZE[0] * DPI), 4)   # rows, columns, RGBA
FAR = 0.5       # grid points farther than this from every sample (unit tau) count as far
NO_VARIANCE = SkillConfig(readout='incremental_ridge')      # the plot fits a Bayesian readout
BAYES = SkillConfig(readout='bayes')                        # the plot queries the skill as it is


def settings(strategy: str, seed: int, num_tasks: int = NUM_TASKS,
             skill: SkillConfig = NO_VARIANCE) -> LearnSettings:
    return LearnSettings(strategy=strategy, num_tasks=num_tasks, seed=seed, num_test=6,
                         search=SearchSettings(max_rollouts=40), skill=skill)


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


@pytest.fixture(scope='module')
def evaluator(task):
    return BatchRollouts(task)


@pytest.fixture(scope='module')
def runs(task, evaluator, tmp_path_factory):
    """Three finished runs with a readout without variance: bootstrap seeds 0 and 1, scratch
    seed 0."""
    out = {}
    for strategy, seed in (('bootstrap', 0), ('bootstrap', 1), ('scratch', 0)):
        folder = tmp_path_factory.mktemp(f'{strategy}{seed}')
        Learner(task, settings(strategy, seed), folder, evaluator).run()
        out[strategy, seed] = folder
    return out


def skill_of(folder):
    return SkillMemory.read(folder / 'memory.npz').get(TASK)


def assert_png(path):
    image = imread(path)
    assert image.shape == PNG_SHAPE
    assert np.ptp(image[..., :3]) > 0.5          # something is drawn, not a blank canvas


def test_several_runs_give_one_png_of_the_figure_size(runs, tmp_path):
    out = tmp_path / 'runs.png'
    assert plot_runs(list(runs.values()), out, grid_points=GRID) == out
    assert_png(out)


def test_variance_grid_is_positive_and_lowest_near_the_samples(runs):
    skill = skill_of(runs['bootstrap', 0])
    assert skill.config.readout == 'incremental_ridge' and skill.num_samples >= 8
    grid = variance_grid(skill, GRID)
    assert grid.fitted and grid.num_samples == skill.num_samples
    assert grid.values.shape == (GRID, GRID)
    np.testing.assert_allclose([a[[0, -1]] for a in grid.axes],
                               np.c_[skill.tau_scaler.low, skill.tau_scaler.high])
    assert np.all(np.isfinite(grid.values)) and np.all(grid.values > 0)
    # distances in unit tau coordinates, grid (row: tau_1, column: tau_0) against the samples
    x, y = np.meshgrid(*grid.axes)
    points = skill.tau_scaler.to_unit(np.c_[x.ravel(), y.ravel()])             # (GRID^2, 2)
    samples = skill.tau_scaler.to_unit(skill.taus)                              # (N, 2)
    dist = np.linalg.norm(points[:, None] - samples[None], axis=2)              # (GRID^2, N)
    values = grid.values.ravel()
    near = values[np.argmin(dist, axis=0)]             # the grid point nearest each sample
    far = values[dist.min(axis=1) > FAR]
    assert far.size > 0
    assert np.mean(near) < np.mean(far)
    assert np.max(near) < np.max(far)


def bayesian_variance_by_hand(skill, config, tau) -> float:
    """Predictive variance of theta (eq. 2.14) in theta's units for a Bayesian readout with the
    precisions of `config`, from scratch: the ELM hidden state h of tau (sigmoid of the skill's
    fixed random layer, eq. 2.2), the posterior
    S_N = (alpha I + beta H^T H)^-1 over the skill's samples (eq. 2.12), 1/beta + h^T S_N h
    times the square of theta's half-range (the same for every theta dimension)."""
    def hidden(taus):                                                   # (n, E) -> (n, N_H)
        low, high = skill.tau_scaler.low, skill.tau_scaler.high
        unit = 2.0 * (np.atleast_2d(taus) - low) / (high - low) - 1.0
        a = config.alpha * (unit @ skill.features.w_inp.T + skill.features.bias)
        return 1.0 / (1.0 + np.exp(-a))
    alpha, beta = config.regularization, config.noise_precision
    big_h = hidden(skill.taus)                                          # (N, N_H)
    s_n = np.linalg.inv(alpha * np.eye(config.n_hidden) + beta * big_h.T @ big_h)
    h = hidden(tau)[0]                                                  # (N_H,)
    half = 0.5 * (skill.theta_scaler.high - skill.theta_scaler.low)     # (F,), all equal
    return float(np.mean((1.0 / beta + h @ s_n @ h) * half**2))


def test_a_skill_with_variance_is_queried_as_it_is(runs):
    """A skill without variance gets a Bayesian readout with its own precisions fitted to its
    samples; one with variance (here beta = 4, not the default 1) is queried with its own.
    Both against the predictive variance computed by hand at grid points."""
    skill = skill_of(runs['scratch', 0])
    assert skill.config.readout == 'incremental_ridge'
    assert not skill.config.estimate_precisions               # fixed alpha, beta by hand
    fitted = variance_grid(skill, GRID)
    mine = SkillConfig(readout='bayes', noise_precision=4.0)
    with_variance = skill.refitted(mine)
    own = variance_grid(with_variance, GRID)
    assert fitted.fitted and not own.fitted
    assert own.num_samples == fitted.num_samples == skill.num_samples
    nearest = np.argmin(np.linalg.norm(skill.taus[0] - np.stack(np.meshgrid(*fitted.axes),
                                                                axis=-1), axis=-1))
    for i, j in [(0, 0), (0, GRID - 1), (GRID - 1, 0), (GRID // 2, GRID // 3),
                 np.unravel_index(nearest, (GRID, GRID))]:
        tau = np.array([fitted.axes[0][j], fitted.axes[1][i]])       # row: tau_1, column: tau_0
        assert fitted.values[i, j] == pytest.approx(
            bayesian_variance_by_hand(skill, skill.config, tau), rel=1e-9)
        assert own.values[i, j] == pytest.approx(
            bayesian_variance_by_hand(with_variance, mine, tau), rel=1e-9)
    with pytest.raises(ValueError, match='n >= 2'):
        variance_grid(skill, 1)


def test_incomplete_run_and_run_without_memory_still_plot(task, evaluator, runs, tmp_path):
    calls = []

    def stop_after_three():
        calls.append(1)
        return len(calls) > 3

    partial = tmp_path / 'partial'
    Learner(task, settings('hybrid', 2), partial, evaluator).run(should_stop=stop_after_three)
    run = load_run(partial)
    assert run['metrics'].summary is None and len(run['metrics'].tasks) == 3
    bare = tmp_path / 'bare'
    shutil.copytree(runs['scratch', 0], bare)
    (bare / 'memory.npz').unlink()
    assert load_run(bare)['memory_path'] is None
    for folders in ([partial, runs['bootstrap', 0]], [bare]):
        out = tmp_path / f'{folders[0].name}.png'
        assert_png(plot_runs(folders, out, grid_points=GRID))


def test_a_one_dimensional_task_plots(evaluator, tmp_path, monkeypatch):
    """reach_over_obstacle with only the obstacle's position as tau, learned for real."""
    folder = tmp_path / 'tasks'
    folder.mkdir()
    data = yaml.safe_load((EMBEDDED_TASKS / f'{TASK}.yaml').read_text())
    data['name'] = 'reach_over_obstacle_1d'
    data['task_parameters'] = data['task_parameters'][:1]
    (folder / 'reach_over_obstacle_1d.yaml').write_text(yaml.safe_dump(data))
    shutil.copy(EMBEDDED_TASKS / data['model'], folder / data['model'])
    monkeypatch.setenv('PSL_TASK_PATH', str(folder))       # the plot finds the tau names
    task_1d = load_task('reach_over_obstacle_1d')
    assert len(task_1d.parameters) == 1
    out = tmp_path / 'run'
    Learner(task_1d, settings('bootstrap', 0, num_tasks=6, skill=BAYES), out,
            BatchRollouts(task_1d)).run()
    skill = SkillMemory.read(out / 'memory.npz').get(task_1d.name)
    grid = variance_grid(skill, GRID)
    assert not grid.fitted and len(grid.axes) == 1 and grid.values.shape == (GRID,)
    assert np.all(grid.values > 0)
    assert_png(plot_runs([out], out / 'learning.png', grid_points=GRID))


def test_bad_folders_are_value_errors_naming_the_file(runs, tmp_path):
    with pytest.raises(ValueError, match='no such folder'):
        load_run(tmp_path / 'nothing')
    empty = tmp_path / 'empty'
    empty.mkdir()
    with pytest.raises(ValueError, match=f'{empty / "metrics.json"}: no such file'):
        load_run(empty)
    corrupt = tmp_path / 'corrupt'
    shutil.copytree(runs['bootstrap', 0], corrupt)
    metrics = corrupt / 'metrics.json'
    text = metrics.read_text()
    metrics.write_text(text[:len(text) // 2])                    # truncated
    with pytest.raises(ValueError, match=f'{metrics}: not readable as JSON'):
        plot_runs([runs['bootstrap', 0], corrupt], tmp_path / 'x.png')
    broken = json.loads(text)
    del broken['tasks'][0]['rollouts']
    metrics.write_text(json.dumps(broken))
    with pytest.raises(ValueError, match=f'{metrics}: corrupt metrics.*rollouts'):
        load_run(corrupt)
    assert not (tmp_path / 'x.png').exists()


def psl_plot(*args):
    return subprocess.run([sys.executable, '-m', 'psl_cli.main', 'plot', *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def test_psl_plot_command(runs, tmp_path):
    first, second = runs['bootstrap', 0], runs['scratch', 0]
    done = psl_plot(first, second)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(first / 'learning.png')
    assert_png(first / 'learning.png')
    out = tmp_path / 'chosen.png'
    done = psl_plot(first, '--out', out)
    assert done.returncode == 0 and done.stdout.strip() == str(out) and out.is_file()
    failed = psl_plot(first, tmp_path / 'missing')
    assert failed.returncode == 2
    assert 'psl plot:' in failed.stderr and str(tmp_path / 'missing') in failed.stderr


@pytest.mark.parametrize('name', ['point_reach_3d', 'payload_transport_timed'])
def test_the_task_variability_tasks_plot(name, tmp_path):
    """A target in 3-D (tau[2:] not drawn) and a duration beside a mass, learned for real."""
    target_task = load_task(name)
    out = tmp_path / 'run'
    Learner(target_task, settings('bootstrap', 0, num_tasks=4, skill=BAYES), out,
            BatchRollouts(target_task)).run()
    skill = SkillMemory.read(out / 'memory.npz').get(target_task.name)
    grid = variance_grid(skill, GRID)
    assert len(grid.axes) == 2 and grid.values.shape == (GRID, GRID)
    assert np.all(grid.values > 0)
    assert_png(plot_runs([out], out / 'learning.png', grid_points=GRID))


def test_a_run_keeps_its_task_and_plots_from_any_folder(tmp_path, monkeypatch):
    """Learned from a YAML outside the search path: metrics.json keeps its path and text, so
    the plot names the axes after the file has gone (from the copy) and while it is there."""
    from psl_bench.plot_learning import _task_info
    from psl_optimizer.metrics import read_metrics
    folder = tmp_path / 'elsewhere'
    folder.mkdir()
    data = yaml.safe_load((EMBEDDED_TASKS / f'{TASK}.yaml').read_text())
    data['name'] = 'my_reach'
    data['task_parameters'][0]['name'] = 'pillar_x'
    shutil.copy(EMBEDDED_TASKS / data['model'], folder / data['model'])
    (folder / 'my_reach.yaml').write_text(yaml.safe_dump(data))
    mine = load_task(str(folder / 'my_reach.yaml'))
    out = tmp_path / 'run'
    Learner(mine, settings('bootstrap', 0, num_tasks=2), out, BatchRollouts(mine)).run()
    metrics = read_metrics(out)
    assert metrics.task_path == str(folder / 'my_reach.yaml')
    assert yaml.safe_load(metrics.task_yaml)['name'] == 'my_reach'
    expected = (['pillar_x [m]', 'obstacle_height [m]'], data['reward']['success_threshold'])
    monkeypatch.chdir(tmp_path)
    assert _task_info(metrics) == expected                  # from the file where it was
    shutil.rmtree(folder)
    assert _task_info(metrics) == expected                  # from the copy of its text
    assert_png(plot_runs([out], tmp_path / 'gone.png', grid_points=GRID))


def test_runs_of_different_settings_are_drawn_apart(runs, task, evaluator, tmp_path):
    """Seeds of one experiment share a label; a session of another length gets its own."""
    from psl_bench.plot_learning import group_label, load_run
    short = tmp_path / 'short'
    Learner(task, settings('bootstrap', 0, num_tasks=3), short, evaluator).run()
    loaded = [load_run(runs['bootstrap', 0]), load_run(runs['bootstrap', 1]), load_run(short)]
    labels = [group_label(run, loaded) for run in loaded]
    assert labels[0] == labels[1] == f'bootstrap (num_tasks={NUM_TASKS})'
    assert labels[2] == 'bootstrap (num_tasks=3)'
    assert group_label(loaded[0], loaded[:2]) == 'bootstrap'
