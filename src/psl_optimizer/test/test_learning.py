"""The learning loop on the embedded task, in batch mode: it improves, and it resumes."""
import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from psl_memory.skill_memory import SkillMemory
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.task_selection import held_out_tasks, task_sequence
from psl_optimizer.policy_search import SearchSettings
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
SETTINGS = LearnSettings(strategy='bootstrap', num_tasks=6, seed=3, num_test=12,
                         search=SearchSettings(max_rollouts=120))


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


@pytest.fixture(scope='module')
def evaluator(task):
    return BatchRollouts(task)


@pytest.fixture(scope='module')
def finished(task, evaluator, tmp_path_factory):
    out = tmp_path_factory.mktemp('learn_full')
    return out, Learner(task, SETTINGS, out, evaluator).run().to_dict()


def memory_arrays(path):
    skill = next(iter(SkillMemory.read(path).skills.values()))
    return skill.get_state()


# A resumed session reloads its memory and checkpoint from files: the same operations on arrays
# at other addresses, which numpy's SIMD loops may sum in another order (seen: a reward
# differing in its 16th digit). Its decisions are the same; its floats within this tolerance.
RELATIVE = 1e-9


def assert_same(a, b, where: str = '') -> None:
    """Two sessions' records (or summaries): the same keys, counts, flags and instances, every
    float within RELATIVE (math.isclose)."""
    if isinstance(a, dict) and isinstance(b, dict):
        assert a.keys() == b.keys(), (where, sorted(a), sorted(b))
        for key in a:
            assert_same(a[key], b[key], f'{where}.{key}')
    elif isinstance(a, list) and isinstance(b, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f'{where}[{i}]')
    elif isinstance(a, float) or isinstance(b, float):
        assert not isinstance(a, bool) and not isinstance(b, bool), where
        assert math.isclose(a, b, rel_tol=RELATIVE, abs_tol=0.0) or a == b, (where, a, b)
    else:
        assert a == b, (where, a, b)


def assert_same_session(a: list, b: list) -> None:
    """Two sessions' task records, their times left out (`assert_same`)."""
    assert_same(without_time(a), without_time(b), 'tasks')


def assert_same_memory(a: dict, b: dict) -> None:
    """Two memories' arrays: the same keys and shapes, values within RELATIVE of each array's
    largest magnitude."""
    assert a and a.keys() == b.keys(), (sorted(a), sorted(b))
    for key in a:
        x, y = np.asarray(a[key]), np.asarray(b[key])
        assert x.shape == y.shape, key
        if x.dtype.kind == 'f':
            scale = max(float(np.max(np.abs(x), initial=0.0)), np.finfo(float).tiny)
            np.testing.assert_allclose(x, y, rtol=0.0, atol=RELATIVE * scale, err_msg=key)
        else:
            np.testing.assert_array_equal(x, y, err_msg=key)


def without_time(records):
    return [{k: v for k, v in r.items() if k != 'seconds'} for r in records]


def test_sequences_are_seeded_and_held_out_tasks_are_new(task):
    np.testing.assert_array_equal(task_sequence(task, 5, 1), task_sequence(task, 5, 1))
    assert not np.array_equal(task_sequence(task, 5, 1), task_sequence(task, 5, 2))
    train, test = task_sequence(task, 50, 1), held_out_tasks(task, 20, 1)
    assert not any(np.any(np.all(np.isclose(train, t), axis=1)) for t in test)


def test_a_short_session_improves_over_the_demonstration(task, evaluator, finished):
    out, metrics = finished
    assert metrics['complete'] and len(metrics['tasks']) == SETTINGS.num_tasks
    summary = metrics['summary']
    assert summary['total_rollouts'] == sum(r['rollouts'] for r in metrics['tasks'])
    # the skill, queried zero-shot on held-out instances, beats the demonstration there
    test = np.array(summary['test_taus'])
    demo = evaluator.run(np.tile(evaluator.policy.default_theta, (len(test), 1)), test)
    demo_success = np.mean([r.evaluation.fulfilled for r in demo])
    demo_reward = np.mean([r.evaluation.reward for r in demo])
    assert summary['zero_shot_success_rate'] > demo_success
    assert summary['zero_shot_mean_reward'] > demo_reward
    # every fulfilled task is in the memory
    skill = SkillMemory.read(out / 'memory.npz').get(TASK)
    assert skill.num_samples == sum(r['fulfilled'] for r in metrics['tasks'])


