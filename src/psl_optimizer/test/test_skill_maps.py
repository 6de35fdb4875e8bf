"""Baselines in the learner's skill slot (`LearnSettings.skill_map`): a tiny session with each
map runs, keeps its samples in the checkpoint's memory file and resumes to the same result;
the elm map through the factory is the learner's default skill; settings and folders of
another map are refused."""
import dataclasses

import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_memory.skill_memory import SkillMemory
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import (BASELINE_MAPS, SKILL_MAPS, InProcessBaseline,
                                    InProcessSkill, Learner, LearnSettings, in_process_skill)
from psl_optimizer.policy_search import SearchSettings
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
TINY = LearnSettings(strategy='bootstrap', num_tasks=3, seed=2, num_test=3,
                     search=SearchSettings(max_rollouts=25))


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


@pytest.fixture(scope='module')
def evaluator(task):
    return BatchRollouts(task)


def learner(task, evaluator, settings, out):
    slot = in_process_skill(task, settings, policy_for(task).default_theta)
    return Learner(task, settings, out, evaluator, skill=slot)


def without_time(records):
    return [{k: v for k, v in r.items() if k != 'seconds'} for r in records]


def test_the_factory_builds_the_named_map(task):
    theta = policy_for(task).default_theta
    assert SKILL_MAPS == ('elm', 'library', 'gp')
    assert isinstance(in_process_skill(task, TINY, theta), InProcessSkill)
    for name, cls in BASELINE_MAPS.items():
        slot = in_process_skill(task, dataclasses.replace(TINY, skill_map=name), theta)
        assert isinstance(slot, InProcessBaseline) and isinstance(slot.map, cls)
        np.testing.assert_array_equal(slot.query(task.tau_low), theta)     # empty: default


@pytest.mark.parametrize('skill_map', SKILL_MAPS)
def test_a_tiny_session_with_each_map_resumes_to_the_same_result(skill_map, task, evaluator,
                                                                 tmp_path):
    s = dataclasses.replace(TINY, skill_map=skill_map)
    full = learner(task, evaluator, s, tmp_path / 'full').run().to_dict()
    assert full['complete'] and full['settings']['skill_map'] == skill_map
    calls = iter([False, False, True])                        # stop after two tasks
    partial = learner(task, evaluator, s, tmp_path / 'part').run(
        should_stop=lambda: next(calls, True)).to_dict()
    assert len(partial['tasks']) == 2 and not partial['complete']
    resumed = learner(task, evaluator, s, tmp_path / 'part').run().to_dict()
    assert without_time(resumed['tasks']) == without_time(full['tasks'])
    assert resumed['summary'] == full['summary']              # the same map after the resume
    # the memory file holds the fulfilled samples
    fulfilled = [t['tau'] for t in full['tasks'] if t['fulfilled']]
    if skill_map == 'elm':
        taus = SkillMemory.read(tmp_path / 'full' / 'memory.npz').get(TASK).taus
    else:
        with np.load(tmp_path / 'full' / 'memory.npz') as data:
            taus = data['taus']
            assert str(data['skill_map']) == skill_map
    np.testing.assert_array_equal(taus, np.array(fulfilled).reshape(-1, len(task.tau_names)))


@pytest.mark.parametrize('skill_map', SKILL_MAPS)
def test_a_restored_slot_answers_as_the_saved_one(skill_map, task, tmp_path):
    theta = policy_for(task).default_theta
    s = dataclasses.replace(TINY, skill_map=skill_map)
    saved = in_process_skill(task, s, theta)
    rng = np.random.default_rng(7)
    unit = rng.uniform(size=(4, len(task.tau_names)))
    for u in unit:
        saved.add(task.tau_low + u * (task.tau_high - task.tau_low),
                  theta + 0.1 * rng.standard_normal(theta.shape))
    saved.save(tmp_path / 'memory.npz')
    restored = in_process_skill(task, s, theta)
    restored.restore(tmp_path / 'memory.npz')
    empty = in_process_skill(task, s, theta)
    for u in rng.uniform(size=(5, len(task.tau_names))):
        tau = task.tau_low + u * (task.tau_high - task.tau_low)
        np.testing.assert_array_equal(restored.query(tau), saved.query(tau))
        assert not np.array_equal(restored.query(tau), empty.query(tau))
        a, b = restored.variance(tau), saved.variance(tau)
        assert (a is None and b is None) or np.array_equal(a, b)


