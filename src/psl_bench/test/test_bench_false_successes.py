"""``psl bench false-successes`` on a tiny configuration: the counts add up, the table shows
them; bad settings are refused."""
import pytest

from psl_bench import false_successes


TINY = dict(tasks=['reach_over_obstacle'], noise=['position=0.00022,velocity=0.02'],
            confirms=[(1, 1), (2, 3)], num_tasks=3, num_test=2, budget=20, reruns=3)


@pytest.fixture(scope='module')
def tiny(tmp_path_factory):
    return false_successes.run(**TINY, out=tmp_path_factory.mktemp('false'))


def test_its_sessions_as_ray_tasks_give_the_same_rows(tiny, tmp_path, ray_cluster):
    on_ray = false_successes.run(**TINY, out=tmp_path, runner='ray')
    assert on_ray['runner'].startswith('ray') and tiny['runner'] == 'serial'
    assert on_ray['missing'] == [] and on_ray['rows'] == tiny['rows']


def test_the_counts_add_up(tiny):
    off, confirmed = tiny['rows']
    assert off['confirm'] == [1, 1] and off['confirm_rollouts'] == 0 and off['unconfirmed'] == 0
    assert off['added'] == off['fulfilled_tasks']
    assert confirmed['confirm_rollouts'] == 2 * confirmed['fulfilled_tasks']
    assert confirmed['added'] == confirmed['fulfilled_tasks'] - confirmed['unconfirmed']
    for row in tiny['rows']:
        assert 0 <= row['false_successes'] <= row['added']
        assert 0 <= row['fails_noise_free'] <= row['added']


def test_the_table_shows_the_reports_numbers(tiny):
    lines = [line for line in false_successes.format_table(tiny).splitlines()
             if line.startswith('| reach_over_obstacle')]
    assert len(lines) == 2
    for line, row in zip(lines, tiny['rows']):
        cells = [c.strip() for c in line.strip('|').split('|')]
        assert cells[3:10] == [str(row[k]) for k in (
            'rollouts', 'confirm_rollouts', 'fulfilled_tasks', 'unconfirmed', 'added',
            'false_successes', 'fails_noise_free')]


@pytest.mark.parametrize('change, words', [
    ({'noise': ['']}, 'no noise'), ({'confirms': [(2, 1)]}, 'k <= n'),
    ({'reruns': 0}, 'reruns')])
def test_bad_settings_are_refused(change, words):
    with pytest.raises(ValueError, match=words):
        false_successes.run(**{'tasks': ['reach_over_obstacle'], **change})


def test_confirm_text():
    assert false_successes.parse_confirm('2/3') == (2, 3)
    for text in ('3/2', '2', 'a/b', '0/1'):
        with pytest.raises(ValueError, match='k/n'):
            false_successes.parse_confirm(text)