def test_stopped_session_resumes_to_the_same_result(task, evaluator, finished, tmp_path):
    full_out, full = finished
    calls = []

    def stop_after_two():
        calls.append(1)
        return len(calls) > 2

    partial = Learner(task, SETTINGS, tmp_path, evaluator).run(
        should_stop=stop_after_two).to_dict()
    assert not partial['complete'] and len(partial['tasks']) == 2
    resumed = Learner(task, SETTINGS, tmp_path, evaluator).run().to_dict()
    assert_same_session(resumed['tasks'], full['tasks'])
    assert_same(resumed['summary'], full['summary'], 'summary')
    assert_same_memory(memory_arrays(tmp_path / 'memory.npz'),
                       memory_arrays(full_out / 'memory.npz'))


def test_a_killed_learner_process_resumes_from_its_checkpoint(finished, tmp_path):
    """SIGKILL `psl learn` after its second task, start it again: same memory, same tasks."""
    full_out, full = finished
    cmd = [sys.executable, '-m', 'psl_cli.main', 'learn', '--strategy', SETTINGS.strategy,
           '--tasks', str(SETTINGS.num_tasks), '--seed', str(SETTINGS.seed),
           '--budget', str(SETTINGS.search.max_rollouts), '--test-tasks',
           str(SETTINGS.num_test), '--out', str(tmp_path)]
    checkpoint = tmp_path / 'checkpoint.json'       # written atomically (os.replace)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if checkpoint.is_file() and len(json.loads(checkpoint.read_text())['tasks']) >= 2:
                break
            time.sleep(0.01)
    finally:
        # its whole process group (its own session; the group's ID cannot be reused before
        # the leader is reaped by the wait below)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, f'psl learn ended by itself ({proc.returncode})'
    done_before = len(json.loads((tmp_path / 'checkpoint.json').read_text())['tasks'])
    assert 2 <= done_before < SETTINGS.num_tasks, 'killed too late to test a resume'
    assert subprocess.run(cmd, capture_output=True, timeout=300).returncode == 0
    metrics = json.loads((tmp_path / 'metrics.json').read_text())
    assert_same_session(metrics['tasks'], full['tasks'])
    assert_same_memory(memory_arrays(tmp_path / 'memory.npz'),
                       memory_arrays(full_out / 'memory.npz'))


def test_a_checkpoint_of_another_session_is_refused(task, evaluator, finished):
    out, _ = finished
    other = LearnSettings(strategy='scratch', num_tasks=6, seed=3)
    with pytest.raises(ValueError, match='another session'):
        Learner(task, other, out, evaluator).run()


