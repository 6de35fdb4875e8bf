"""bag_recorder: record live topics into an MCAP rosbag2 bag and read it back with rosbags."""

import os
import threading
import time

import pytest
import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbags.rosbag2 import Reader
from ruamel.yaml import YAML
from psl_msgs.msg import TaskInstance
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from psl_ros.bag_recorder import make_typestore, read_bag_summary, record

N_EFFORT = 50
N_JOINT_STATES = 30
MATCH_TIMEOUT = 8.0  # [s] for the recorder to subscribe to a publisher
ACK_TIMEOUT = 5.0  # [s] for the recorder to acknowledge everything published
DISCOVERY_TIMEOUT = 0.5  # [s] given to record()
LATE_TOPIC_DELAY = 0.7  # [s] > DISCOVERY_TIMEOUT: effort_command appears this late


@pytest.fixture
def ros(monkeypatch):
    """rclpy initialised on a private domain (set before rclpy.init), shut down afterwards."""
    monkeypatch.setenv('ROS_DOMAIN_ID', str(100 + os.getpid() % 100))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    rclpy.init()
    try:
        yield
    finally:
        rclpy.try_shutdown()


def _wait_matched(publisher, timeout: float = MATCH_TIMEOUT) -> None:
    deadline = time.monotonic() + timeout
    while publisher.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            raise TimeoutError(f'no subscription on {publisher.topic_name}')
        time.sleep(0.01)


def _joint_state(i: int) -> JointState:
    msg = JointState()
    msg.header.stamp.sec = i
    msg.header.stamp.nanosec = 1000 * i
    msg.name = ['shoulder', 'elbow']
    msg.position = [0.01 * i, -0.02 * i]
    msg.velocity = [float(i), 2.0 * i]
    msg.effort = [0.5, -0.5]
    return msg


def _task_instance() -> TaskInstance:
    msg = TaskInstance()
    msg.stamp.sec = 7
    msg.stamp.nanosec = 8
    msg.task = 'reach'
    msg.tau = [0.3, -0.4]
    msg.num_steps = 500
    msg.control_period = 0.002
    return msg


def _publish(node: Node, stop: threading.Event, errors: list) -> None:
    """Publish once the recorder listens, then end the recording.

    The effort publisher appears only after the recorder's discovery timeout, so that
    subscribing to late topics is exercised.
    """
    try:
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        task_pub = node.create_publisher(TaskInstance, 'task_instance', latched)
        joint_pub = node.create_publisher(JointState, 'joint_states', 10)
        task_pub.publish(_task_instance())  # before anyone listens: latched
        _wait_matched(joint_pub)
        _wait_matched(task_pub)
        time.sleep(LATE_TOPIC_DELAY)
        effort_pub = node.create_publisher(Float64MultiArray, 'effort_command', 10)
        _wait_matched(effort_pub)
        for i in range(max(N_EFFORT, N_JOINT_STATES)):
            if i < N_JOINT_STATES:
                joint_pub.publish(_joint_state(i))
            if i < N_EFFORT:
                effort_pub.publish(Float64MultiArray(data=[float(i), -float(i)]))
            time.sleep(0.001)
        for publisher in (joint_pub, effort_pub, task_pub):
            if not publisher.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT)):
                raise TimeoutError(f'{publisher.topic_name} not acknowledged')
        time.sleep(0.3)  # let the recorder's executor take what was acknowledged
    except Exception as exc:  # reported by the test in the main thread
        errors.append(exc)
    finally:
        stop.set()


