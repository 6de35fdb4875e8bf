"""The learning curve of a session (`SessionProgress`) against the session's own records:
one point per training rollout, counters without gaps, per task the record's rollouts, its
answer's reward among the rollouts' and fulfilment, and the skill's variance at each instance as a replay of the memory's
samples in their order gives it."""
import math

import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_memory.skill_memory import SkillMemory
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import InProcessSkill, Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_optimizer.rollouts import Rollouts
from psl_optimizer.session_progress import SessionProgress
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
SETTINGS = LearnSettings(strategy='bootstrap', num_tasks=5, seed=4, num_test=3,
                         search=SearchSettings(max_rollouts=60))
VARIANCE_RTOL = 1e-12       # the same additions in the same order: equal but for BLAS sums


class Watched(Rollouts):
    """The learner's rollouts, each batch handed to a SessionProgress (as the learner node
    does), the points kept."""

    def __init__(self, inner: Rollouts):
        super().__init__(inner.task)
        self.inner, self.points, self.progress, self.batches = inner, [], None, 0

    def run(self, thetas, taus):
        results = self.inner.run(thetas, taus)
        self.batches += 1
        self.points += self.progress.after(taus, results)
        return results


@pytest.fixture(scope='module')
def session(tmp_path_factory):
    task = load_task(TASK)
    out = tmp_path_factory.mktemp('progress')
    watched = Watched(BatchRollouts(task))
    learner = Learner(task, SETTINGS, out, watched)
    watched.progress = SessionProgress(learner)
    metrics = learner.run()
    return task, out, metrics, watched.points


def test_one_point_per_training_rollout_with_counters_without_gaps(session):
    _, _, metrics, points = session
    records = metrics.tasks
    assert len(points) == sum(r.rollouts for r in records) == metrics.summary.total_rollouts
    assert [p.rollout for p in points] == list(range(1, len(points) + 1))
    for record in records:
        mine = [p for p in points if p.task_index == record.index]
        assert [p.rollouts_on_task for p in mine] == list(range(1, record.rollouts + 1))
        assert all(p.tau == tuple(record.tau) for p in mine)
        # the task's answer is one of its rollouts (the search's settling success, which a
        # draw before it may have beaten: the best on the task is at least the answer's)
        assert record.best_reward in [p.reward for p in mine]
        assert mine[-1].best_reward >= record.best_reward
        assert mine[-1].task_fulfilled == record.fulfilled
        assert [p.best_reward for p in mine] == list(np.maximum.accumulate(
            [p.reward for p in mine]))
        assert mine[0].reward == record.start_reward
        before = [r for r in records if r.index < record.index]
        assert all(p.tasks_done == len(before) for p in mine)
        assert all(p.tasks_solved == sum(r.fulfilled for r in before) for p in mine)


def test_the_variance_is_the_skills_before_the_task(session):
    task, out, metrics, points = session
    memory = next(iter(SkillMemory.read(out / 'memory.npz').skills.values())).get_state()
    taus, thetas = np.asarray(memory['taus']), np.asarray(memory['thetas'])
    skill = InProcessSkill(task, SETTINGS.skill, policy_for(task).default_theta)
    added = 0
    for record in metrics.tasks:
        point = next(p for p in points if p.task_index == record.index)
        expected = skill.variance(np.asarray(record.tau))
        assert expected is not None               # the default readout has a variance
        assert point.skill_variance == pytest.approx(float(np.mean(expected)),
                                                     rel=VARIANCE_RTOL)
        if record.fulfilled or not SETTINGS.add_only_fulfilled:
            skill.add(taus[added], thetas[added])
            added += 1
    assert added == len(taus)
    assert not any(math.isnan(p.skill_variance) for p in points)


def test_the_held_out_test_gives_no_point(session):
    _, _, metrics, points = session
    assert max(p.task_index for p in points) == SETTINGS.num_tasks - 1
    assert points[-1].tasks_done == SETTINGS.num_tasks - 1