def test_variance_selection_picks_the_candidate_the_skill_knows_least(task, tmp_path):
    """Of the candidates it asked the skill about (recorded), the chosen instance has the
    largest mean predictive variance; the same call chooses the same; it lies away from the
    samples."""
    from psl_optimizer.learning import InProcessSkill
    from psl_optimizer.task_selection import most_uncertain
    from psl_controller.policy import policy_for

    skill = InProcessSkill(task, LearnSettings().skill, policy_for(task).default_theta)
    theta = policy_for(task).default_theta
    low, high = task.tau_low, task.tau_high
    for u in np.linspace(0.0, 0.4, 6):                # samples in one corner only
        skill.add(low + u * (high - low), theta)

    def choose(count, index):
        asked = []

        def variance(tau):
            asked.append(np.array(tau, copy=True))
            return skill.variance(tau)
        return most_uncertain(task, variance, count, seed=1, index=index), np.array(asked)

    chosen, asked = choose(30, index=0)
    assert asked.shape == (30, len(task.tau_names))
    assert len(np.unique(asked, axis=0)) == 30                 # 30 different candidates
    assert np.all((asked >= low) & (asked <= high))            # from the task's ranges
    scores = np.array([np.mean(skill.variance(tau)) for tau in asked])
    assert np.any(np.all(asked == chosen, axis=1))             # one of them ...
    assert np.mean(skill.variance(chosen)) == scores.max()     # ... the least certain
    assert scores.max() > np.median(scores)                    # (a choice that matters)
    again, asked_again = choose(30, index=0)
    np.testing.assert_array_equal(again, chosen)
    np.testing.assert_array_equal(asked_again, asked)
    unit = (chosen - low) / (high - low)
    assert np.linalg.norm(unit) > 0.8                  # far from the sampled corner
    without = InProcessSkill(task, dataclasses.replace(LearnSettings().skill,
                                                       readout='incremental_ridge'), theta)
    with pytest.raises(ValueError, match='variance'):
        most_uncertain(task, without.variance, 5, seed=1, index=0)


def test_a_variance_selected_session_resumes_to_the_same_tasks(task, evaluator, tmp_path):
    s = dataclasses.replace(SETTINGS, num_tasks=4, task_selection='variance')
    full = Learner(task, s, tmp_path / 'full', evaluator).run().to_dict()
    first = Learner(task, dataclasses.replace(s, num_tasks=4), tmp_path / 'part', evaluator)
    calls = iter([False, False, True])
    first.run(should_stop=lambda: next(calls, True))
    resumed = Learner(task, s, tmp_path / 'part', evaluator).run().to_dict()
    assert_same_session(resumed['tasks'], full['tasks'])
    random = [t['tau'] for t in Learner(task, dataclasses.replace(s, task_selection='random'),
                                        tmp_path / 'random', evaluator).run().to_dict()['tasks']]
    assert random != [t['tau'] for t in full['tasks']]


def test_a_session_killed_between_its_memory_and_its_checkpoint_resumes_alike(
        task, evaluator, finished, tmp_path):
    """The third task's memory is saved, then the process dies before its checkpoint: the
    resumed session redoes the third task with the memory of the second (before, memory.npz
    already held the third sample and the redo added it twice: 7 samples, not 6)."""
    full_out, full = finished

    class Killed(Exception):
        pass
    learner = Learner(task, SETTINGS, tmp_path, evaluator)
    save, saved = learner.skill.save, []

    def save_then_die(path):
        save(path)
        saved.append(path)
        if len(saved) == 3:
            raise Killed
    learner.skill.save = save_then_die
    with pytest.raises(Killed):
        learner.run()
    assert len(json.loads((tmp_path / 'checkpoint.json').read_text())['tasks']) == 2
    resumed = Learner(task, SETTINGS, tmp_path, evaluator).run().to_dict()
    assert_same_session(resumed['tasks'], full['tasks'])
    assert_same_memory(memory_arrays(tmp_path / 'memory.npz'),
                       memory_arrays(full_out / 'memory.npz'))
    assert not sorted(tmp_path.glob('memory.task*.npz'))


@pytest.mark.parametrize('change', [
    {'search': SearchSettings(max_rollouts=SETTINGS.search.max_rollouts + 1)},
    {'skill': dataclasses.replace(SETTINGS.skill, regularization=0.5)},
    {'add_only_fulfilled': not SETTINGS.add_only_fulfilled},
])
def test_a_resume_with_another_budget_or_skill_is_refused(task, evaluator, finished, change):
    """The checkpoint names what decided its searches and its skill: resuming it with another
    budget, readout or sample rule would go on as another session, silently; it is refused."""
    out, _ = finished
    with pytest.raises(ValueError, match='another session'):
        Learner(task, dataclasses.replace(SETTINGS, **change), out, evaluator).run()
