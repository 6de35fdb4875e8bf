"""bag_recorder: record live topics into an MCAP rosbag2 bag; read it back with rosbags and with
an independent reader (the ``mcap`` and ``mcap-ros2-support`` packages); losses counted."""

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import rclpy
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rcl_interfaces.msg import Log
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbags.rosbag2 import Reader
from ruamel.yaml import YAML
from psl_msgs.msg import TaskInstance
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from psl_ros.bag_recorder import LOSS_KEY, make_typestore, read_bag_summary, record

N_EFFORT = 50
N_JOINT_STATES = 30
MATCH_TIMEOUT = 8.0  # [s] for the recorder to subscribe to a publisher
ACK_TIMEOUT = 5.0  # [s] for the recorder to acknowledge everything published
LOG_TIMEOUT = 10.0  # [s] for the recorder to say that it waits for a late topic
DISCOVERY_TIMEOUT = 0.5  # [s] given to record()
NAMED_TOPICS = ['joint_states', 'effort_command', 'task_instance', 'never_there']
# what the named recording holds
EXPECTED_COUNTS = {'/joint_states': N_JOINT_STATES, '/effort_command': N_EFFORT,
                   '/task_instance': 1}
EXPECTED_TYPES = {'/joint_states': 'sensor_msgs/msg/JointState',
                  '/effort_command': 'std_msgs/msg/Float64MultiArray',
                  '/task_instance': 'psl_msgs/msg/TaskInstance'}


def _private_domain(monkeypatch, domain: int) -> None:
    """Set a domain of this test process only (conftest.py `private_ros_domain`, before
    rclpy.init): no graph of the run publishes there; discovery on this machine."""
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


@pytest.fixture
def ros(monkeypatch, private_ros_domain):
    """rclpy initialised on a private domain, shut down afterwards."""
    _private_domain(monkeypatch, private_ros_domain)
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


def _wait_acked(*publishers) -> None:
    for publisher in publishers:
        if not publisher.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT)):
            raise TimeoutError(f'{publisher.topic_name} not acknowledged')


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


