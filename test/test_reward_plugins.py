"""Reward components from a user's own package: examples/psl_reward_example (hand_path_length)
pip-installed into a temporary folder (not into psl's sources or venv), found by its entry point
in batch mode, in the graph's processes and by `psl check`; and a package whose components
raise or return NaN, which fail only the rollouts they cannot score."""
import importlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_task.arm_model import ArmModel
from psl_task.task import TaskError, load_task

EXAMPLE = Path(__file__).resolve().parents[1] / 'examples' / 'psl_reward_example'
EXAMPLE_TASK = EXAMPLE / 'reach_over_obstacle_short_path.yaml'
FAR = 0.7       # m: obstacle_x beyond this, the faulty components fail
FAULTY = {
    'pyproject.toml': '''
[build-system]
requires = ["setuptools>=61", "wheel"]
build-backend = "setuptools.build_meta"
[project]
name = "psl-faulty-costs"
version = "0.0.1"
[project.entry-points."psl.reward_components"]
raises_far = "psl_faulty_costs:raises_far"
nan_far = "psl_faulty_costs:nan_far"
[tool.setuptools]
py-modules = ["psl_faulty_costs"]
''',
    'psl_faulty_costs.py': f'''
import numpy as np

def raises_far(rollouts):
    if (rollouts.taus[:, 0] > {FAR}).any():
        raise ValueError('an obstacle too far')
    return np.zeros(len(rollouts))

def nan_far(rollouts):
    return np.where(rollouts.taus[:, 0] > {FAR}, np.nan, 0.0)
'''}


def pip_install(source: Path, target: Path, build: Path) -> None:
    """pip-install the package at `source` (copied to `build`: pip builds in place) into
    the folder `target`, offline."""
    shutil.copytree(source, build)
    done = subprocess.run([sys.executable, '-m', 'pip', 'install', '--no-deps', '--no-index',
                           '--no-build-isolation', '--target', str(target), str(build)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope='module')
def plugins(tmp_path_factory):
    """Both packages installed into one folder, on the path of this process and of every
    process it starts (the graph's nodes, psl check) while the module runs."""
    root = tmp_path_factory.mktemp('plugins')
    faulty = root / 'faulty-src'
    faulty.mkdir()
    for name, text in FAULTY.items():
        (faulty / name).write_text(text)
    target = root / 'site'
    pip_install(EXAMPLE, target, root / 'example-build')
    pip_install(faulty, target, root / 'faulty-build')
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv('PYTHONPATH', os.pathsep.join(
            [str(target)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]))
        patch.syspath_prepend(str(target))
        importlib.invalidate_caches()
        yield target
    importlib.invalidate_caches()


def task_file(folder: Path, name: str, weights: dict, base: Path = EXAMPLE_TASK) -> Path:
    """A copy of the task `base` named `name`, with `weights` added to its reward."""
    data = yaml.safe_load(base.read_text())
    data['name'] = name
    data['reward']['weights'].update(weights)
    path = folder / f'{name}.yaml'
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope='module')
def faulty_task(plugins, tmp_path_factory):
    return task_file(tmp_path_factory.mktemp('faulty'), 'reach_with_faulty_costs',
                     {'raises_far': 1.0, 'nan_far': 1.0})


@pytest.fixture(scope='module')
def graph_task(plugins):
    return str(EXAMPLE_TASK)


@pytest.fixture(scope='module')
def task(plugins):
    return load_task(str(EXAMPLE_TASK))


def hand_points(task, q: np.ndarray) -> np.ndarray:
    """The hand's positions (T, 3) at the joint angles q (T, n): forward kinematics of the
    task's model file, written here independently of the reward's sensors."""
    model = mujoco.MjModel.from_xml_path(str(task.model_path))
    data = mujoco.MjData(model)
    site = model.site(task.end_effector_site).id
    points = []
    for qk in q:
        data.qpos[ArmModel(task).qpos_adr] = qk
        mujoco.mj_kinematics(model, data)
        points.append(data.site_xpos[site].copy())
    return np.array(points)


def test_a_component_of_a_users_package_scores_batch_and_graph_alike(task, graph_matches_batch):
    theta = policy_for(task).default_theta
    for tau in (task.tau_default, task.tau_high):
        evaluation, batch = graph_matches_batch(task, tau, theta)   # every component agrees
        cost = batch.evaluation.components['hand_path_length']
        points = hand_points(task, batch.q)
        assert cost == pytest.approx(np.linalg.norm(np.diff(points, axis=0), axis=1).sum(),
                                     rel=1e-9)
        # over the obstacle: longer than the straight line from the start to the end
        assert cost > 1.2 * np.linalg.norm(points[-1] - points[0])
        weights = task.reward.weights
        assert batch.evaluation.reward == pytest.approx(
            -sum(weights.get(k, 0.0) * v for k, v in batch.evaluation.components.items()),
            rel=1e-12)
        assert 'hand_path_length' in evaluation.component_names


def test_a_misspelt_component_is_refused_with_the_nearest_name(plugins, client, tmp_path):
    path = task_file(tmp_path, 'typo', {})
    text = path.read_text().replace('hand_path_length:', 'hand_path_lenght:')
    path.write_text(text)
    with pytest.raises(TaskError, match=r"'hand_path_lenght' \(did you mean hand_path_length\?\)"):
        load_task(str(path))
    task = load_task(str(EXAMPLE_TASK))
    result = client.rollout(str(path), task.tau_default, policy_for(task).default_theta)
    assert not result.success and 'did you mean hand_path_length' in result.message, \
        result.message


