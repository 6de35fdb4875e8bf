"""rclpy's ActionClient without the lost-response race of rclpy 7.1.6 (ROS 2 Jazzy).

``ActionClient.send_goal_async`` (and the cancel and result requests) send the request first
and register its sequence number afterwards. When the executor runs in another thread (a
MultiThreadedExecutor, or a client spun in a background thread) and the answer arrives in
between, ``execute`` drops it ("Ignoring unexpected goal response") and the future never
completes: ros2/rclpy#1123, fixed upstream by ros2/rclpy#1308 (backported to Jazzy in #1519,
not in the 7.1.6 wheels this workspace installs). Here the request and its registration
happen under one lock that ``execute`` takes before it looks an answer up.

The action's services keep `psl_ros.qos.SERVICES` here as on psl's servers
(`psl_ros.action_server`: with rclpy's keep-last 10 a client taking answers slower than a busy
server sends them loses the oldest).
"""
from __future__ import annotations

import threading

from rclpy.action import ActionClient as _RclpyActionClient

from psl_ros.action_server import SERVICE_QOS
from psl_ros.qos import SERVICES


class ActionClient(_RclpyActionClient):
    """Drop-in replacement for ``rclpy.action.ActionClient``."""

    def __init__(self, *args, **kwargs):
        for service in SERVICE_QOS:
            kwargs.setdefault(service, SERVICES)
        super().__init__(*args, **kwargs)
        self._registering = threading.Lock()

    def send_goal_async(self, goal, feedback_callback=None, goal_uuid=None):
        with self._registering:
            return super().send_goal_async(goal, feedback_callback, goal_uuid)

    def _cancel_goal_async(self, goal_handle):
        with self._registering:
            return super()._cancel_goal_async(goal_handle)

    def _get_result_async(self, goal_handle):
        with self._registering:
            return super()._get_result_async(goal_handle)

    async def execute(self, taken_data):
        with self._registering:     # a request being sent has registered its number
            pass
        return await super().execute(taken_data)
