"""psl bench learn: the report's numbers are the runs' metrics files, read back; the strategies
of a seed saw the same task instances; run folders are reused, never mixed."""
import json

import numpy as np
import pytest

from psl_bench import learn as bench_learn
from psl_optimizer.task_selection import held_out_tasks, task_sequence
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
STRATEGIES = ('scratch', 'bootstrap')
SEEDS = (0, 1)
TINY = dict(task_name=TASK, strategies=STRATEGIES, seeds=SEEDS, num_tasks=3, budget=25,
            num_test=3, after=1)


@pytest.fixture(scope='module')
def bench_run(tmp_path_factory):
    out = tmp_path_factory.mktemp('bench_learn')
    return out, bench_learn.run(out=out, **TINY)


def metrics_of(out, strategy, seed):
    folder = bench_learn.run_folder(out, TASK, strategy, seed, None)
    return json.loads((folder / 'metrics.json').read_text())


def test_every_run_keeps_its_metrics_file(bench_run):
    out, report = bench_run
    for seed in SEEDS:
        for strategy in STRATEGIES:
            metrics = metrics_of(out, strategy, seed)
            assert metrics['complete'] and metrics['strategy'] == strategy
            assert metrics['seed'] == seed and len(metrics['tasks']) == 3


def test_numbers_are_computed_from_the_metrics_files(bench_run):
    out, report = bench_run
    for strategy in STRATEGIES:
        totals, late, success, reward, seconds = [], [], [], [], []
        for seed in SEEDS:
            metrics = metrics_of(out, strategy, seed)
            rollouts = [t['rollouts'] for t in metrics['tasks']]
            totals.append(sum(rollouts))
            late.append(np.mean(rollouts[1:]))                  # after=1: tasks 2-3
            success.append(metrics['summary']['zero_shot_success_rate'])
            reward.append(metrics['summary']['zero_shot_mean_reward'])
            seconds.append(sum(t['seconds'] for t in metrics['tasks']))
            run = report['runs'][str(seed)][strategy]
            assert run['total_rollouts'] == sum(rollouts) == metrics['summary']['total_rollouts']
        row = report['strategies'][strategy]
        assert row['total_rollouts']['values'] == totals
        assert row['total_rollouts']['mean'] == pytest.approx(np.mean(totals))
        assert row['total_rollouts']['sd'] == pytest.approx(np.std(totals, ddof=1))
        assert row['late_rollouts']['mean'] == pytest.approx(np.mean(late))
        assert row['zero_shot_success']['mean'] == pytest.approx(np.mean(success))
        assert row['zero_shot_reward']['mean'] == pytest.approx(np.mean(reward))
        assert row['train_seconds']['mean'] == pytest.approx(np.mean(seconds))
    ratios = [report['runs'][str(s)]['scratch']['late_rollouts']
              / report['runs'][str(s)]['bootstrap']['late_rollouts'] for s in SEEDS]
    assert report['strategies']['bootstrap']['speedup']['values'] == pytest.approx(ratios)
    assert report['targets']['speedup']['bootstrap'] == pytest.approx(np.mean(ratios))
    table = bench_learn.format_table(report)
    mean, sd = (report['strategies']['bootstrap']['total_rollouts'][k] for k in ('mean', 'sd'))
    assert f'| bootstrap | {mean:.1f} ± {sd:.1f} |' in table


def test_strategies_of_a_seed_saw_the_same_instances(bench_run):
    out, _ = bench_run
    task = load_task(TASK)
    for seed in SEEDS:
        expected = task_sequence(task, 3, seed).tolist()
        expected_test = held_out_tasks(task, 3, seed).tolist()
        for strategy in STRATEGIES:
            metrics = metrics_of(out, strategy, seed)
            assert [t['tau'] for t in metrics['tasks']] == expected
            assert metrics['summary']['test_taus'] == expected_test
    assert task_sequence(task, 3, SEEDS[0]).tolist() != task_sequence(task, 3, SEEDS[1]).tolist()




