"""psl_bench.recording without a graph: what the loop publishes, the busy processes, the table."""
import os

import pytest

from psl_bench.busy_cores import busy_cores
from psl_bench.recording import format_report, loop_messages
from psl_ros.graph import pid_alive


def test_loop_messages_one_per_state_or_per_rollout():
    counts = loop_messages(1000, 3, ['joint_states', 'effort_command', '/clock',
                                     'rollout_evaluation', 'scene'])
    assert counts == {'/joint_states': 3003, '/effort_command': 3003, '/clock': 3003,
                      '/rollout_evaluation': 3, '/scene': None}


def test_busy_cores_spin_while_inside_and_are_ended_by_pid():
    with busy_cores(2) as pids:
        assert len(set(pids)) == 2 and os.getpid() not in pids
        assert all(pid_alive(pid) for pid in pids)
    assert not any(pid_alive(pid) for pid in pids)


@pytest.mark.parametrize('missing', [0, 5])
def test_format_report_names_every_topic_and_what_is_missing(missing):
    topics = {'/joint_states': {'published': 2002, 'in_bag': 2002 - missing,
                                'lost_counted': missing, 'missing': missing},
              '/scene': {'published': None, 'in_bag': 61, 'lost_counted': 0, 'missing': None}}
    report = {'task': 'reach', 'rollouts': 2, 'rounds': 1, 'steps_per_episode': 1000,
              'busy_cores': 1, 'machine_cores': 2, 'with_over_without': 0.5, 'topics': topics,
              'missing': missing, 'lost_counted': missing,
              'without_recorder': {'steps_per_second_median': 1800.0,
                                   'steps_per_second_min': 1700.0},
              'with_recorder': {'steps_per_second_median': 900.0,
                                'steps_per_second_min': 800.0}}
    table = format_report(report)
    assert '1800 steps/s' in table and '900 steps/s' in table and 'rounds 0.50' in table
    assert '/joint_states' in table and '/scene' in table
    assert ('every message is in the bag' in table) == (missing == 0)
    assert (f'{missing} messages missing, {missing} counted lost' in table) == (missing > 0)
