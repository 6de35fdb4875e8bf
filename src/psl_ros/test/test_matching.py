"""Matched-endpoint reports (psl_ros.matching) between two DDS participants: the report
follows the publisher's matches as they come and go, and once it says a new subscription is
matched, the very next message reaches it."""
import os
import threading
import time

import pytest

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from psl_ros.matching import PUBLISHER, SUBSCRIPTION, MatchedEndpoints, MatchReport  # noqa: E402
from psl_ros.qos import RELIABLE  # noqa: E402

TOPIC = f'psl_matching_test_{os.getpid()}'
WAIT = 20.0     # s, deadline for discovery on a loaded machine


class Participant:
    """A node in a context of its own (its own DDS participant), spun in a thread."""

    def __init__(self, name: str):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - shut down under us
            pass

    def close(self):
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self.thread.join(timeout=2.0)


def wait_for(condition, timeout=WAIT) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


@pytest.fixture
def pair():
    server, client = Participant('reporting'), Participant('watching')
    try:
        yield server, client
    finally:
        client.close()
        server.close()


def test_the_report_follows_matches_and_a_matched_reader_gets_the_next_message(pair):
    server, client = pair
    report = MatchReport(server.node)
    publisher = report.create_publisher(String, TOPIC, RELIABLE)
    report.create_subscription(String, TOPIC + '_in', lambda _: None, RELIABLE)
    topic = server.node.resolve_topic_name(TOPIC)
    reports = MatchedEndpoints(client.node)
    # the report is latched: a watcher that comes later gets the current counts
    assert wait_for(lambda: reports.counts(PUBLISHER, topic) == {'/reporting': 0})
    assert reports.counts(SUBSCRIPTION, topic + '_in') == {'/reporting': 0}

    for round_ in range(3):
        got = []
        sub = client.node.create_subscription(String, TOPIC, lambda m: got.append(m.data),
                                              RELIABLE)
        # both halves: the remote writer's (the report) and the local reader's
        assert wait_for(lambda: reports.counts(PUBLISHER, topic) == {'/reporting': 1}
                        and sub.get_publisher_count() == 1), reports.counts(PUBLISHER, topic)
        publisher.publish(String(data=f'first {round_}'))
        assert wait_for(lambda: got), 'a matched reader missed the first message'
        assert got == [f'first {round_}']
        client.node.destroy_subscription(sub)
        assert wait_for(lambda: reports.counts(PUBLISHER, topic) == {'/reporting': 0})

    # the subscription side is reported too
    writer = client.node.create_publisher(String, TOPIC + '_in', RELIABLE)
    assert wait_for(lambda: reports.counts(SUBSCRIPTION, topic + '_in') == {'/reporting': 1})
    client.node.destroy_publisher(writer)
    assert wait_for(lambda: reports.counts(SUBSCRIPTION, topic + '_in') == {'/reporting': 0})
