"""The robot loop end to end: sim, controller, executor and evaluator as separate processes."""
import threading
import time

import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray

from psl_ros.bag_recorder import make_typestore, read_bag_summary, record
from psl_controller.policy import policy_for
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
DELIVERY_TIMEOUT = 10.0  # s, for messages already published to reach the recorder
GOAL_TOLERANCE = 0.005   # m, end-effector distance to the goal after the demonstration


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


@pytest.fixture(scope='module')
def theta(task):
    return policy_for(task).default_theta


@pytest.fixture(scope='module')
def reference_result(client, task, theta):
    """The demonstration's rollout at the default task instance (compared against below)."""
    result = client.rollout(TASK, task.tau_default, theta)
    assert result.success, result.message
    return result.evaluation


def components(evaluation) -> dict:
    return dict(zip(evaluation.component_names, evaluation.component_values))


def test_demonstration_rollout_ends_at_goal(reference_result, task):
    ev = reference_result
    assert ev.task == TASK
    assert list(ev.tau) == task.tau_default.tolist()
    assert ev.num_steps == task.num_steps
    assert components(ev)['goal_error'] < GOAL_TOLERANCE
    assert components(ev)['penetration'] == 0.0
    assert ev.fulfilled and ev.reward >= task.reward.success_threshold


def test_lockstep_rollouts_are_identical(client, task, theta, reference_result):
    other = client.rollout(TASK, task.tau_high, theta)     # a different instance in between
    assert other.success, other.message
    assert list(other.evaluation.component_values) != list(reference_result.component_values)
    again = client.rollout(TASK, task.tau_default, theta)
    assert again.success, again.message
    assert again.evaluation.reward == reference_result.reward
    assert list(again.evaluation.component_values) == list(reference_result.component_values)


@pytest.mark.parametrize('task_name, tau, theta_change, words', [
    ('no_such_task', None, None, ['unknown task', 'no_such_task', TASK]),
    (TASK, [0.7], None, ['2 task parameters', 'got 1']),
    (TASK, [0.7, 10.0], None, ['obstacle_height', 'outside its range']),
    (TASK, [float('nan'), 0.2], None, ['finite']),
    (TASK, None, 'short', ['theta', 'entries', 'got 3']),
    (TASK, None, 'nan', ['NaN']),
    (TASK, None, 'huge', ['theta[0]', 'a units or scaling error']),
])
def test_bad_rollout_requests_get_clear_errors(client, task, theta, reference_result,
                                               task_name, tau, theta_change, words):
    bad_theta = theta.copy()
    if theta_change == 'short':
        bad_theta = theta[:3]
    elif theta_change == 'nan':
        bad_theta[5] = np.nan
    elif theta_change == 'huge':
        bad_theta[:] = 1e308
    result = client.rollout(task_name, task.tau_default if tau is None else tau, bad_theta)
    assert not result.success
    for word in words:
        assert word in result.message, result.message
    # the graph goes on serving, and nothing of the bad request stayed behind
    good = client.rollout(TASK, task.tau_default, theta)
    assert good.success, good.message
    assert list(good.evaluation.component_values) == list(reference_result.component_values)


def test_reset_refuses_bad_task_instances(client, task):
    response = client.reset(TASK, [0.7, 0.2, 0.1])
    assert not response.success and 'got 3' in response.message
    response = client.reset('nope', [0.7, 0.2])
    assert not response.success and 'unknown task' in response.message


def test_bad_effort_commands_never_reach_the_physics(client, graph, task, theta,
                                                     reference_result, wait_until):
    """Wrong-sized and NaN commands, published from the episode's start on, are refused: the
    rollout is bit-identical to one without them, and the simulator says why. (A publisher
    besides the controller that exists at a reset stops the episode from starting at all:
    test_bad_requests.py.)"""
    node = client.node
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    stop, running = threading.Event(), threading.Event()
    sim_log = next(p for p in graph.processes if p.name == 'sim').log_path

    def spam():
        running.wait(60)
        pub = node.create_publisher(Float64MultiArray, 'effort_command', qos)
        try:
            bad = [Float64MultiArray(data=[1.0, 2.0]),
                   Float64MultiArray(data=[np.nan, 0.0, 0.0])]
            i = 0
            while not stop.is_set():
                pub.publish(bad[i % 2])
                i += 1
                time.sleep(0.002)
        finally:
            node.destroy_publisher(pub)

    thread = threading.Thread(target=spam, daemon=True)
    thread.start()
    try:
        # the episode has started once the executor reports progress
        result = client.rollout(TASK, task.tau_default, theta,
                                feedback=lambda _: running.set())
        # the simulator saw the bad commands (while the episode ran, or after it)
        assert wait_until(lambda: 'refused effort_command: expected 3 finite torques'
                          in sim_log.read_text(), 30.0)
    finally:
        running.set()
        stop.set()
        thread.join(timeout=30)
    assert not thread.is_alive(), 'the spamming publisher did not stop'
    assert result.success, result.message
    assert list(result.evaluation.component_values) == list(reference_result.component_values)
    # once the publisher has gone, episodes start again
    assert wait_until(lambda: client.rollout(TASK, task.tau_default, theta).success, 30.0)


