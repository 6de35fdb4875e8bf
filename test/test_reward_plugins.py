"""Reward components from a user's own package: examples/psl_reward_example (hand_path_length)
pip-installed into a temporary folder (not into psl's sources or venv), found by its entry point
in batch mode, in the graph's processes and by `psl check`; and a package whose components
raise or return NaN, which fail only the rollouts they cannot score, and whose components try
to hurt the session (issue 46), in batch mode and in the graph's evaluator, which serves on: one
writes into its inputs (it gets read-only views: the write fails its rollouts and changes
nothing the others see), one returns 1+2j (refused), one does not return (bounded by the
task's reward.component_timeout), one fails every rollout (psl learn exits 1 with the
reason)."""
import importlib
import json
import os
import shutil
import subprocess
import sys
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
writes_hand_path = "psl_faulty_costs:writes_hand_path"
zeroes_quietly = "psl_faulty_costs:zeroes_quietly"
returns_complex = "psl_faulty_costs:returns_complex"
sleeps_until_released = "psl_faulty_costs:sleeps_until_released"
always_raises = "psl_faulty_costs:always_raises"
[tool.setuptools]
py-modules = ["psl_faulty_costs"]
''',
    'psl_faulty_costs.py': f'''
import os
import time

import numpy as np

ENTERED = []        # the populations sleeps_until_released was called on (this process)
WRITTEN = []        # what zeroes_quietly could write into (this process)

def raises_far(rollouts):
    if (rollouts.taus[:, 0] > {FAR}).any():
        raise ValueError('an obstacle too far')
    return np.zeros(len(rollouts))

def nan_far(rollouts):
    return np.where(rollouts.taus[:, 0] > {FAR}, np.nan, 0.0)

def writes_hand_path(rollouts):
    rollouts.measured.end_effector[:] = 0.0
    return np.zeros(len(rollouts))

def zeroes_quietly(rollouts):
    """Writes wherever it can and goes on: the hand's path, the joint angles, the weights."""
    writes = {{'hand': lambda: rollouts.measured.end_effector.fill(0.0),
              'q': lambda: rollouts.q.fill(0.0),
              'weights': lambda: rollouts.task.reward.weights.update(
                  (name, 0.0) for name in list(rollouts.task.reward.weights))}}
    for what, write in writes.items():
        try:
            write()
            WRITTEN.append(what)
        except Exception:
            pass
    return np.zeros(len(rollouts))

def returns_complex(rollouts):
    return np.full(len(rollouts), 1.0 + 2.0j)

def sleeps_until_released(rollouts):
    """Returns when the file PSL_FAULTY_RELEASE names exists (at most a minute)."""
    ENTERED.append(len(rollouts))
    deadline = time.monotonic() + 60.0
    while not os.path.exists(os.environ['PSL_FAULTY_RELEASE']) and time.monotonic() < deadline:
        time.sleep(0.01)
    return np.zeros(len(rollouts))

def always_raises(rollouts):
    raise RuntimeError('no cost for anyone')