@pytest.mark.parametrize('override', [dict(after=3), dict(strategies=('magic',)),
                                      dict(seeds=()), dict(readout='magic')])
def test_bad_settings(override, tmp_path):
    with pytest.raises(ValueError):
        bench_learn.run(out=tmp_path, **{**TINY, **override})


def test_baselines_in_the_skill_slot_get_their_own_folders_and_rows(bench_run):
    """--skill-maps elm,library: a row per (strategy, map); the elm run is the default's
    folder (reused), the library's is its own; every number from its metrics file."""
    out, _ = bench_run
    report = bench_learn.run(out=out, **{**TINY, 'strategies': ('scratch', 'bootstrap'),
                                         'skill_maps': ('elm', 'library')})
    names = ['scratch', 'scratch-library', 'bootstrap', 'bootstrap-library']
    assert sorted(report['strategies']) == sorted(names)
    assert report['rows']['bootstrap-library'] == {'strategy': 'bootstrap',
                                                   'skill_map': 'library'}
    for seed in SEEDS:
        runs = report['runs'][str(seed)]
        assert runs['bootstrap']['reused'] and not runs['bootstrap-library']['reused']
        folder = bench_learn.run_folder(out, TASK, 'bootstrap', seed, None, 'library')
        assert folder.name == f'{TASK}-bootstrap-library-seed{seed}'
        metrics = json.loads((folder / 'metrics.json').read_text())
        assert metrics['settings']['skill_map'] == 'library'
        assert runs['bootstrap-library']['skill_map'] == 'library'
        assert runs['bootstrap-library']['total_rollouts'] == sum(
            t['rollouts'] for t in metrics['tasks'])
        assert (runs['bootstrap-library']['zero_shot_success']
                == metrics['summary']['zero_shot_success_rate'])
        # scratch's searches never start from the skill: the same rollouts with either map
        assert (runs['scratch-library']['rollouts_per_task']
                == runs['scratch']['rollouts_per_task'])
    row = report['strategies']['bootstrap-library']
    assert row['total_rollouts']['values'] == [report['runs'][str(s)]['bootstrap-library'][
        'total_rollouts'] for s in SEEDS]
    assert 'speedup' in row                     # against scratch with the same map
    table = bench_learn.format_table(report)
    mean, sd = (row['total_rollouts'][k] for k in ('mean', 'sd'))
    assert f'| bootstrap | library | {mean:.1f} ± {sd:.1f} |' in table
    assert '| bootstrap | elm |' in table and '| skill map |' in table


def test_runs_from_before_the_skill_map_option_are_reused(bench_run, tmp_path):
    import shutil
    out, _ = bench_run
    old = tmp_path / 'old'
    shutil.copytree(out, old)
    for seed in SEEDS:
        path = bench_learn.run_folder(old, TASK, 'bootstrap', seed, None) / 'metrics.json'
        metrics = json.loads(path.read_text())
        del metrics['settings']['skill_map']
        path.write_text(json.dumps(metrics))
    report = bench_learn.run(out=old, **{**TINY, 'strategies': ('bootstrap',)})
    assert all(report['runs'][str(s)]['bootstrap']['reused'] for s in SEEDS)
    assert '| skill map |' not in bench_learn.format_table(report)     # the table as it was


@pytest.mark.parametrize('skill_maps', [(), ('magic',), ('elm', 'elm')])
def test_bad_skill_maps(skill_maps, tmp_path):
    with pytest.raises(ValueError, match='skill map'):
        bench_learn.run(out=tmp_path, **{**TINY, 'skill_maps': skill_maps})