def test_psl_check_lists_the_components_and_where_they_come_from(plugins):
    done = subprocess.run(['psl', 'check', '--task', str(EXAMPLE_TASK)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    listed = {line.split()[-4]: line.split() for line in done.stdout.splitlines()
              if line.endswith(')') and ':' in line and line.startswith('  ')}
    assert listed['hand_path_length'] == [
        '*', '0.1', 'hand_path_length', 'psl_reward_example.costs:hand_path_length',
        '(psl-reward-example', '0.1.0)']                    # weighted by this task, its package
    assert listed['goal_error'][:4] == ['*', '10', 'goal_error',
                                         'psl_optimizer.reward:goal_error_cost']
    assert listed['orientation_error'][0] == 'orientation_error'     # registered, unused


def test_a_component_that_raises_or_returns_nan_fails_only_its_rollouts(task, faulty_task):
    faulty = load_task(str(faulty_task))
    theta = policy_for(task).default_theta
    taus = np.array([[0.6, 0.15], [0.75, 0.15], [0.65, 0.2], [0.78, 0.12]])
    thetas = np.repeat(theta[None], len(taus), axis=0)
    plain = BatchRollouts(task).run(thetas, taus)
    results = BatchRollouts(faulty).run(thetas, taus)
    for tau, mine, reference in zip(taus, results, plain):
        if tau[0] > FAR:
            # raises_far raises for the population and for this rollout alone; nan_far
            # returns NaN for it: the first component in the task's order is named
            assert "reward component 'raises_far' raised ValueError: an obstacle too far" == \
                mine.evaluation.failure
            assert mine.evaluation.reward == faulty.safety.penalty
            assert not mine.evaluation.fulfilled
        else:
            assert mine.evaluation.failure == ''
            assert mine.evaluation.reward == reference.evaluation.reward    # + 1 * 0.0, twice
            assert mine.evaluation.components['nan_far'] == 0.0


def test_a_nan_fails_the_rollout_with_the_components_name(task, tmp_path):
    nan_only = load_task(str(task_file(tmp_path, 'reach_nan_far', {'nan_far': 1.0})))
    theta = policy_for(task).default_theta
    near, far = BatchRollouts(nan_only).run(np.repeat(theta[None], 2, axis=0),
                                            np.array([[0.6, 0.15], [0.75, 0.15]]))
    assert near.evaluation.failure == '' and near.evaluation.components['nan_far'] == 0.0
    assert far.evaluation.failure == "reward component 'nan_far' returned nan (not finite)"
    assert far.evaluation.reward == nan_only.safety.penalty


def test_a_learning_session_goes_on_past_a_failing_component(faulty_task, tmp_path):
    out = tmp_path / 'session'
    done = subprocess.run(['psl', 'learn', '--task', str(faulty_task), '--tasks', '4',
                           '--budget', '6', '--seed', '3', '--test-tasks', '2', '--out',
                           str(out)], capture_output=True, text=True, timeout=600)
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['complete'], done.stderr
    tasks = metrics['tasks']
    assert {t['tau'][0] > FAR for t in tasks} == {True, False}, 'seed 3 draws both kinds'
    for record in tasks:
        if record['tau'][0] > FAR:
            assert record['failed'] == record['rollouts'] and not record['fulfilled']
            assert "'raises_far'" in record['failure']
            assert f"task {record['index'] + 1}: {record['rollouts']} rollouts not scored" \
                in done.stderr
        else:
            assert record['failed'] == 0 and record['failure'] == ''


def test_a_failing_component_fails_the_graphs_rollout_and_the_graph_serves_on(
        task, faulty_task, client, graph_matches_batch):
    theta = policy_for(task).default_theta
    result = client.rollout(str(faulty_task), [0.75, 0.15], theta)
    assert result.success, result.message
    ev = result.evaluation
    assert ev.failure == "reward component 'raises_far' raised ValueError: an obstacle too far"
    assert ev.reward == load_task(str(faulty_task)).safety.penalty and not ev.fulfilled
    graph_matches_batch(load_task(str(faulty_task)), np.array([0.6, 0.15]), theta)


def test_a_session_with_the_component_learns_the_same_in_batch_and_graph_mode(task, client):
    settings = dict(task=str(EXAMPLE_TASK), strategy='bootstrap', num_tasks=1,
                    max_rollouts_per_task=4, seed=5, num_test=1)
    # inside the memory node's folder (the graph's: the system's temporary folder)
    out = Path(tempfile.gettempdir()) / f'psl-reward-plugins-{os.getpid()}'
    try:
        graph = client.learn(timeout=600, mode='graph', output_dir=str(out / 'graph'),
                             **settings)
        assert graph.success, graph.message
        batch = client.learn(timeout=600, mode='batch', output_dir=str(out / 'batch'),
                             **settings)
        assert batch.success, batch.message
        tasks = [json.loads(Path(r.metrics_path).read_text())['tasks'] for r in (graph, batch)]
    finally:
        shutil.rmtree(out, ignore_errors=True)
    assert [t['rollouts'] for t in tasks[0]] == [t['rollouts'] for t in tasks[1]]
    assert [t['fulfilled'] for t in tasks[0]] == [t['fulfilled'] for t in tasks[1]]
    for key in ('start_reward', 'best_reward'):
        assert tasks[0][0][key] == pytest.approx(tasks[1][0][key], rel=1e-7), key
