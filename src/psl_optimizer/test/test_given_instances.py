"""Task selection 'given': a session learns on the instances it is handed (the environment
decides them), records them as they were, and refuses a source where none is expected."""
import numpy as np
import pytest

from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_optimizer.rollout_modes import make_rollouts
from psl_optimizer.task_selection import task_sequence
from psl_task.task import load_task


def test_the_session_learns_on_the_instances_it_is_given(tmp_path):
    task = load_task('reach_over_obstacle')
    given = task_sequence(task, 3, 77)          # any instances: here a seed the session lacks
    asked = []

    def source(index):
        asked.append(index)
        return given[index]
    settings = LearnSettings(num_tasks=3, num_test=2, task_selection='given',
                             search=SearchSettings(max_rollouts=20))
    metrics = Learner(task, settings, tmp_path, make_rollouts('batch', task),
                      instances=source).run()
    assert asked == [0, 1, 2]
    assert np.array_equal([t.tau for t in metrics.tasks], given)
    # a source's bad instance is the task's to refuse, with its reason
    bad = Learner(task, settings, tmp_path / 'bad', make_rollouts('batch', task),
                  instances=lambda index: np.array([np.nan, 0.1]))
    with pytest.raises(ValueError, match='task parameters must be finite'):
        bad.run()


def test_given_needs_a_source_and_only_given_takes_one(tmp_path):
    task = load_task('reach_over_obstacle')
    with pytest.raises(ValueError, match="'given'"):
        Learner(task, LearnSettings(task_selection='given'), tmp_path,
                make_rollouts('batch', task))
    with pytest.raises(ValueError, match="'given'"):
        Learner(task, LearnSettings(), tmp_path, make_rollouts('batch', task),
                instances=lambda index: np.zeros(2))