def test_the_inverse_kinematics_share_is_reported_where_there_is_one(bench_run, tmp_path):
    """A joint-space task has no inverse kinematics (no share reported); an end-effector-space
    one reports its share of the session, within (0, 1), and its time per path, which times
    the number of paths solved cannot exceed the session."""
    _, joint = bench_run
    assert all('ik_share' not in row for row in joint['strategies'].values())
    report = bench_learn.run(out=tmp_path, **{**TINY, 'task_name': 'point_reach_3d',
                                              'strategies': ('bootstrap',), 'seeds': (0,)})
    row = report['strategies']['bootstrap']
    share, per_path = row['ik_share']['mean'], row['ik_ms_per_path']['mean']
    assert 0.0 < share < 1.0 and per_path > 0.0
    session = row['session_seconds']['mean']
    assert per_path * 1e-3 <= share * session * (1 + 1e-9)
    assert 'inverse kinematics' in bench_learn.format_table(report)
    # a task with a target: the hand's final miss on the held-out instances, the mean of
    # the run's own numbers
    folder = bench_learn.run_folder(tmp_path, 'point_reach_3d', 'bootstrap', 0, None)
    errors = json.loads((folder / 'metrics.json').read_text())['summary']['test_hand_errors']
    assert len(errors['goal_error']) == TINY['num_test']
    assert row['held_out_goal_error']['mean'] == pytest.approx(np.mean(errors['goal_error']))
    assert 'orientation_error' not in errors            # point_reach_3d does not score it
    assert 'held_out_orientation_error' not in row
    assert 0.0 < row['held_out_goal_error']['mean'] < 0.5
    assert "final miss on the held-out" in bench_learn.format_table(report)
    # of the one seed: the median and 90th percentile of its instances
    assert row['held_out_goal_error_median'] == pytest.approx(np.median(errors['goal_error']))
    assert row['held_out_goal_error_p90'] == pytest.approx(
        np.percentile(errors['goal_error'], 90))
    # a feed-forward: the session's held-out tracking RMSE, PD only / learned / oracle
    tracking = json.loads((folder / 'metrics.json').read_text())['summary']
    for name in bench_learn.TRACKING:
        assert row[f'tracking_{name}']['mean'] == tracking[f'tracking_rmse_{name}_mean']
    assert 'tracking RMSE' in bench_learn.format_table(report)
    # the consistency of the run's samples, read from its memory file (the measure itself:
    # test_sample_consistency_against_a_smooth_map_and_noise)
    from psl_memory.skill_memory import SkillMemory
    skill = SkillMemory.read(folder / 'memory.npz').get('point_reach_3d')
    from psl_controller.policy import policy_for
    policy = policy_for(load_task('point_reach_3d'))
    index = np.arange(skill.theta_dim)
    assert row['consistency_goal']['mean'] == bench_learn.sample_consistency(
        skill, {'goal': index[policy.goal]})['goal']


def test_sample_consistency_against_a_smooth_map_and_noise():
    """A skill whose samples lie on a smooth map of tau (quadratic): its leave-one-out error is
    a small share of their spread; samples of independent noise: about their whole spread
    (the others tell nothing about each); a block all samples share is left out."""
    from psl_memory.skill_memory import SkillMemory
    rng = np.random.default_rng(0)
    memory = SkillMemory()
    memory.create('s', np.zeros(2), np.ones(2), np.zeros(6))
    skill = memory.get('s')
    taus = rng.uniform(0.0, 1.0, (40, 2))
    smooth = np.c_[taus, taus ** 2] - 0.5                     # entries 0-3
    noise = rng.normal(0.0, 0.3, (40, 1))                     # entry 4
    for tau, a, b in zip(taus, smooth, noise):
        skill.add(tau, np.r_[a, b, 0.25])                     # entry 5: the same in all
    got = bench_learn.sample_consistency(skill, {'smooth': np.arange(4), 'noise': [4],
                                                 'shared': [5]})
    assert set(got) == {'smooth', 'noise'}
    assert got['smooth'] < 0.1
    assert got['noise'] > 0.9
