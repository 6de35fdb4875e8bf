"""psl against a robot it does not simulate (test/minimal_robot.py, written here, not psl's
simulator): the robot only publishes JointState on /joint_states (its own joint order, an extra
joint, wall-clock stamps, noise) and takes Float64MultiArray torques on
/effort_controller/commands; its masses are not the model's and its commands act a period
late. psl runs every episode itself (homing from the measured posture, the primitive, the wall
clock) and nothing of psl's is served or called on the robot."""
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from psl_ros.client import RosClient
from psl_ros.graph import STATE_TIMEOUT, Graph, pid_alive
from psl_task.arm_model import joint_names_of
from psl_task.task import load_task

pytestmark = pytest.mark.robot_on_the_wall_clock

TASK = 'reach_over_obstacle'
NAMESPACE = '/external'
ROBOT_TOPICS = {'joint_states': '/joint_states', 'effort_command': '/effort_controller/commands'}
SILENCE = 3.0           # s the robot's states stop for (SIGUSR1)
MAX_SPEED = 20.0        # rad/s: a jump faster than this between two states is a teleport
# the controller's gains on this robot: a third of the task's. A Python robot, controller and
# evaluator on a loaded 2-core machine answer a state several periods late at times, and
# the task's gains, tuned for lockstep, then make the arm oscillate (seen: a joint wound to
# -27 rad); as on hardware, gains are set for the robot's latency (pd_controller kp, kd)
GAINS = {'kp': '[100.0,66.0,33.0]', 'kd': '[6.0,4.0,1.6]'}


def robot_order(task) -> list[str]:
    return list(reversed(joint_names_of(task)))        # not the task's order


@pytest.fixture(scope='module')
def robot(tmp_path_factory):
    """The robot process, started at a posture away from the task's start; ended by its
    process group."""
    task = load_task(TASK)
    order = robot_order(task)
    names = joint_names_of(task)
    start = [task.start_posture[names.index(j)] + 0.3 for j in order]
    log = open(tmp_path_factory.mktemp('robot') / 'robot.log', 'wb')
    process = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name('minimal_robot.py')), '--model',
         str(task.model_path), '--joints', *order, '--start', *map(str, start),
         '--silence', str(SILENCE)], stdout=log, stderr=subprocess.STDOUT,
        start_new_session=True)
    try:
        yield process
    finally:
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        process.wait(timeout=10)
        log.close()


@pytest.fixture(scope='module')
def graph(robot, tmp_path_factory):
    task = load_task(TASK)
    g = Graph(task=TASK, namespace=NAMESPACE, robot='external', robot_topics=ROBOT_TOPICS,
              log_dir=tmp_path_factory.mktemp('external_logs'),
              extra_params={'pd_controller': {'command_joints':
                                              '[' + ','.join(robot_order(task)) + ']', **GAINS},
                            'learner': {'test_tasks': 1,
                                        'output_root': str(tmp_path_factory.mktemp('runs'))}})
    try:
        g.start()
        g.wait_ready(timeout=60)
        yield g
    finally:
        g.stop()
        left = [p.name for p in g.processes if pid_alive(p.pid)]
        assert not left, f'processes left behind: {left}'


@pytest.fixture(scope='module')
def client(graph):
    with RosClient(NAMESPACE) as c:
        yield c


class Recorder:
    """The robot's joint states and the controller's commands, as the test process sees
    them (stamp or arrival time, values)."""

    def __init__(self, node):
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray
        from psl_ros.qos import WHOLE_EPISODE
        self.lock = threading.Lock()
        self.states, self.commands = [], []
        self.subs = [
            node.create_subscription(JointState, '/joint_states', self.on_state, WHOLE_EPISODE),
            node.create_subscription(Float64MultiArray, '/effort_controller/commands',
                                     self.on_command, WHOLE_EPISODE)]

    def on_state(self, msg):
        with self.lock:
            self.states.append((msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9,
                                time.monotonic(), list(msg.name), np.array(msg.position)))

    def on_command(self, msg):
        with self.lock:
            self.commands.append((time.time(), np.array(msg.data)))    # the robot's clock


