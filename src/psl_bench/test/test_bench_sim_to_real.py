"""``psl bench sim-to-real`` on a tiny configuration: every session runs on the robot, the
table shows the report's numbers; bad settings are refused."""
import pytest

from psl_bench import sim_to_real
from psl_optimizer.metrics import read_metrics


@pytest.fixture(scope='module')
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp('s2r')
    report = sim_to_real.run(tasks=['payload_transport'], nominal_tasks=2, num_tasks=2,
                             num_test=2, budget=20, ilc_iterations=2, out=out)
    return report, out


def test_the_sessions_run_on_the_robot_and_the_continued_ones_from_the_simulated_skill(tiny):
    report, out = tiny
    r = report['tasks']['payload_transport']
    assert set(r['sessions']) == {'scratch', 'residual', 'samples'}
    folder = out / 'payload_transport'
    assert read_metrics(folder / 'nominal').settings['model_error'] == ''
    for name, way in (('scratch', ''), ('continued-residual', 'residual'),
                      ('continued-samples', 'samples')):
        metrics = read_metrics(folder / name)
        assert metrics.settings['model_error'] == sim_to_real.REAL_ROBOT
        assert metrics.settings['continuation'] == way
        assert len(metrics.tasks) == 2 and len(metrics.summary.test_taus) == 2
        assert metrics.settings['continue_from'] == ('' if name == 'scratch' else
                                                     str(folder / 'nominal' / 'memory.npz'))
    tracking = r['tracking']
    assert set(tracking) == set(sim_to_real.TRACKING)
    # the simulated feed-forward helps on the robot; ILC on the robot helps more
    assert tracking['simulated']['mean'] < tracking['pd_only']['mean']
    assert tracking['ilc']['mean'] < tracking['simulated']['mean']


def test_the_table_shows_the_reports_numbers(tiny):
    report, _ = tiny
    table = sim_to_real.format_table(report)
    r = report['tasks']['payload_transport']
    row = next(line for line in table.splitlines() if line.startswith('| payload_transport')
               and '%' in line)
    cells = [c.strip() for c in row.strip('|').split('|')]
    assert cells[1:4] == [str(r['sessions'][n]['rollouts'])
                          for n in ('scratch', 'residual', 'samples')]
    assert f"{r['tracking']['pd_only']['mean']:.4f}" in table


@pytest.mark.parametrize('change, words', [
    ({'model_error': ''}, 'needs a model error'),
    ({'continuations': ['forget']}, 'continuations'),
    ({'num_tasks': 0}, 'num_tasks'),
])
def test_bad_settings_are_refused(change, words):
    with pytest.raises(ValueError, match=words):
        sim_to_real.run(**{'tasks': ['reach_over_obstacle'], **change})
