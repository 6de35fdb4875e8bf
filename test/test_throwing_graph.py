"""The throwing task in the graph: the ball's pose comes from a topic another process publishes
(psl's simulator, as a motion capture would: world/ball/pose), the evaluator scores where it
lands; without noise the reward equals batch mode's for the same rollout, with noise it
differs by what the noise can move the landing point, and a session learns on it."""
import json
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters

from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.landing import landing_points
from psl_ros.qos import WORLD_POSES
from psl_task.task import load_task

TASK = 'ball_throw'
NOISE = 0.003       # m, the motion capture's standard deviation on the ball's position


@pytest.fixture(scope='module')
def graph_task():
    return TASK


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


def set_noise(client, value: float) -> None:
    service = client.node.create_client(SetParameters, 'sim/set_parameters')
    try:
        assert service.wait_for_service(timeout_sec=10)
        request = SetParameters.Request(parameters=[Parameter(
            name='world_pose_noise', value=ParameterValue(
                type=ParameterType.PARAMETER_DOUBLE, double_value=float(value)))])
        response = client.wait(service.call_async(request), 10, 'set_parameters')
        assert all(r.successful for r in response.results), response.results
    finally:
        client.node.destroy_client(service)


def test_the_reward_of_a_throw_equals_batch_modes(task, graph_matches_batch):
    theta = policy_for(task).default_theta
    for tau in (task.tau_low, task.tau_high):
        evaluation, batch = graph_matches_batch(task, tau, theta)   # every component agrees
        landing = dict(zip(evaluation.component_names,
                           evaluation.component_values))['landing_error']
        assert landing == pytest.approx(batch.evaluation.components['landing_error'],
                                        rel=1e-9, abs=1e-12)
        assert 0.0 < landing < 1.5


def test_the_ball_is_published_as_the_batch_sensors_saw_it(task, client, wait_until):
    """The poses on world/ball/pose of one episode are batch mode's sensor readings of the
    ball, and the ball comes down where the evaluator says it lands."""
    theta = policy_for(task).default_theta
    poses = {}
    sub = client.node.create_subscription(
        PoseStamped, 'world/ball/pose',
        lambda m: poses.__setitem__(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m),
        WORLD_POSES)
    try:
        result = client.rollout(TASK, task.tau_default, theta)
        assert result.success, result.message
        stamp = result.evaluation.stamp
        t0 = stamp.sec * 10**9 + stamp.nanosec
        episode = [t0 + k * task.control_period_ns for k in range(task.num_steps + 1)]
        assert wait_until(lambda: all(t in poses for t in episode), 10.0), \
            f'{sum(t in poses for t in episode)} of {len(episode)} poses'
    finally:
        client.node.destroy_subscription(sub)
    graph = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z,
                       p.pose.orientation.w, p.pose.orientation.x, p.pose.orientation.y,
                       p.pose.orientation.z] for p in (poses[t] for t in episode)])
    batch = BatchRollouts(task).run(theta[None], task.tau_default)[0].world['ball']
    # the same physics; the arm's law adds in another order (1e-9 rad), the ball's contacts
    # carry that on
    assert np.abs(graph - batch).max() < 1e-6
    assert graph[0, 2] > 0.8 and graph[:, 2].max() > 1.2      # in the cup, then thrown
    # the evaluation carries the poses it scored: those published
    carried = np.asarray(result.evaluation.observed_poses).reshape(-1, 7)
    assert list(result.evaluation.observed_bodies) == ['ball']
    np.testing.assert_array_equal(carried, graph)
    point, landed = landing_points(graph[None], np.array([task.target.position[2]]))
    assert landed[0]
    target = task.target_of(task.tau_default)[0]
    components = dict(zip(result.evaluation.component_names,
                          result.evaluation.component_values))
    assert components['landing_error'] == pytest.approx(
        np.linalg.norm(point[0, :2] - target[:2]), abs=1e-6)


def test_a_noisy_motion_capture_moves_the_landing_point_by_its_noise(task, client):
    theta = policy_for(task).default_theta
    batch = BatchRollouts(task).run(theta[None], task.tau_default)[0].evaluation
    try:
        set_noise(client, NOISE)
        results = [client.rollout(TASK, task.tau_default, theta) for _ in range(3)]
    finally:
        set_noise(client, 0.0)
    landing = []
    for result in results:
        assert result.success, result.message
        components = dict(zip(result.evaluation.component_names,
                              result.evaluation.component_values))
        landing.append(components['landing_error'])
    differences = np.abs(np.array(landing) - batch.components['landing_error'])
    # the noise moves the measured crossing: by about the noise, never by a throw's length
    assert differences.max() > 0.0
    assert differences.max() < 10 * NOISE, differences


