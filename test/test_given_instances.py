"""Task instances from the environment: psl learn --task-selection given takes each training
instance from a topic (std_msgs/Float64MultiArray, data = tau), in the order they come; a bad
one is skipped with a warning and the session learns on the rest."""
import json
import os
import signal
import subprocess
import sys

import numpy as np

from psl_ros.client import RosClient
from psl_task.task import load_task

PSL = [sys.executable, '-m', 'psl_cli.main']
TOPIC = '/given_instances'


def test_a_session_learns_on_the_instances_published_to_it(tmp_path, wait_until):
    from std_msgs.msg import Float64MultiArray
    from psl_ros.qos import RELIABLE

    task = load_task('reach_over_obstacle')
    given = [task.tau_low + 0.25 * (task.tau_high - task.tau_low),
             task.tau_low + 0.75 * (task.tau_high - task.tau_low)]
    out = tmp_path / 'session'
    learn = subprocess.Popen(PSL + ['learn', '--tasks', '2', '--budget', '10', '--test-tasks',
                                    '1', '--task-selection', 'given', '--tau-topic', TOPIC,
                                    '--tau-timeout', '60', '-o', str(out)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True)
    try:
        with RosClient() as client:
            publisher = client.node.create_publisher(Float64MultiArray, TOPIC, RELIABLE)
            assert wait_until(lambda: publisher.get_subscription_count() >= 1, 60.0), \
                'psl learn never subscribed'
            for tau in ([np.nan, 0.1], given[0], [1.0, 2.0, 3.0], given[1]):
                publisher.publish(Float64MultiArray(data=[float(x) for x in tau]))
            stdout, stderr = learn.communicate(timeout=300)
    finally:
        if learn.poll() is None:
            os.killpg(learn.pid, signal.SIGKILL)
            learn.wait(timeout=10)
    assert learn.returncode == 0, stderr
    tasks = json.loads((out / 'metrics.json').read_text())['tasks']
    np.testing.assert_array_equal([t['tau'] for t in tasks], given)
    # the two bad ones skipped, each said with its reason
    skipped = [line for line in stderr.splitlines() if f'on {TOPIC} skipped' in line]
    assert len(skipped) == 2, stderr
    assert 'nan' in skipped[0] and '[1.0, 2.0, 3.0]' in skipped[1], skipped


def test_a_topic_that_is_no_topic_name_is_refused_with_the_reason(tmp_path):
    bad = 'a b' + 'x' * 100_000
    done = subprocess.run(PSL + ['learn', '--tasks', '1', '--task-selection', 'given',
                                 '--tau-topic', bad, '-o', str(tmp_path / 'out')],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and 'Invalid topic name' in done.stderr
    assert 'Traceback' not in done.stderr and len(done.stderr) < 1000
