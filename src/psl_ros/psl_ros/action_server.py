"""rclpy's ActionServer whose goal answers wait for a client the server has not matched yet.

The goal request of an action is a service call, and its answer is lost the way a service's
is (`psl_ros.service`): the client's ``wait_for_server`` is true once the *client* has matched
the server, but the server may match the client's response reader only later. Fast DDS
(rmw_fastrtps ``rmw_response.cpp``) then waits 100 ms and gives the answer up with a warning
("failed to send response (timeout)"), which rclpy 7.1.6 (Jazzy) takes for success: the goal
runs and the client, without the answer, waits in vain and never sees it (seen in CI: a learn
goal sent right after the graph came up had no answer in 30 s).

Here the answer is sent again until the server has matched the client (each attempt blocks
rmw's 100 ms; goals are rare, the client usually appears within a second under load) or
`GOAL_ANSWER_PATIENCE` s have passed; a client that has gone is recognised by rmw (the answer
is dropped as sent). A goal whose answer is given up is dropped unexecuted: nobody would
hear of it.

Its three services (goal, result, cancel) keep `psl_ros.qos.SERVICES` (keep-last 5,000) on
both ends, here and in `psl_ros.action_client`, instead of rclpy's keep-last 10: a flood of
goals (200 in 2 s right after a homing goal on the standard robot) left more than ten
requests untaken in the server's reader while its threads were busy, and more than ten answers
untaken in the client's, and each side dropped the oldest: 136-195 of 200 goals answered, and
of the results asked for at once, 11-31 of 160 (measured here with the one side or the other
still at 10: 143 and 69 of 200). A depth is not part of QoS matching: clients with rclpy's
default still talk to these servers.
"""
from __future__ import annotations

import time

from action_msgs.msg import GoalInfo
from rclpy.action import ActionServer as _RclpyActionServer
from rclpy.action import GoalResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.executors import await_or_execute
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.task import Future

from psl_ros.qos import SERVICES
from psl_ros.service import answered

GOAL_ANSWER_PATIENCE = 10.0   # s a goal answer is tried (clients wait 30 s for one)
RETRY_PAUSE = 0.05            # s between attempts (each attempt itself waits 100 ms in rmw)
# the keywords of rclpy's ActionServer and ActionClient for the QoS of the action's services
SERVICE_QOS = ('goal_service_qos_profile', 'result_service_qos_profile',
               'cancel_service_qos_profile')


class ActionServer(_RclpyActionServer):
    """Drop-in replacement for ``rclpy.action.ActionServer``, with one more keyword:
    ``before_answer(goal_handle)``, called for an accepted goal before the client hears it
    was accepted (a controller takes the goal then: a client that starts the robot's clock on
    the answer finds it in place); undone by ``dropped(goal_handle)`` if the answer is given
    up."""

    def __init__(self, *args, before_answer=None, dropped=None, **kwargs):
        for service in SERVICE_QOS:
            kwargs.setdefault(service, SERVICES)
        super().__init__(*args, **kwargs)
        self._before_answer, self._dropped = before_answer, dropped

    def _send_goal_answer(self, request_header, response) -> bool:
        """Whether the answer was sent (or dropped by rmw for a client that has gone)."""
        deadline = time.monotonic() + GOAL_ANSWER_PATIENCE
        attempts = 0
        while True:
            attempts += 1
            try:
                done = answered(lambda: self._handle.send_goal_response(request_header, response))
            except _rclpy.RCLError as exc:   # as rclpy: the client may have gone away
                self._logger.warning(f'goal answer failed: {exc}')
                return False
            if not done:
                if time.monotonic() >= deadline:
                    self._logger.error(f'goal answer given up after {attempts} attempts: the '
                                       'client never matched this server')
                    return False
                time.sleep(RETRY_PAUSE)
                continue
            if attempts > 1:
                self._logger.info(f'goal answer sent at attempt {attempts} (the server '
                                  'matched the client late)')
            return True

    async def _execute_goal_request(self, request_header_and_message):
        # rclpy 7.1.6's ActionServer._execute_goal_request; only the answer is sent with
        # patience (`_send_goal_answer`) and a goal whose answer is given up is dropped
        request_header, goal_request = request_header_and_message
        goal_uuid = goal_request.goal_id
        goal_info = GoalInfo()
        goal_info.goal_id = goal_uuid
        with self._lock:
            goal_id_exists = self._handle.goal_exists(goal_info)
        accepted = False
        goal_handle = None
        if not goal_id_exists:
            response = await await_or_execute(self._goal_callback, goal_request.goal)
            if not isinstance(response, GoalResponse):
                self._logger.warning('Goal request callback did not return a GoalResponse '
                                     'type. Rejecting goal.')
            else:
                accepted = GoalResponse.ACCEPT == response
        if accepted:
            goal_info.stamp = self._node.get_clock().now().to_msg()
            try:
                with self._lock:
                    goal_handle = ServerGoalHandle(self, goal_info, goal_request.goal)
            except RuntimeError as exc:
                self._logger.error(f'Failed to accept new goal with ID {goal_uuid.uuid}: {exc}')
                accepted = False
            else:
                self._goal_handles[bytes(goal_uuid.uuid)] = goal_handle
                self._result_futures[bytes(goal_uuid.uuid)] = Future()
                self.add_future(self._result_futures[bytes(goal_uuid.uuid)])
                if self._before_answer is not None:
                    self._before_answer(goal_handle)
        response_msg = self._action_type.Impl.SendGoalService.Response()
        response_msg.accepted = accepted
        response_msg.stamp = goal_info.stamp
        if not self._send_goal_answer(request_header, response_msg):
            if goal_handle is not None and self._dropped is not None:
                self._dropped(goal_handle)
            if goal_handle is not None:
                key = bytes(goal_uuid.uuid)   # as rclpy's _execute_expire_goals
                goal_handle.destroy()
                del self._goal_handles[key]
                self.remove_future(self._result_futures.pop(key))
            return
        if not accepted:
            return
        self._handle.publish_status()
        await await_or_execute(self._handle_accepted_callback, goal_handle)
