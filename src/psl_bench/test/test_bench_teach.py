"""psl bench teach: the taught skill holds the demonstrations it was given (their instances
solved by the demonstrator), and each row is its session's own metrics file."""
import json

import numpy as np

from psl_bench import teach
from psl_memory.skill_memory import SkillMemory


def test_a_taught_session_starts_from_its_demonstrations(tmp_path):
    report = teach.run(tasks=['reach_over_obstacle'], counts=[0, 3], seeds=[0], num_tasks=21,
                       num_test=3, budget=60, out=tmp_path)
    rows = {r['count']: r for r in report['rows']}
    assert set(rows) == {0, 3}
    folder = tmp_path / 'reach_over_obstacle-seed0'
    taught = SkillMemory.read(folder / 'taught3' / 'taught.npz').get('reach_over_obstacle')
    demonstrator = json.loads((folder / 'demonstrator' / 'metrics.json').read_text())
    solved = [t['tau'] for t in demonstrator['tasks'] if t['fulfilled']]
    assert taught.num_samples == 3
    np.testing.assert_array_equal(taught.taus, np.array(solved[:3]))
    for count, row in rows.items():
        metrics = json.loads((folder / f'taught{count}' / 'session' / 'metrics.json')
                             .read_text())
        assert row['total_rollouts'] == sum(t['rollouts'] for t in metrics['tasks'])
        assert row['zero_shot_success'] == metrics['summary']['zero_shot_success_rate']
    assert '| reach_over_obstacle | 3 |' in teach.format_table(report)


def test_its_sessions_as_ray_tasks_give_the_same_rows(tmp_path, ray_cluster):
    settings = dict(tasks=['reach_over_obstacle'], counts=[0, 2], seeds=[0, 1], num_tasks=21,
                    num_test=3, budget=40)
    serial = teach.run(**settings, out=tmp_path / 'serial')
    on_ray = teach.run(**settings, out=tmp_path / 'ray', runner='ray')
    assert serial['runner'] == 'serial' and on_ray['runner'].startswith('ray')
    assert on_ray['missing'] == [] and on_ray['rows'] == serial['rows']
