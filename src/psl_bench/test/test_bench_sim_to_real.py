"""``psl bench sim-to-real`` on a tiny configuration: every session of every robot seed runs on
the robot (its task: the task with the robot controller's gains), the table shows the report's
numbers; bad settings are refused."""
import pytest
import yaml

from psl_bench import sim_to_real
from psl_optimizer.metrics import read_metrics
from psl_task.task import load_task


TINY = dict(tasks=['payload_transport'], nominal_tasks=2, num_tasks=2, num_test=2, budget=20,
            ilc_iterations=2, seeds=[11, 12], robot_gains=0.5,
            measurement_noise='velocity=0.01')


@pytest.fixture(scope='module')
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp('s2r')
    return sim_to_real.run(**TINY, out=out), out


def test_its_sessions_as_ray_tasks_give_the_same_report(tiny, tmp_path, ray_cluster):
    """Each session has its own noisy robot: run in any order, on other processes, the same
    numbers (noise included)."""
    report, _ = tiny
    on_ray = sim_to_real.run(**TINY, out=tmp_path, runner='ray')
    assert on_ray['runner'].startswith('ray') and report['runner'] == 'serial'
    assert on_ray['missing'] == [] and on_ray['tasks'] == report['tasks']
    # one local cluster (a node) for both stages: the nominal session, then 4 per robot seed
    assert list(on_ray['nodes'].values()) == [1 + 2 * 4]


def test_a_session_alone_gives_its_row_of_the_sweep(tiny, tmp_path):
    """A robot seed's session run by itself, without the sessions before it in the sweep:
    the same row (its noise draws do not depend on what ran before)."""
    report, out = tiny
    nominal, robot, _ = sim_to_real._plans(
        'payload_transport', sim_to_real.REAL_ROBOT, 3, 2, [12], 2, 2, 20, 2, ['samples'],
        TINY['measurement_noise'], 0.5, tmp_path)
    sim_to_real.learn_session(**nominal.kwargs)
    alone = sim_to_real.learn_session(**robot[-1].kwargs)
    assert robot[-1].key == ('payload_transport', 12, 'samples')
    assert sim_to_real._row(alone) == report['tasks']['payload_transport']['runs']['12'][
        'sessions']['samples']


def test_the_sessions_run_on_the_robot_and_the_continued_ones_from_the_simulated_skill(tiny):
    report, out = tiny
    r = report['tasks']['payload_transport']
    assert set(r['runs']) == {'11', '12'}
    folder = out / 'payload_transport'
    nominal = read_metrics(folder / 'nominal')
    assert nominal.settings['model_error'] == nominal.settings['measurement_noise'] == ''
    for seed, run in r['runs'].items():
        assert set(run['sessions']) == {'scratch', 'residual', 'samples'}
        for name, way in (('scratch', ''), ('continued-residual', 'residual'),
                          ('continued-samples', 'samples')):
            metrics = read_metrics(folder / f'seed{seed}' / name)
            assert metrics.settings['model_error'] == sim_to_real.REAL_ROBOT
            assert metrics.settings['measurement_noise'] == 'velocity=0.01'
            assert metrics.settings['continuation'] == way
            assert metrics.seed == int(seed)
            assert len(metrics.tasks) == 2 and len(metrics.summary.test_taus) == 2
            assert metrics.settings['continue_from'] == ('' if name == 'scratch' else
                                                         str(folder / 'nominal' / 'memory.npz'))
            # on the robot's task: the task's YAML with half its controller gains
            robot = yaml.safe_load(metrics.task_yaml)
            task = yaml.safe_load(load_task('payload_transport').path.read_text())
            assert robot['controller'] == {key: [0.5 * v for v in task['controller'][key]]
                                           for key in ('kp', 'kd')}
            assert {k: v for k, v in robot.items() if k not in ('controller', 'model')} == {
                k: v for k, v in task.items() if k not in ('controller', 'model')}
        tracking = run['tracking']
        assert set(tracking) == set(sim_to_real.TRACKING)
        # the simulated feed-forward helps on the robot
        assert tracking['simulated']['mean'] < tracking['pd_only']['mean']


def test_the_table_shows_the_reports_numbers(tiny):
    report, _ = tiny
    table = sim_to_real.format_table(report)
    r = report['tasks']['payload_transport']
    ways = ('scratch', 'residual', 'samples')
    for seed, run in r['runs'].items():
        row = next(line for line in table.splitlines()
                   if line.startswith(f'| payload_transport | {seed} |'))
        cells = [c.strip() for c in row.strip('|').split('|')]
        assert cells[2:5] == [str(run['sessions'][n]['rollouts']) for n in ways]
    total = next(line for line in table.splitlines()
                 if line.startswith('| payload_transport | all 2 |'))
    cells = [c.strip() for c in total.strip('|').split('|')]
    assert cells[2:5] == [f"**{sum(run['sessions'][n]['rollouts'] for run in r['runs'].values())}**"
                          for n in ways]
    assert 'controller gains 0.5 times' in table


@pytest.mark.parametrize('change, words', [
    ({'model_error': ''}, 'needs a model error'),
    ({'continuations': ['forget']}, 'continuations'),
    ({'num_tasks': 0}, 'num_tasks'),
    ({'seeds': [1, 1]}, 'seed'),
    ({'robot_gains': 0.0}, 'robot_gains'),
    ({'measurement_noise': 'loud'}, 'KEY=VALUE'),
])
def test_bad_settings_are_refused(change, words):
    with pytest.raises(ValueError, match=words):
        sim_to_real.run(**{'tasks': ['reach_over_obstacle'], **change})