def count_messages(node, topics, counts):
    """Subscriptions on `node` that count each topic's messages into `counts` (QoS like the
    recorder's: reliable, the latched task_instance transient-local); returns them."""
    from psl_msgs.msg import RolloutEvaluation, TaskInstance
    from rclpy.qos import DurabilityPolicy
    from sensor_msgs.msg import JointState

    types = {'/joint_states': JointState, '/effort_command': Float64MultiArray,
             '/task_instance': TaskInstance, '/rollout_evaluation': RolloutEvaluation}
    subscriptions = []
    for topic in topics:
        counts[topic] = 0
        qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE,
                         durability=(DurabilityPolicy.TRANSIENT_LOCAL if topic == '/task_instance'
                                     else DurabilityPolicy.VOLATILE))

        def count(_, topic=topic):
            counts[topic] += 1
        subscriptions.append(node.create_subscription(types[topic], topic, count, qos,
                                                      raw=True))
    return subscriptions


def test_recorded_bag_reads_back(client, task, theta, tmp_path, reference_result, wait_until):
    bag = tmp_path / 'rollout_bag'
    topics = ['joint_states', 'effort_command', 'task_instance', 'rollout_evaluation']
    n = task.num_steps + 1       # states 0..N, each answered by one command
    # task_instance is latched: the recorder also receives the previous episode's announcement
    expected = {'/joint_states': n, '/effort_command': n, '/task_instance': 2,
                '/rollout_evaluation': 1}
    stop = threading.Event()
    recordings, so_far = [], {}
    recorder = threading.Thread(target=lambda: recordings.append(
        record(bag, topics, stop=stop, discovery_timeout=1.0,
               progress=lambda recording: so_far.update(recording.counts))))
    # a second listener beside the recorder: what has reached this machine's subscribers
    delivered = {}
    probes = count_messages(client.node, expected, delivered)
    recorder.start()
    try:
        client.wait_for_subscribers(topics, extra=2,           # the recorder and the probes
                                    subscriptions=probes)
        # the latched announcement of the episode before has reached both (matched is not
        # delivered: on a busy machine the next announcement would replace it in the
        # publisher's history of one before it arrived)
        assert wait_until(lambda: delivered.get('/task_instance') == 1
                          and so_far.get('/task_instance') == 1, DELIVERY_TIMEOUT), \
            (delivered, so_far)
        result = client.rollout(TASK, task.tau_default, theta)
        # the rollout is over, its last messages may still be on their way (a reliable
        # reader that missed a sample gets it on the writer's next heartbeat): stop the
        # recorder once they have reached the probes and the recorder
        wait_until(lambda: delivered == expected and so_far == expected, DELIVERY_TIMEOUT)
    finally:
        stop.set()
        recorder.join(timeout=30)
        for probe in probes:
            client.node.destroy_subscription(probe)
    assert result.success, result.message
    assert delivered == expected
    assert recordings, 'record() raised (see the thread exception above)'
    counts = recordings[0].counts
    summary = read_bag_summary(bag)
    assert {topic: count for topic, (_, count) in summary.items()} == expected
    assert counts == expected
    assert summary['/joint_states'][0] == 'sensor_msgs/msg/JointState'
    assert summary['/rollout_evaluation'][0] == 'psl_msgs/msg/RolloutEvaluation'
    # the evaluation in the bag is the one the action returned
    from rosbags.rosbag2 import Reader
    store = make_typestore()
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == '/rollout_evaluation']
        (_, _, raw), = list(reader.messages(connections=conns))
        stored = store.deserialize_cdr(raw, conns[0].msgtype)
    assert stored.reward == result.evaluation.reward
    assert (bag / 'metadata.yaml').read_text().count('storage_identifier: mcap') == 1