class _RecorderLog:
    """The recorder node's /rosout lines, seen from `node` (spun here in a thread)."""

    def __init__(self, node: Node):
        self._lines: list[str] = []
        self._changed = threading.Condition()
        node.create_subscription(Log, '/rosout', self._on_log, QoSProfile(
            depth=1000, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self._executor = SingleThreadedExecutor()
        self._executor.add_node(node)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True)
        self._thread.start()

    def _on_log(self, msg: Log) -> None:
        if msg.name == 'psl_bag_recorder':
            with self._changed:
                self._lines.append(msg.msg)
                self._changed.notify_all()

    def wait_for(self, text: str, timeout: float = LOG_TIMEOUT) -> None:
        with self._changed:
            if not self._changed.wait_for(lambda: any(text in line for line in self._lines),
                                          timeout):
                raise TimeoutError(f'the recorder never logged {text!r}: {self._lines}')

    def close(self) -> None:
        self._executor.shutdown()
        self._thread.join(timeout=5.0)


def _publish(node: Node, log: _RecorderLog, stop: threading.Event, errors: list) -> None:
    """Publish once the recorder listens, then end the recording.

    The effort publisher appears only once the recorder has said that it is still waiting
    for it after its discovery timeout, so that subscribing to late topics is exercised. The
    recording ends when the recorder has acknowledged every message: record() writes every
    message its subscriptions acknowledged.
    """
    try:
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        task_pub = node.create_publisher(TaskInstance, 'task_instance', latched)
        joint_pub = node.create_publisher(JointState, 'joint_states', 10)
        task_pub.publish(_task_instance())  # before anyone listens: latched
        _wait_matched(joint_pub)
        _wait_matched(task_pub)
        log.wait_for('no publisher yet on /effort_command')
        effort_pub = node.create_publisher(Float64MultiArray, 'effort_command', 10)
        _wait_matched(effort_pub)
        for i in range(max(N_EFFORT, N_JOINT_STATES)):
            if i < N_JOINT_STATES:
                joint_pub.publish(_joint_state(i))
            if i < N_EFFORT:
                effort_pub.publish(Float64MultiArray(data=[float(i), -float(i)]))
            time.sleep(0.001)
        _wait_acked(joint_pub, effort_pub, task_pub)
    except Exception as exc:  # reported by the test in the main thread
        errors.append(exc)
    finally:
        stop.set()


@pytest.fixture(scope='module')
def named_bag(tmp_path_factory, private_ros_domain) -> dict:
    """One recording of NAMED_TOPICS (see `_publish`), read by several tests: the bag, what
    record() returned, the publishers' type hashes, the wall clock before and after it."""
    bag = tmp_path_factory.mktemp('named') / 'bag'
    with pytest.MonkeyPatch.context() as monkeypatch:
        _private_domain(monkeypatch, private_ros_domain)
        rclpy.init()
        try:
            publisher_node = Node('bag_test_publisher')
            log = _RecorderLog(publisher_node)
            stop = threading.Event()
            errors = []
            thread = threading.Thread(target=_publish,
                                      args=(publisher_node, log, stop, errors))
            try:
                wall = [time.time_ns()]
                thread.start()
                recording = record(bag, NAMED_TOPICS, stop=stop, duration=30.0,
                                   discovery_timeout=DISCOVERY_TIMEOUT)
                wall.append(time.time_ns())
                thread.join(timeout=10.0)
                type_hashes = {
                    t: str(publisher_node.get_publishers_info_by_topic(t)[0].topic_type_hash)
                    for t in ('/joint_states', '/task_instance')}
            finally:
                stop.set()
                thread.join(timeout=10.0)
                log.close()
                publisher_node.destroy_node()
        finally:
            rclpy.try_shutdown()
    assert not errors, errors
    return {'bag': bag, 'recording': recording, 'type_hashes': type_hashes, 'wall': wall}


def test_record_named_topics(named_bag):
    bag, recording = named_bag['bag'], named_bag['recording']
    assert recording.path == bag
    assert recording.counts == {**EXPECTED_COUNTS, '/never_there': 0}
    assert recording.lost == dict.fromkeys(recording.counts, 0)
    assert read_bag_summary(bag) == {topic: (EXPECTED_TYPES[topic], count)
                                     for topic, count in EXPECTED_COUNTS.items()}

    metadata = YAML(typ='safe').load((bag / 'metadata.yaml').read_text())
    info = metadata['rosbag2_bagfile_information']
    assert info['storage_identifier'] == 'mcap'
    assert info['version'] == 9
    assert json.loads(info['custom_data'][LOSS_KEY]) == dict.fromkeys(EXPECTED_COUNTS, 0)
    assert [p.suffix for p in bag.iterdir() if p.name != 'metadata.yaml'] == ['.mcap']
    topic_metadata = {t['topic_metadata']['name']: t['topic_metadata']
                      for t in info['topics_with_message_count']}
    task_qos = topic_metadata['/task_instance']['offered_qos_profiles']
    assert [(q['reliability'], q['durability']) for q in task_qos] == [
        ('reliable', 'transient_local')]
    assert task_qos[0]['deadline'] == {'sec': 9223372036, 'nsec': 854775807}  # infinite
    joint_qos = topic_metadata['/joint_states']['offered_qos_profiles']
    assert [q['durability'] for q in joint_qos] == ['volatile']
    for topic, type_hash in named_bag['type_hashes'].items():
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
    # receive times on the wall clock: within the recording
    assert named_bag['wall'][0] <= min(stamps) <= max(stamps) <= named_bag['wall'][1]

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


def test_an_independent_mcap_reader_reads_the_bag(named_bag):
    """The ``mcap`` reader (not rosbags): ros2 profile, a schema per channel, statistics equal
    to what record() reported, messages decoded by mcap_ros2 from the stored schemas alone,
    and rosbag2's metadata record."""
    bag, recording = named_bag['bag'], named_bag['recording']
    (mcap_file,) = bag.glob('*.mcap')
    with mcap_file.open('rb') as stream:
        reader = make_reader(stream, validate_crcs=True, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == set(EXPECTED_COUNTS)
        for topic, channel in channels.items():
            schema = summary.schemas[channel.schema_id]
            assert (schema.name, schema.encoding) == (EXPECTED_TYPES[topic], 'ros2msg')
            assert schema.data
            assert channel.message_encoding == 'cdr'
            assert 'offered_qos_profiles' in channel.metadata
        statistics = summary.statistics
        per_topic = {c.topic: statistics.channel_message_counts[cid]
                     for cid, c in summary.channels.items()}
        assert per_topic == {t: n for t, n in recording.counts.items() if n}
        assert per_topic == {t: n for t, (_, n) in read_bag_summary(bag).items()}
        assert statistics.message_count == sum(recording.counts.values())

        decoded: dict[str, list] = {topic: [] for topic in channels}
        for _schema, channel, message, msg in reader.iter_decoded_messages(
                log_time_order=False):
            decoded[channel.topic].append(msg)
            assert statistics.message_start_time <= message.log_time \
                <= statistics.message_end_time
        assert [(m.header.stamp.sec, m.header.stamp.nanosec, list(m.position))
                for m in decoded['/joint_states']] == [
            (i, 1000 * i, [0.01 * i, -0.02 * i]) for i in range(N_JOINT_STATES)]
        assert [list(m.data) for m in decoded['/effort_command']] == [
            [float(i), -float(i)] for i in range(N_EFFORT)]
        (task,) = decoded['/task_instance']
        assert (task.task, list(task.tau), task.num_steps) == ('reach', [0.3, -0.4], 500)

        (metadata,) = [m for m in reader.iter_metadata() if m.name == 'rosbag2']
    info = YAML(typ='safe').load(metadata.metadata['serialized_metadata'])
    assert {t['topic_metadata']['name']: t['message_count']
            for t in info['topics_with_message_count']} == per_topic
    assert json.loads(info['custom_data'][LOSS_KEY]) == dict.fromkeys(EXPECTED_COUNTS, 0)


# record() in its own process, so that the test can stop it (SIGSTOP) like a starved reader
RECORDER_PROCESS = """
import sys
from psl_ros.bag_recorder import record
record(sys.argv[1], sys.argv[2:], discovery_timeout=0.0)
"""
N_BURST = 20000  # published while the recorder is stopped: more than DDS buffers for it


def test_losses_are_counted_and_equal_the_gap(ros, tmp_path):
    """A recorder that takes nothing for a while loses messages from a keep-last publisher
    (its history overwrites what the recorder has not acknowledged): the losses it counts
    and writes into the metadata equal the indices missing from the bag."""
    bag = tmp_path / 'lossy'
    node = Node('bag_test_lossy_publisher')
    publisher = node.create_publisher(JointState, 'lossy', QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE))
    # The recorder is stopped while the burst is published. With psl's lease of 4 s a burst
    # that takes longer on a loaded machine made this process drop the stopped recorder as
    # dead and match it again as a new (volatile) reader afterwards: it then got nothing, and
    # the acknowledgement wait had nobody to wait for (seen in CI: the bag held message 0
    # only). The recorder announces a lease longer than any burst.
    profile = tmp_path / 'long_lease.xml'
    text, found = re.subn(r'(<leaseDuration>\s*<sec>)\d+', r'\g<1>600',
                          Path(os.environ['FASTRTPS_DEFAULT_PROFILES_FILE']).read_text())
    assert found == 1, 'no leaseDuration in the Fast DDS profile'
    profile.write_text(text)
    recorder = subprocess.Popen([sys.executable, '-c', RECORDER_PROCESS, str(bag), 'lossy'],
                                stderr=subprocess.PIPE, text=True,
                                env={**os.environ, 'FASTRTPS_DEFAULT_PROFILES_FILE': str(profile)})
    try:
        _wait_matched(publisher, timeout=60.0)
        publisher.publish(_joint_state(0))
        _wait_acked(publisher)  # the recorder receives
        os.kill(recorder.pid, signal.SIGSTOP)
        try:
            for i in range(1, N_BURST + 1):
                publisher.publish(_joint_state(i))
        finally:
            os.kill(recorder.pid, signal.SIGCONT)
        assert publisher.get_subscription_count() == 1, 'the stopped recorder was unmatched'
        _wait_acked(publisher)
        recorder.send_signal(signal.SIGINT)  # ends the recording normally
        _, stderr = recorder.communicate(timeout=60.0)
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.communicate()
        node.destroy_node()
    assert recorder.returncode == 0, stderr

    typestore = make_typestore()
    with Reader(bag) as reader:
        received = [typestore.deserialize_cdr(raw, c.msgtype).header.stamp.sec
                    for c, _, raw in reader.messages()]
    metadata = YAML(typ='safe').load((bag / 'metadata.yaml').read_text())
    lost = json.loads(metadata['rosbag2_bagfile_information']['custom_data'][LOSS_KEY])
    assert received == sorted(set(received))
    assert received[0] == 0 and received[-1] == N_BURST  # the last ones are in the history
    gap = N_BURST + 1 - len(received)
    assert gap > 0, 'nothing was lost: the scenario did not starve the recorder'
    assert lost == {'/lossy': gap}
    assert f'{gap} messages lost: /lossy {gap}' in stderr


def test_record_all_topics_for_a_duration(ros, tmp_path):
    publisher_node = Node('bag_test_publisher')
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publisher = publisher_node.create_publisher(TaskInstance, 'task_instance', latched)
    publisher.publish(_task_instance())
    bag = tmp_path / 'all'
    try:
        start, wall_start = time.monotonic(), time.time_ns()
        recording = record(bag, duration=1.0, discovery_timeout=1.0)   # looks the whole time
        elapsed, wall_end = time.monotonic() - start, time.time_ns()
    finally:
        publisher_node.destroy_node()
    assert recording.counts == {'/task_instance': 1}  # /rosout and /parameter_events left out
    assert read_bag_summary(bag) == {'/task_instance': ('psl_msgs/msg/TaskInstance', 1)}
    assert elapsed >= 1.0  # the whole duration, however slow the machine
    info = YAML(typ='safe').load((bag / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']
    assert wall_start <= info['starting_time']['nanoseconds_since_epoch'] <= wall_end


def test_record_into_existing_path_raises(tmp_path):
    (tmp_path / 'bag').mkdir()
    with pytest.raises(FileExistsError):
        record(tmp_path / 'bag', ['joint_states'], duration=0.1)
    assert list((tmp_path / 'bag').iterdir()) == []
