"""HotPath's subscriptions come and go while its loop runs: an unsubscribed topic's messages
no longer arrive, its subscription leaves the ROS graph, the others keep arriving, and a topic
subscribed again arrives again."""
import os
import threading
import time

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

import rclpy  # noqa: E402
from rclpy.node import Node  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from psl_ros.hot_path import HotPath  # noqa: E402
from psl_ros.qos import RELIABLE  # noqa: E402

TOPICS = (f'hot_path_a_{os.getpid()}', f'hot_path_b_{os.getpid()}')
WAIT = 20.0     # s, deadline for discovery and delivery on a loaded machine


def until(condition, timeout: float = WAIT) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_a_subscription_removed_while_the_loop_runs_stops_and_leaves_the_graph():
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node(f'hot_path_test_{os.getpid()}', context=context)
    loop = HotPath(node, pause=0.005)
    got = {topic: [] for topic in TOPICS}
    lock = threading.Lock()

    def keep(topic):
        def on(data):
            with lock:
                got[topic].append(bytes(data))
        return on
    try:
        publishers = {t: node.create_publisher(String, t, RELIABLE) for t in TOPICS}
        handles = {t: loop.subscribe(String, t, keep(t), RELIABLE, raw=True) for t in TOPICS}
        loop.start()
        assert until(lambda: all(node.count_subscribers(t) == 1 for t in TOPICS))
        assert until(lambda: all(h.get_publisher_count() == 1 for h in handles.values()))

        def publish_until_both_arrive(topics):
            marks = {t: len(got[t]) for t in topics}
            return until(lambda: [publishers[t].publish(String(data='x')) for t in topics]
                         and all(len(got[t]) > marks[t] for t in topics))
        assert publish_until_both_arrive(TOPICS)
        loop.unsubscribe(handles[TOPICS[0]])
        assert until(lambda: node.count_subscribers(TOPICS[0]) == 0)
        with lock:
            before = len(got[TOPICS[0]])
        for _ in range(50):
            publishers[TOPICS[0]].publish(String(data='unheard'))
        assert publish_until_both_arrive([TOPICS[1]])       # the loop runs on ...
        assert len(got[TOPICS[0]]) == before                # ... without the removed one
        handles[TOPICS[0]] = loop.subscribe(String, TOPICS[0], keep(TOPICS[0]), RELIABLE,
                                            raw=True)
        assert until(lambda: handles[TOPICS[0]].get_publisher_count() == 1)
        assert publish_until_both_arrive(TOPICS)
    finally:
        loop.stop()
        node.destroy_node()
        rclpy.shutdown(context=context)


def test_a_subscription_removed_before_the_loop_took_it_up_leaves_the_graph():
    """Subscribe and unsubscribe at once, again and again: the loop may wake once for both,
    and must still destroy each (once, it compared its empty set with the empty set)."""
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node(f'hot_path_quick_{os.getpid()}', context=context)
    loop = HotPath(node)
    loop.start()
    try:
        for _ in range(20):
            handle = loop.subscribe(String, TOPICS[0], lambda data: None, RELIABLE, raw=True)
            loop.unsubscribe(handle)
            assert until(lambda: node.count_subscribers(TOPICS[0]) == 0), \
                'an unsubscribed subscription stayed in the graph'
    finally:
        loop.stop()
        node.destroy_node()
        rclpy.shutdown(context=context)
