"""Lossless recording: while lockstep rollouts run back to back through the real graph, with one
core kept busy by a spinning process, a bag of the loop's topics (record() in a thread, as
``psl demo`` records) holds every message of every rollout, read back with an independent
reader (``mcap`` + ``mcap_ros2``), and the recorder counts no loss.

Per rollout of N control periods the loop publishes states 0..N: N + 1 joint_states, ee_pose
and /clock messages with the episode's stamps, N + 1 controller states (psl's controller's
reference and output, while someone subscribes) with the same stamps, N + 1 effort commands
(the controller answers every state, the last one too; the simulator ignores that answer) and
one task announcement and evaluation.
"""
import json
import threading

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from ruamel.yaml import YAML

from psl_bench.busy_cores import busy_cores
from psl_controller.pd_law import law_for
from psl_controller.policy import policy_for
from psl_ros.bag_recorder import LOSS_KEY, read_bag_summary, record
from psl_ros.stamps import NS_PER_S, to_ns
from psl_task.task import load_task, task_id

TASK = 'reach_over_obstacle'
# back to back: 2 x 1001 messages per topic, more than a keep-last-1000 subscription holds
# (what the recorder had), fewer than a publisher's history (psl_ros.qos.RELIABLE: 5000)
ROLLOUTS = 2
RECORDER_TIMEOUT = 120.0     # [s] for the recorder to take what the rollouts published
# stamp of each message of the topics that carry one message per state
PER_STATE_STAMP = {'/joint_states': lambda m: m.header.stamp,
                   '/pd_controller/controller_state': lambda m: m.header.stamp,
                   '/ee_pose': lambda m: m.header.stamp,
                   '/clock': lambda m: m.clock}
PER_ROLLOUT = ('/task_instance', '/rollout_evaluation')
TOPICS = [*PER_STATE_STAMP, '/effort_command', *PER_ROLLOUT]


def _ns(stamp) -> int:
    """Nanoseconds of a decoded builtin_interfaces/Time (mcap_ros2 objects)."""
    return stamp.sec * NS_PER_S + stamp.nanosec


class _Progress:
    """The recording so far, from record()'s progress reports."""

    def __init__(self):
        self._so_far = None
        self._changed = threading.Condition()

    def update(self, so_far) -> None:
        with self._changed:
            self._so_far = so_far
            self._changed.notify_all()

    def wait_for(self, expected: dict[str, int], timeout: float) -> bool:
        """Until every topic's messages taken or known lost reach its expected count; False
        after `timeout` s."""
        def arrived() -> bool:
            return self._so_far is not None and all(
                self._so_far.counts.get(t, 0) + self._so_far.lost.get(t, 0) >= n
                for t, n in expected.items())
        with self._changed:
            return self._changed.wait_for(arrived, timeout)

    def __repr__(self) -> str:
        return repr(self._so_far)


def _decoded(bag) -> tuple[dict[str, list], dict[str, int]]:
    """Messages per topic in the order written (mcap_ros2 decoding from the stored schemas),
    and the Statistics record's count per topic."""
    (path,) = bag.glob('*.mcap')
    with path.open('rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        statistics = {summary.channels[cid].topic: n
                      for cid, n in summary.statistics.channel_message_counts.items()}
        messages: dict[str, list] = {topic: [] for topic in statistics}
        for _schema, channel, _message, msg in reader.iter_decoded_messages(
                log_time_order=False):
            messages[channel.topic].append(msg)
    return messages, statistics


def test_a_bag_of_the_loop_holds_every_message_while_a_core_is_busy(graph, client, tmp_path):
    task = load_task(TASK)
    theta = policy_for(task).default_theta
    rng = np.random.default_rng(12)
    n = task.num_steps
    bag = tmp_path / 'loop'
    progress, stop, out = _Progress(), threading.Event(), {}

    def recording() -> None:
        out['recording'] = record(bag, TOPICS, stop=stop, discovery_timeout=2.0,
                                  progress=progress.update)

    starts = []
    with busy_cores(1):
        recorder = threading.Thread(target=recording)
        recorder.start()
        try:
            # every topic: the simulator builds the pose and the clock only for subscribers
            # it has matched
            client.wait_for_subscribers(TOPICS)
            for _ in range(ROLLOUTS):
                result = client.rollout(task_id(task), task.sample_tau(rng), theta)
                assert result.success, result.message
                starts.append(to_ns(result.evaluation.stamp))
            expected = {**dict.fromkeys([*PER_STATE_STAMP, '/effort_command'],
                                        ROLLOUTS * (n + 1)),
                        **dict.fromkeys(PER_ROLLOUT, ROLLOUTS)}
            assert progress.wait_for(expected, RECORDER_TIMEOUT), f'so far {progress}'
        finally:
            stop.set()
            recorder.join(timeout=60.0)
    assert 'recording' in out, 'record() raised (see the thread exception above)'
    recording = out['recording']
    assert recording.lost == dict.fromkeys(TOPICS, 0)
    # the latched task_instance may also bring the announcement of an episode before these
    assert recording.counts['/task_instance'] - ROLLOUTS in (0, 1)
    assert {t: c for t, c in recording.counts.items() if t != '/task_instance'} == {
        t: c for t, c in expected.items() if t != '/task_instance'}

    messages, statistics = _decoded(bag)
    assert statistics == recording.counts
    assert {t: c for t, (_, c) in read_bag_summary(bag).items()} == recording.counts
    episode_stamps = [t0 + k * task.control_period_ns for t0 in starts for k in range(n + 1)]
    for topic, stamp in PER_STATE_STAMP.items():
        assert [_ns(stamp(m)) for m in messages[topic]] == episode_stamps, topic
    assert [_ns(m.stamp) for m in messages['/rollout_evaluation']] == starts
    assert [_ns(m.stamp) for m in messages['/task_instance']][-ROLLOUTS:] == starts

    # the k-th effort command answers the k-th state: the controller's law on the state and
    # the reference the bag holds gives it exactly, and it is the output the controller said
    law = law_for(task)
    states = messages['/joint_states']
    references = [m.reference for m in messages['/pd_controller/controller_state']]
    answers = law.torque(np.array([m.position for m in states]),
                         np.array([m.velocity for m in states]),
                         np.array([m.positions for m in references]),
                         np.array([m.velocities for m in references]),
                         np.array([m.effort for m in references]))
    commands = np.array([m.data for m in messages['/effort_command']])
    assert commands.shape == answers.shape == (ROLLOUTS * (n + 1), task.n_joints)
    assert np.array_equal(commands, answers)
    outputs = np.array([m.output.effort for m in messages['/pd_controller/controller_state']])
    assert np.array_equal(commands, outputs)

    info = YAML(typ='safe').load((bag / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']
    assert json.loads(info['custom_data'][LOSS_KEY]) == recording.lost