'''}
SLOW_TIMEOUT = 2.0      # s: reward.component_timeout of the task of sleeps_until_released
NEAR = [0.6, 0.15]      # a task instance none of the faulty components treats apart


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
        patch.setenv('PSL_FAULTY_RELEASE', str(root / 'release'))   # sleeps_until_released
        patch.syspath_prepend(str(target))
        importlib.invalidate_caches()
        yield target
    importlib.invalidate_caches()


def task_file(folder: Path, name: str, weights: dict, base: Path = EXAMPLE_TASK,
              first: bool = False, **reward_keys) -> Path:
    """A copy of the task `base` named `name`, with `weights` added to its reward (`first`:
    before its own, so their components are called before the task's own plugins) and
    `reward_keys`."""
    data = yaml.safe_load(base.read_text())
    data['name'] = name
    own = data['reward']['weights']
    data['reward']['weights'] = {**weights, **own} if first else {**own, **weights}
    data['reward'].update(reward_keys)
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
    assert done.returncode == 0, done.stderr          # some rollouts were scored
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


def test_a_session_with_the_component_learns_the_same_in_batch_and_graph_mode(task, client,
                                                                           tmp_path):
    settings = dict(task=str(EXAMPLE_TASK), strategy='bootstrap', num_tasks=1,
                    max_rollouts_per_task=4, seed=5, num_test=1)
    # inside the memory node's folder (the run's: conftest.py memory_folder)
    graph = client.learn(timeout=600, mode='graph', output_dir=str(tmp_path / 'graph'),
                         **settings)
    assert graph.success, graph.message
    batch = client.learn(timeout=600, mode='batch', output_dir=str(tmp_path / 'batch'),
                         **settings)
    assert batch.success, batch.message
    tasks = [json.loads(Path(r.metrics_path).read_text())['tasks'] for r in (graph, batch)]
    assert [t['rollouts'] for t in tasks[0]] == [t['rollouts'] for t in tasks[1]]
    assert [t['fulfilled'] for t in tasks[0]] == [t['fulfilled'] for t in tasks[1]]
    for key in ('start_reward', 'best_reward'):
        assert tasks[0][0][key] == pytest.approx(tasks[1][0][key], rel=1e-7), key


# -- components that try to hurt the session (issue 46) -----------------------------------------
@pytest.fixture(scope='module')
def unsafe(plugins, tmp_path_factory):
    """The tasks of the components that try to hurt the session, by component."""
    folder = tmp_path_factory.mktemp('unsafe')
    return {
        'writes_hand_path': task_file(folder, 'reach_writing_its_inputs',
                                      {'writes_hand_path': 1.0}, first=True),
        'zeroes_quietly': task_file(folder, 'reach_zeroing_quietly', {'zeroes_quietly': 1.0},
                                    first=True),
        'returns_complex': task_file(folder, 'reach_complex', {'returns_complex': 1.0}),
        'sleeps_until_released': task_file(folder, 'reach_sleeping',
                                           {'sleeps_until_released': 1.0},
                                           component_timeout=SLOW_TIMEOUT),
        'always_raises': task_file(folder, 'reach_never_scored', {'always_raises': 1.0}),
    }


WRITE_REFUSED = ("reward component 'writes_hand_path' raised ValueError: assignment "
                 'destination is read-only')
COMPLEX_REFUSED = ("reward component 'returns_complex' returned complex numbers ((1+2j), ...), "
                   'not real costs')
LATE = (f"reward component 'sleeps_until_released' did not return within {SLOW_TIMEOUT:g} s "
        '(reward.component_timeout)')
STILL_LATE = (f"reward component 'sleeps_until_released' has not returned from a call that "
              f'passed its {SLOW_TIMEOUT:g} s (reward.component_timeout): its rollouts fail '
              'until it does')


def population_of(task, count: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """`count` copies of the default theta on near task instances."""
    theta = policy_for(task).default_theta
    return np.repeat(theta[None], count, axis=0), np.array([NEAR, [0.62, 0.12], [0.66, 0.18]])


def test_batch_a_component_that_writes_into_its_inputs_fails_its_rollouts(task, unsafe):
    rollouts = BatchRollouts(load_task(str(unsafe['writes_hand_path'])))
    results = rollouts.run(*population_of(task))
    assert [r.evaluation.failure for r in results] == [WRITE_REFUSED] * 3
    assert rollouts.failed == 3 and not any(r.evaluation.fulfilled for r in results)


def test_batch_a_component_that_writes_quietly_changes_nothing_the_others_see(task, unsafe):
    import psl_faulty_costs

    thetas, taus = population_of(task)
    plain = BatchRollouts(task).run(thetas, taus)
    written = len(psl_faulty_costs.WRITTEN)
    quiet = BatchRollouts(load_task(str(unsafe['zeroes_quietly']))).run(thetas, taus)
    assert psl_faulty_costs.WRITTEN[written:] == [], 'a write went through'
    for mine, theirs in zip(quiet, plain):
        assert mine.evaluation.failure == ''
        assert mine.evaluation.components == {**theirs.evaluation.components,
                                              'zeroes_quietly': 0.0}
        assert mine.evaluation.reward == theirs.evaluation.reward
        assert mine.evaluation.fulfilled == theirs.evaluation.fulfilled
        assert np.array_equal(mine.q, theirs.q)
    assert load_task(str(EXAMPLE_TASK)).reward.weights['hand_path_length'] == 0.1


def test_batch_a_component_returning_a_complex_cost_fails_its_rollouts(task, unsafe):
    rollouts = BatchRollouts(load_task(str(unsafe['returns_complex'])))
    results = rollouts.run(*population_of(task))
    assert [r.evaluation.failure for r in results] == [COMPLEX_REFUSED] * 3
    assert rollouts.failed == 3


@pytest.fixture
def release(plugins):
    """The file that releases sleeps_until_released: absent while the test runs, made at its
    end (a call still sleeping returns), removed before the next."""
    path = Path(os.environ['PSL_FAULTY_RELEASE'])
    path.unlink(missing_ok=True)
    try:
        yield path
    finally:
        path.touch()


def test_batch_a_component_that_does_not_return_fails_its_populations_until_it_does(
        task, unsafe, release, wait_until):
    import psl_faulty_costs

    slow = BatchRollouts(load_task(str(unsafe['sleeps_until_released'])))
    thetas, taus = population_of(task)
    entered = len(psl_faulty_costs.ENTERED)
    assert [r.evaluation.failure for r in slow.run(thetas, taus)] == [LATE] * 3
    # its call still runs: the next populations fail with the reason, without calling it
    assert [r.evaluation.failure for r in slow.run(thetas, taus)] == [STILL_LATE] * 3
    assert [r.evaluation.failure for r in slow.run(thetas[:1], taus[:1])] == [STILL_LATE]
    assert psl_faulty_costs.ENTERED[entered:] == [3] and slow.failed == 7
    release.touch()
    scored = []
    assert wait_until(lambda: scored.append(slow.run(thetas, taus)) or
                      scored[-1][0].evaluation.failure == '', timeout=30.0)
    assert psl_faulty_costs.ENTERED[entered:] == [3, 3]     # called once more, when it could
    plain = BatchRollouts(task).run(thetas, taus)
    assert [r.evaluation.reward for r in scored[-1]] == [r.evaluation.reward for r in plain]


def learn(task: Path, out: Path, *options: str) -> subprocess.CompletedProcess:
    return subprocess.run(['psl', 'learn', '--task', str(task), '--tasks', '1', '--budget', '2',
                           '--seed', '1', '--test-tasks', '1', '--out', str(out), *options],
                          capture_output=True, text=True, timeout=600)


def check_nothing_scored(done: subprocess.CompletedProcess, out: Path) -> None:
    """psl learn exited 1 with the reason; the session's metrics were written."""
    assert done.returncode == 1, (done.returncode, done.stderr)
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['complete']
    rollouts, failed, refused = (sum(t[key] for t in metrics['tasks'])
                                 for key in ('rollouts', 'failed', 'refused'))
    assert failed > 0 and failed + refused == rollouts
    refusals = f', {refused} refused by the safety check' if refused else ''
    line = done.stderr.strip().splitlines()[-1]
    assert line == (f"psl learn: the reward scored none of the session's {rollouts} rollouts "
                    f"({failed} not scored{refusals}): reward component 'always_raises' raised "
                    f"RuntimeError: no cost for anyone (metrics in {out / 'metrics.json'})"), \
        done.stderr


def test_batch_a_session_that_could_score_nothing_exits_1_with_the_reason(unsafe, tmp_path):
    out = tmp_path / 'never_scored'
    check_nothing_scored(learn(unsafe['always_raises'], out), out)


def test_graph_a_component_that_writes_into_its_inputs_fails_the_rollout_and_the_graph_serves_on(
        task, unsafe, client, graph_matches_batch):
    theta = policy_for(task).default_theta
    result = client.rollout(str(unsafe['writes_hand_path']), NEAR, theta)
    assert result.success, result.message
    assert result.evaluation.failure == WRITE_REFUSED and not result.evaluation.fulfilled
    plain = client.rollout(str(EXAMPLE_TASK), NEAR, theta)
    quiet = client.rollout(str(unsafe['zeroes_quietly']), NEAR, theta)
    assert plain.success and quiet.success, (plain.message, quiet.message)
    mine, theirs = quiet.evaluation, plain.evaluation
    assert mine.failure == '' and mine.reward == theirs.reward
    assert mine.fulfilled == theirs.fulfilled
    components = dict(zip(theirs.component_names, theirs.component_values))
    assert dict(zip(mine.component_names, mine.component_values)) == {**components,
                                                                      'zeroes_quietly': 0.0}
    assert components['hand_path_length'] > 0.5 and list(mine.position) == list(theirs.position)
    graph_matches_batch(task, np.array(NEAR), theta)


def test_graph_a_component_returning_a_complex_cost_fails_the_rollout_and_the_graph_serves_on(
        task, unsafe, client, graph_matches_batch):
    theta = policy_for(task).default_theta
    result = client.rollout(str(unsafe['returns_complex']), NEAR, theta)
    assert result.success, result.message
    assert result.evaluation.failure == COMPLEX_REFUSED and not result.evaluation.fulfilled
    graph_matches_batch(task, np.array(NEAR), theta)


def test_graph_a_component_that_does_not_return_fails_its_rollouts_and_the_graph_serves_on(
        task, unsafe, client, release, wait_until, graph_matches_batch):
    theta = policy_for(task).default_theta
    slow = str(unsafe['sleeps_until_released'])
    first = client.rollout(slow, NEAR, theta)
    assert first.success, first.message
    assert first.evaluation.failure == LATE and not first.evaluation.fulfilled
    second = client.rollout(slow, NEAR, theta)     # its call still runs in the evaluator
    assert second.success and second.evaluation.failure == STILL_LATE, second.evaluation.failure
    graph_matches_batch(task, np.array(NEAR), theta)        # the evaluator serves on
    release.touch()
    scored = []
    assert wait_until(lambda: scored.append(client.rollout(slow, NEAR, theta)) or
                      scored[-1].evaluation.failure == '', timeout=60.0), \
        scored[-1].evaluation.failure
    plain = client.rollout(str(EXAMPLE_TASK), NEAR, theta)
    assert scored[-1].evaluation.reward == plain.evaluation.reward


def test_graph_a_session_that_could_score_nothing_exits_1_with_the_reason(unsafe, client,
                                                                         tmp_path):
    out = tmp_path / 'never_scored'
    check_nothing_scored(learn(unsafe['always_raises'], out, '--mode', 'graph'), out)
