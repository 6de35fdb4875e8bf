"""psl bench encodings: the GMR variant changes only the encoding; the selection curve is the
sessions' own zero-shot success, checked against an independent session."""
import tempfile

import pytest

from psl_bench import encodings as bench_encodings
from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_task.task import load_task

TASK = 'reach_over_obstacle'


def test_the_gmr_variant_changes_only_the_encoding():
    base = load_task(TASK)
    gmr = bench_encodings.encoding_variant(base, 'gmr', 5)
    assert gmr.policy.kind == 'gmr' and base.policy.kind == 'dmp'
    assert policy_for(gmr).num_parameters == 2 * 5 * base.n_joints
    assert gmr.tau_names == base.tau_names and gmr.reward == base.reward


@pytest.fixture(scope='module')
def selection():
    return bench_encodings.run_selection(TASK, seeds=[2], num_tasks=4, budget=40, num_test=6)


def test_the_selection_curve_is_the_sessions_zero_shot_success(selection):
    for name, rows in selection.items():
        row = rows[0]
        used = [u for u, _ in row['curve']]
        assert len(row['curve']) == 4 and used == sorted(used)
        settings = LearnSettings(strategy='bootstrap', num_tasks=4, seed=2, num_test=6,
                                 task_selection=name, search=SearchSettings(max_rollouts=40))
        with tempfile.TemporaryDirectory() as out:
            task = load_task(TASK)
            metrics = Learner(task, settings, out, BatchRollouts(task)).run().to_dict()
        assert row['total_rollouts'] == metrics['summary']['total_rollouts'] == used[-1]
        assert row['final_success'] == metrics['summary']['zero_shot_success_rate']
        reached = [i for i, (_, ok) in enumerate(row['curve']) if ok >= bench_encodings.TARGET]
        if reached:
            assert row['tasks_to_target'] == reached[0] + 1
            assert row['rollouts_to_target'] == row['curve'][reached[0]][0]
        else:
            assert row['tasks_to_target'] is None


def test_the_table_and_a_bad_setting(selection):
    report = {'settings': {'task': TASK, 'seeds': [2], 'tasks': 4, 'budget': 40,
                           'test_tasks': 6, 'after': 2, 'n_components': 6},
              'encodings': {'dmp': [{'theta_size': 24, 'demonstration_success': 0.5,
                                     'total_rollouts': 10, 'late_rollouts_per_task': 1.0,
                                     'fulfilled_tasks': 4, 'zero_shot_success': 1.0,
                                     'zero_shot_reward': -0.1}]},
              'selection': selection}
    table = bench_encodings.format_tables(report)
    assert '| dmp | 24 | 50.00 % | 10.00 |' in table and '| random |' in table
    with pytest.raises(ValueError, match='--after'):
        bench_encodings.run(TASK, seeds=[2], num_tasks=3, after=3)