def test_record_named_topics(ros, tmp_path):
    publisher_node = Node('bag_test_publisher')
    stop = threading.Event()
    errors = []
    thread = threading.Thread(target=_publish, args=(publisher_node, stop, errors))
    bag = tmp_path / 'bag'
    try:
        thread.start()
        counts = record(bag, ['joint_states', 'effort_command', 'task_instance', 'never_there'],
                        stop=stop, duration=20.0, discovery_timeout=DISCOVERY_TIMEOUT)
        thread.join(timeout=10.0)
        type_hashes = {t: str(publisher_node.get_publishers_info_by_topic(t)[0].topic_type_hash)
                       for t in ('/joint_states', '/task_instance')}
    finally:
        stop.set()
        thread.join(timeout=10.0)
        publisher_node.destroy_node()
    assert not errors, errors

    assert counts == {'/joint_states': N_JOINT_STATES, '/effort_command': N_EFFORT,
                      '/task_instance': 1, '/never_there': 0}
    assert read_bag_summary(bag) == {
        '/joint_states': ('sensor_msgs/msg/JointState', N_JOINT_STATES),
        '/effort_command': ('std_msgs/msg/Float64MultiArray', N_EFFORT),
        '/task_instance': ('psl_msgs/msg/TaskInstance', 1),
    }

    metadata = YAML(typ='safe').load((bag / 'metadata.yaml').read_text())
    info = metadata['rosbag2_bagfile_information']
    assert info['storage_identifier'] == 'mcap'
    assert info['version'] == 9
    assert [p.suffix for p in bag.iterdir() if p.name != 'metadata.yaml'] == ['.mcap']
    topic_metadata = {t['topic_metadata']['name']: t['topic_metadata']
                      for t in info['topics_with_message_count']}
    task_qos = topic_metadata['/task_instance']['offered_qos_profiles']
    assert [(q['reliability'], q['durability']) for q in task_qos] == [
        ('reliable', 'transient_local')]
    assert task_qos[0]['deadline'] == {'sec': 9223372036, 'nsec': 854775807}  # infinite
    joint_qos = topic_metadata['/joint_states']['offered_qos_profiles']
    assert [q['durability'] for q in joint_qos] == ['volatile']
    for topic, type_hash in type_hashes.items():
        assert topic_metadata[topic]['type_description_hash'] == type_hash

    typestore = make_typestore()
    joint_states, efforts, tasks = [], [], []
    with Reader(bag) as reader:
        for connection in reader.connections:
            assert connection.msgdef.data  # schema stored for ros2 bag info / Foxglove
        stamps = []
        for connection, stamp, raw in reader.messages():
            msg = typestore.deserialize_cdr(raw, connection.msgtype)
            stamps.append(stamp)
            {'/joint_states': joint_states, '/effort_command': efforts,
             '/task_instance': tasks}[connection.topic].append(msg)
    assert abs(stamps[0] - time.time_ns()) < 60e9  # receive time on the wall clock

    assert [m.header.stamp.sec for m in joint_states] == list(range(N_JOINT_STATES))
    sample = joint_states[12]
    expected = _joint_state(12)
    assert sample.header.stamp.nanosec == expected.header.stamp.nanosec
    assert sample.name == ['shoulder', 'elbow']
    assert list(sample.position) == list(expected.position)
    assert list(sample.velocity) == list(expected.velocity)
    assert list(sample.effort) == list(expected.effort)
    assert [list(m.data) for m in efforts] == [[float(i), -float(i)] for i in range(N_EFFORT)]
    (task,) = tasks
    assert (task.stamp.sec, task.stamp.nanosec) == (7, 8)
    assert task.task == 'reach'
    assert list(task.tau) == [0.3, -0.4]
    assert (task.num_steps, task.control_period) == (500, 0.002)


def test_record_all_topics_for_a_duration(ros, tmp_path):
    publisher_node = Node('bag_test_publisher')
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publisher = publisher_node.create_publisher(TaskInstance, 'task_instance', latched)
    publisher.publish(_task_instance())
    bag = tmp_path / 'all'
    try:
        start = time.monotonic()
        counts = record(bag, duration=1.0, discovery_timeout=0.8)
        elapsed = time.monotonic() - start
    finally:
        publisher_node.destroy_node()
    assert counts == {'/task_instance': 1}  # /rosout and /parameter_events left out
    assert read_bag_summary(bag) == {'/task_instance': ('psl_msgs/msg/TaskInstance', 1)}
    assert 1.0 <= elapsed < 3.0


def test_record_into_existing_path_raises(tmp_path):
    (tmp_path / 'bag').mkdir()
    with pytest.raises(FileExistsError):
        record(tmp_path / 'bag', ['joint_states'], duration=0.1)
    assert list((tmp_path / 'bag').iterdir()) == []