def test_the_robot_offers_no_service_and_its_own_joint_order(client, robot, wait_until):
    recorder = Recorder(client.node)
    assert wait_until(lambda: len(recorder.states) > 10, 30.0)
    assert wait_until(
        lambda: ('minimal_robot', '/') in client.node.get_node_names_and_namespaces(), 30.0)
    assert client.node.get_service_names_and_types_by_node('minimal_robot', '/') == []
    assert recorder.states[-1][2] == robot_order(load_task(TASK)) + ['gripper_finger']


def test_a_graph_mode_session_on_the_robot(client, tmp_path):
    """A learning session in graph mode completes on the robot; its joint states are
    continuous across the episodes (psl homes the arm, never teleports it)."""
    recorder = Recorder(client.node)
    result = client.learn(timeout=600, task=TASK, strategy='bootstrap', num_tasks=2,
                          max_rollouts_per_task=4, seed=1, mode='graph',
                          output_dir=str(tmp_path / 'session'))
    assert result.success, result.message
    metrics = json.loads(open(result.metrics_path).read())
    rollouts = metrics['summary']['total_rollouts']
    assert rollouts >= 2
    with recorder.lock:
        stamps = np.array([s[0] for s in recorder.states])
        q = np.array([s[3] for s in recorder.states])
    # every rollout is at least a homing and an episode of the task's length
    task = load_task(TASK)
    assert stamps[-1] - stamps[0] > rollouts * task.duration
    # a jump: more than MAX_SPEED allows between two states, beyond ten times the noise
    jumps = np.abs(np.diff(q, axis=0)) - MAX_SPEED * np.diff(stamps)[:, None]
    assert jumps.max() < 0.01, f'a jump of {jumps.max():.3f} rad between two states'


def test_states_that_stop_mid_episode_fail_the_rollout_and_the_controller_stops(client, robot,
                                                                              wait_until):
    """The robot's joint states stop mid-episode: the controller commands zero torque
    within its state_timeout and a period or two, the rollout fails with the reason, and the
    next rollout (states back) succeeds."""
    from psl_msgs.msg import TaskInstance
    from psl_ros.qos import LATCHED
    task = load_task(TASK)
    episodes = []
    now = time.time()       # the latched announcement of an earlier episode does not count
    client.node.create_subscription(
        TaskInstance, NAMESPACE + '/task_instance',
        lambda m: episodes.append(m) if m.stamp.sec + m.stamp.nanosec * 1e-9 > now else None,
        LATCHED)
    recorder = Recorder(client.node)
    theta = _default_theta(task)
    tau = (task.tau_low + task.tau_high) / 2
    outcome = []
    rolling = threading.Thread(target=lambda: outcome.append(
        client.rollout(TASK, tau, theta, timeout=120)))
    rolling.start()
    try:
        # the primitive's episode is announced (LEAD s before its start): silence from now
        assert wait_until(lambda: outcome or any(not e.homing for e in episodes), 60)
        assert not outcome, outcome[0].message
        os.kill(robot.pid, signal.SIGUSR1)
        silenced = time.monotonic()
    finally:
        rolling.join(timeout=120)
    assert outcome, 'the rollout did not end'
    result = outcome[0]
    assert not result.success and 'joint states stopped' in result.message, result.message
    with recorder.lock:
        # the robot's stamp of its last state before the silence (its clock: the system's)
        last_state = max(s[0] for s in recorder.states if s[1] < silenced + SILENCE / 2)
        zero = [t for t, u in recorder.commands if t > last_state and not np.any(u)]
        late = [t for t, u in recorder.commands if t > last_state and np.any(u)
                and t < last_state + SILENCE / 2]
    assert zero, 'the controller never commanded zero torque'
    stopped_after = zero[0] - last_state
    # the watchdog: state_timeout and a timer period, plus the way to this process (up to
    # 0.2 s on a loaded machine)
    assert stopped_after < STATE_TIMEOUT + 0.2, f'zero torque only {stopped_after:.3f} s after'
    assert all(t < zero[0] for t in late), 'it commanded torque after it had stopped'
    # the states come back: the session can go on
    assert wait_until(lambda: recorder.states[-1][1] > silenced + SILENCE, SILENCE + 10)
    again = client.rollout(TASK, tau, theta, timeout=120)
    assert again.success, again.message


def _default_theta(task):
    from psl_controller.policy import policy_for
    return policy_for(task).default_theta

