"""Task instances from the environment: a topic a perception node or an operator publishes on.

The message: std_msgs/Float64MultiArray, ``data`` = the task parameters tau of one instance
(the task YAML's ``task_parameters``, in order); each message is one instance, taken in the
order they come (a queue: an instance published while a task is being learned is the next
one's). An instance the task refuses (wrong size, NaN, outside the ranges) is logged and
skipped: the session waits for the next. ``ros2 topic pub --once /tau
std_msgs/msg/Float64MultiArray "{data: [0.6, 0.15]}"`` gives one.
"""
from __future__ import annotations

import queue
import time
from typing import Callable

import numpy as np
from rclpy.exceptions import NameValidationException
from rclpy.node import Node
from rclpy.validate_topic_name import validate_topic_name
from std_msgs.msg import Float64MultiArray

from psl_ros.qos import RELIABLE

STOP_POLL = 0.2     # s between looks at should_stop while waiting


class InstanceStopped(Exception):
    """The session was asked to stop while it waited for an instance."""


class TopicInstances:
    """`Learner`'s instance source (task selection 'given'): index -> tau, the next instance
    from `topic`, waiting up to `timeout` s (RuntimeError after). `validate` (the task's
    validate_tau) refuses a bad instance with a reason, which is logged; the next is taken."""

    def __init__(self, node: Node, topic: str, validate: Callable[[np.ndarray], None],
                 timeout: float = 60.0, should_stop: Callable[[], bool] = lambda: False):
        self.node, self.validate, self.timeout = node, validate, timeout
        self.should_stop = should_stop
        self._queue: queue.Queue = queue.Queue()
        try:
            validate_topic_name(topic if topic.startswith(('/', '~')) else '/' + topic)
        except NameValidationException as exc:
            raise ValueError(f'task instance topic {topic[:80]!r}: '
                             f'{str(exc).splitlines()[0]}') from None
        self.subscription = node.create_subscription(
            Float64MultiArray, topic, lambda m: self._queue.put(np.array(m.data, dtype=float)),
            RELIABLE)
        self.topic = self.subscription.topic_name

    def __call__(self, index: int) -> np.ndarray:
        deadline = time.monotonic() + self.timeout
        while True:
            if self.should_stop():
                raise InstanceStopped(f'stopped while waiting for task {index} on {self.topic}')
            left = deadline - time.monotonic()
            if left <= 0.0:
                raise RuntimeError(f'no task instance on {self.topic} within {self.timeout:g} s '
                                   f'(task {index}): publish its tau there '
                                   '(std_msgs/Float64MultiArray)')
            try:
                tau = self._queue.get(timeout=min(STOP_POLL, left))
            except queue.Empty:
                continue
            try:
                self.validate(tau)
            except ValueError as exc:
                self.node.get_logger().warning(f'task instance {tau.tolist()} on {self.topic} '
                                               f'skipped: {exc}')
                continue
            return tau
