"""metrics.json: what the learner writes reads back into the same Metrics and writes out to the
same file; a missing, truncated or foreign file is a MetricsError naming it; the episodes that
foreign goals preempted are counted per task."""
import json

import pytest

from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.metrics import METRICS_FILE, MetricsError, read_metrics
from psl_optimizer.policy_search import SearchSettings
from psl_task.task import load_task

SMALL = dict(strategy='bootstrap', num_tasks=2, seed=1, num_test=3,
             search=SearchSettings(max_rollouts=20))


@pytest.mark.parametrize('task_name', ['reach_over_obstacle', 'payload_transport'])
def test_the_file_reads_back_to_the_same_metrics_and_the_same_text(task_name, tmp_path):
    task = load_task(task_name)
    metrics = Learner(task, LearnSettings(**SMALL), tmp_path, BatchRollouts(task)).run()
    text = (tmp_path / METRICS_FILE).read_text()
    again = read_metrics(tmp_path)
    assert again == metrics
    assert json.loads(text) == again.to_dict()
    assert again.write(tmp_path / '..' / tmp_path.name).read_text() == text
    summary = again.summary
    assert summary.total_rollouts == sum(t.rollouts for t in again.tasks)
    assert (summary.tracking_rmse is None) == (task_name == 'reach_over_obstacle')
    if summary.tracking_rmse is not None:          # flat keys in the file
        data = json.loads(text)['summary']
        assert data['tracking_rmse_learned'] == summary.tracking_rmse['learned']
        assert data['tracking_rmse_oracle_mean'] == summary.tracking_rmse_mean['oracle']


def test_an_unfinished_session_has_no_summary(tmp_path):
    calls = iter([False, True])
    task = load_task('reach_over_obstacle')
    metrics = Learner(task, LearnSettings(**SMALL), tmp_path,
                      BatchRollouts(task)).run(should_stop=lambda: next(calls, True))
    assert not metrics.complete and metrics.summary is None and len(metrics.tasks) == 1
    assert 'summary' not in json.loads((tmp_path / METRICS_FILE).read_text())
    assert read_metrics(tmp_path) == metrics and metrics.num_tasks == SMALL['num_tasks']


def test_bad_files_are_refused_with_their_name(tmp_path):
    with pytest.raises(MetricsError, match='no such file'):
        read_metrics(tmp_path)
    path = tmp_path / METRICS_FILE
    for text, words in (('{"task": "x", "str', 'not readable as JSON'), ('[1, 2]', 'not a JSON'),
                        ('{"task": "x", "strategy": "s", "seed": 0}', "no 'tasks'"),
                        ('{"task": "x", "strategy": "s", "seed": 0, "tasks": [{"index": 0}]}',
                         "no 'tau'")):
        path.write_text(text)
        with pytest.raises(MetricsError, match=words) as info:
            read_metrics(tmp_path)
        assert str(path) in str(info.value)
    assert issubclass(MetricsError, ValueError)


class Preempting(BatchRollouts):
    """Batch rollouts that report a preemption in the batches `at` (as graph mode does when a
    goal that is not psl's preempted an episode, which it then ran again: the same results)."""

    def __init__(self, task, at):
        super().__init__(task)
        self.at, self.batches = set(at), 0

    def run(self, thetas, taus):
        self.batches += 1
        if self.batches in self.at:
            self.preempted += 1
        return super().run(thetas, taus)


def test_preempted_episodes_are_counted_per_task_and_change_nothing_else(tmp_path):
    task = load_task('reach_over_obstacle')
    plain = Learner(task, LearnSettings(**SMALL), tmp_path / 'plain', BatchRollouts(task)).run()
    rollouts = Preempting(task, at=(1, 2))
    metrics = Learner(task, LearnSettings(**SMALL), tmp_path / 'preempted', rollouts).run()
    assert [t.preempted for t in metrics.tasks] == [2, 0]   # both in the first task's search
    assert metrics.preempted == 2 and plain.preempted == 0
    assert read_metrics(tmp_path / 'preempted') == metrics
    strip = lambda m: [{k: v for k, v in t.to_dict().items()      # noqa: E731
                        if k not in ('seconds', 'preempted')} for t in m.tasks]
    assert strip(metrics) == strip(plain) and metrics.summary == plain.summary
