"""``psl bench dynamics`` on a small budget: the report's fields, the table, refusals."""
import pytest

from psl_bench import dynamics as bench_dynamics


def test_small_run_reports_tracking_errors_and_targets(tmp_path):
    report = bench_dynamics.run(optimisers=['ilc'], seeds=[0], num_tasks=3, budget=40,
                                num_test=2, out=tmp_path)
    mean = report['optimisers']['ilc']['mean']
    assert mean['pd_only'] > mean['oracle'] > 0.0
    assert mean['reduction_vs_pd'] == pytest.approx(1.0 - mean['learned'] / mean['pd_only'])
    assert set(mean['met']) == {'reduction_vs_pd', 'ratio_to_oracle'}
    assert len(report['held_out_example']['taus']) == 2
    assert (tmp_path / 'payload_transport-dynamics-ilc-seed0' / 'metrics.json').is_file()
    table = bench_dynamics.format_table(report)
    assert '| ilc |' in table and 'oracle' in table and ('met' in table or 'MISSED' in table)


def test_unknown_optimiser_and_task_without_feedforward_are_refused():
    with pytest.raises(ValueError, match='optimiser'):
        bench_dynamics.run(optimisers=['sgd'], seeds=[0])
    with pytest.raises(ValueError, match='feed-forward'):
        bench_dynamics.run(task_name='reach_over_obstacle', seeds=[0])