def test_graph_and_batch_mode_agree(graph_matches_batch, task, theta):
    """The same policy and task instance in graph mode (separate processes, lockstep) and in
    batch mode (mujoco.rollout, PD inside the model): same joint trajectory and reward."""
    rng = np.random.default_rng(7)
    perturbed = theta + rng.normal(0.0, 0.1 * np.abs(theta).max(), theta.size)
    graph_matches_batch(task, task.sample_tau(rng), perturbed)


def test_a_gmr_encoded_task_runs_in_the_graph_as_in_batch_mode(graph_matches_batch, tmp_path):
    """policy.kind: gmr in a task YAML (theta_K = GMR means and slopes, eq. 2.25): the
    executor's reference and batch mode's are the same, so the rollouts agree."""
    import yaml

    task = load_task('reach_over_obstacle')
    data = yaml.safe_load(task.path.read_text())
    data.update(name='reach_over_obstacle_gmr', model=str(task.model_path))
    data['policy'] = dict(data['policy'], kind='gmr', n_components=6)
    path = tmp_path / 'reach_over_obstacle_gmr.yaml'
    path.write_text(yaml.safe_dump(data))
    mine = load_task(str(path))
    theta = policy_for(mine).default_theta
    assert theta.size == 2 * 6 * mine.n_joints
    rng = np.random.default_rng(4)
    evaluation, _ = graph_matches_batch(mine, mine.tau_default,
                                        theta + rng.normal(0.0, 0.02, theta.size))
    assert evaluation.task == str(path.resolve())


def test_both_modes_follow_a_changed_law(client, graph_matches_batch, task, theta):
    """Other gains and torque limits set on the running controller (its ROS parameters), and
    the same law given to batch mode: the rollouts agree, and differ from the task's law."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    from psl_controller.pd_law import PDLaw, law_for

    default = law_for(task)
    limit = 0.5 * np.maximum(-default.torque_low, default.torque_high)
    changed = PDLaw(0.5 * default.kp, 2.0 * default.kd, -limit, limit)
    service = client.node.create_client(SetParameters, 'pd_controller/set_parameters')

    def set_law(kp, kd, torque_limit):
        values = {'kp': kp, 'kd': kd, 'torque_limit': torque_limit}
        request = SetParameters.Request(parameters=[Parameter(name=name, value=ParameterValue(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY, double_array_value=list(map(float, v))))
            for name, v in values.items()])
        assert service.wait_for_service(timeout_sec=10)
        response = client.wait(service.call_async(request), 10, 'set_parameters')
        assert all(r.successful for r in response.results), response.results

    strong = theta * 1.3                       # a motion that loads the torque limits
    try:
        set_law(changed.kp, changed.kd, limit)
        graph_changed, batch_changed = graph_matches_batch(task, task.tau_default, strong,
                                                           law=changed)
    finally:
        set_law([0.0], [0.0], [0.0])           # back to the task's law for the other tests
        client.node.destroy_client(service)
    default_batch = graph_matches_batch(task, task.tau_default, strong)[1]
    assert np.abs(batch_changed.q - default_batch.q).max() > 1e-3
    assert np.abs(batch_changed.torque).max() <= limit.max() + 1e-12


def test_the_simulator_reports_where_a_step_goes(client, task, theta, wait_until):
    """With each episode's end the simulator reports the medians of its step phases; the
    command's way from the controller is part of the wait for it, and the phases together fit
    in a step of the episode's own rate."""
    from diagnostic_msgs.msg import DiagnosticArray
    from psl_ros import names
    from psl_ros.qos import RELIABLE
    reports = []

    def on_diagnostics(msg):
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if values.get('steps_done') == values.get('steps') and 'step_wait_us' in values:
                reports.append(values)
    sub = client.node.create_subscription(DiagnosticArray, names.DIAGNOSTICS, on_diagnostics,
                                          RELIABLE)
    try:
        client.wait_for_subscribers([names.DIAGNOSTICS], subscriptions=[sub])
        assert client.rollout(TASK, task.tau_default, theta).success
        assert wait_until(lambda: reports, 10.0)
    finally:
        client.node.destroy_subscription(sub)
    report = reports[-1]
    us = {k[len('step_'):-len('_us')]: float(v) for k, v in report.items()
          if k.startswith('step_')}
    assert set(us) == {'wait', 'command_transport', 'physics', 'state', 'extras'}
    assert all(v > 0 for v in us.values()), us
    assert us['command_transport'] <= us['wait']
    per_step_us = 1e6 / float(report['steps_per_second'])
    assert us['wait'] + us['physics'] + us['state'] <= 1.5 * per_step_us, (us, per_step_us)