def test_the_elm_map_of_the_factory_is_the_learners_default(task, evaluator, tmp_path):
    default = Learner(task, TINY, tmp_path / 'default', evaluator).run().to_dict()
    factory = learner(task, evaluator, TINY, tmp_path / 'factory').run().to_dict()
    assert without_time(default['tasks']) == without_time(factory['tasks'])
    assert default['summary'] == factory['summary']


def test_a_baseline_session_starts_empty_and_learns(task, evaluator, tmp_path):
    """After its session the library answers its own training instances with their theta."""
    s = dataclasses.replace(TINY, skill_map='library')
    slot = in_process_skill(task, s, policy_for(task).default_theta)
    Learner(task, s, tmp_path, evaluator, skill=slot).run()
    assert slot.map.num_samples >= 1
    for tau, theta in zip(slot.map.taus, slot.map.thetas):
        np.testing.assert_array_equal(slot.query(tau), theta)


def test_a_folder_of_another_map_is_refused(task, evaluator, tmp_path):
    library = dataclasses.replace(TINY, skill_map='library', num_tasks=1)
    learner(task, evaluator, library, tmp_path / 'library').run()
    learner(task, evaluator, dataclasses.replace(TINY, num_tasks=1), tmp_path / 'elm').run()
    for settings, folder in ((dataclasses.replace(library, skill_map='gp'), 'library'),
                             (library, 'elm')):
        with pytest.raises(ValueError, match='another session|skill map'):
            learner(task, evaluator, dataclasses.replace(settings, num_tasks=2),
                    tmp_path / folder).run()


@pytest.mark.parametrize('override, message', [
    (dict(skill_map='magic'), 'unknown skill map'),
    (dict(skill_map='library', continue_from='memory.npz'), 'continue_from'),
    (dict(skill_map='gp', continue_from='memory.npz'), 'continue_from'),
    (dict(skill_map='library', task_selection='variance'), 'variance'),
])
def test_settings_a_map_cannot_run_are_refused(override, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(TINY, **override)


def test_variance_selection_runs_with_the_gp(task, evaluator, tmp_path):
    s = dataclasses.replace(TINY, skill_map='gp', task_selection='variance', num_tasks=2)
    metrics = learner(task, evaluator, s, tmp_path).run()
    assert metrics.complete


def test_psl_learn_takes_a_skill_map(tmp_path, capsys):
    from psl_cli.main import main
    argv = ['learn', '--tasks', '2', '--budget', '20', '--test-tasks', '2', '--seed', '2',
            '--out', str(tmp_path / 'gp'), '--skill-map', 'gp']
    assert main(argv) == 0
    metrics = (tmp_path / 'gp' / 'metrics.json').read_text()
    assert '"skill_map": "gp"' in metrics
    with np.load(tmp_path / 'gp' / 'memory.npz') as data:
        assert str(data['skill_map']) == 'gp'
    capsys.readouterr()
    argv[argv.index('--out') + 1] = str(tmp_path / 'refused')
    assert main(argv[:-1] + ['magic']) == 2
    assert 'unknown skill map' in capsys.readouterr().err
    assert main(argv + ['--mode', 'graph']) == 2
    assert 'the learner node learns with the skill memory (elm) only' in capsys.readouterr().err
    assert not (tmp_path / 'refused').exists()           # refused before the folder is made