def test_a_session_learns_on_the_motion_captures_poses(task, client, tmp_path):
    """A graph-mode session scored on the noisy poses of the ball fulfils its task (seed 1:
    batch mode, without the noise, fulfils it after one generation of 12 rollouts)."""
    try:
        set_noise(client, NOISE)
        result = client.learn(timeout=900, task=TASK, strategy='bootstrap', num_tasks=1,
                              max_rollouts_per_task=40, seed=1, num_test=1, mode='graph',
                              output_dir=str(tmp_path / 'session'))
        assert result.success, result.message
        tasks = json.loads(Path(result.metrics_path).read_text())['tasks']
        assert len(tasks) == 1 and tasks[0]['failed'] == 0 and tasks[0]['fulfilled']
    finally:
        set_noise(client, 0.0)


def test_graph_rollouts_carry_the_balls_poses_as_batch_mode_does(task, client):
    """GraphRollouts (the learner's rollouts through the graph) give the ball's poses with
    the result (RolloutResult.world), as batch mode does."""
    from psl_optimizer.graph_rollout import trajectory_of

    theta = policy_for(task).default_theta
    result = client.rollout(TASK, task.tau_high, theta)
    assert result.success, result.message
    world = trajectory_of(result.evaluation)['world']
    batch = BatchRollouts(task).run(theta[None], task.tau_high)[0].world
    assert set(world) == set(batch) == {'ball'}
    assert world['ball'].shape == batch['ball'].shape == (task.num_steps + 1, 7)
    assert np.abs(world['ball'] - batch['ball']).max() < 1e-6


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def test_a_recording_has_the_balls_flight(task, client, tmp_path, wait_until):
    """psl record's recorder (psl_ros.bag_recorder.record) keeps every pose of the ball it was
    sent, live while the ball flies: the bag holds what a reader of the topic beside it got,
    message for message, each state of the episode among them, nothing lost.

    The simulator's poses are latched (`psl_ros.qos.WORLD_POSES`: its last 2000): a reader gets
    that history once the simulator's writer has matched it, which is some time after the
    reader exists on a busy machine, and with an episode running meanwhile the oldest poses
    leave the history before they are sent (seen with a core busy: the recorder's first pose
    0.05-2.5 s after its subscription; started during an episode, it held 200 and 848 poses
    fewer than a reader matched before, every pose of the episode in its bag, none lost that
    it was sent). So both readers are matched, and have the same history,
    before the episode: an episode first (the history then ends with its last pose, and
    nothing is published until the next), the readers, the whole history at both, then the
    episode recorded."""
    import threading

    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rosbags.rosbag2 import Reader

    from psl_ros.bag_recorder import make_typestore, read_bag_summary, record

    theta = policy_for(task).default_theta
    topic = '/world/ball/pose'
    before = client.rollout(TASK, task.tau_low, theta)
    assert before.success, before.message
    start = before.evaluation.stamp
    last = start.sec * 10**9 + start.nanosec + task.num_steps * task.control_period_ns
    bag, stop, recordings, so_far = tmp_path / 'throw_bag', threading.Event(), [], {}
    recorder = threading.Thread(target=lambda: recordings.append(record(
        bag, [topic], stop=stop, discovery_timeout=2.0,
        progress=lambda recording: so_far.update(recording.counts))))
    # this test's own reader beside it: latched as the recorder's, keeping all (as it does)
    mine = []
    own = client.node.create_subscription(
        PoseStamped, topic, lambda m: mine.append(stamp_ns(m)),
        QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL))
    recorder.start()
    try:
        # one writer, reliable: its poses arrive in order; with the last one published, a
        # reader holds the whole history, and the recorder holds as many
        assert wait_until(lambda: last in mine, 30.0), 'the history did not reach the reader'
        history = len(mine)
        assert wait_until(lambda: so_far.get(topic, 0) >= history, 30.0), \
            f'the recorder got {so_far.get(topic, 0)} of the {history} poses of the history'
        result = client.rollout(TASK, task.tau_default, theta)
        assert result.success, result.message
        t0 = result.evaluation.stamp.sec * 10**9 + result.evaluation.stamp.nanosec
        episode = {t0 + k * task.control_period_ns for k in range(task.num_steps + 1)}
        assert wait_until(lambda: episode <= set(mine), 30.0), 'the episode did not reach ' \
            'the reader'
        assert wait_until(lambda: so_far.get(topic, 0) >= len(mine), 30.0), \
            f'the recorder got {so_far.get(topic, 0)} of the {len(mine)} poses the reader got'
    finally:
        stop.set()
        recorder.join(timeout=30)
        client.node.destroy_subscription(own)
    assert recordings, 'record() raised'
    assert recordings[0].counts == {topic: len(mine)} and recordings[0].lost == {topic: 0}
    assert read_bag_summary(bag)[topic] == ('geometry_msgs/msg/PoseStamped', len(mine))
    store, stamps = make_typestore(), []
    with Reader(bag) as reader:
        for connection, _, data in reader.messages():
            stamps.append(stamp_ns(store.deserialize_cdr(data, connection.msgtype)))
    assert sorted(stamps) == sorted(mine)
    assert episode <= set(stamps), f'{len(episode - set(stamps))} states of the episode lost'
