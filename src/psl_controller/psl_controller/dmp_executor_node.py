"""The DMP executor node: serves the ``execute_rollout`` action (psl_msgs/ExecuteRollout).

One rollout: check the goal, roll out the policy for theta on the control grid, send the
commanded trajectory to the controller (``joint_trajectory``, stamped zero = "start with the
next state"), start an episode of the task instance with the simulator's ``sim/reset``
service, then wait for the reward evaluator's ``rollout_evaluation`` of that episode and
return it. Rollouts run one at a time; a bad goal gets ``success=false`` and a message.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from diagnostic_msgs.msg import DiagnosticArray
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from psl_controller.policy import Reference, policy_for
from psl_msgs.action import ExecuteRollout
from psl_msgs.msg import RolloutEvaluation
from psl_msgs.srv import ResetTask
from psl_ros import names
from psl_ros.futures import wait_for
from psl_ros.node_main import run_node
from psl_ros.qos import RELIABLE, SERVICES
from psl_ros.stamps import duration_msg, to_ns
from psl_sim.arm_model import joint_names_of
from psl_sim.task import TaskError, load_task


def trajectory_msg(joint_names: list[str], ref: Reference) -> JointTrajectory:
    msg = JointTrajectory()
    msg.joint_names = list(joint_names)
    dt_ns = int(round((ref.t[1] - ref.t[0]) * 1e9)) if len(ref.t) > 1 else 0
    for k in range(len(ref.t)):
        msg.points.append(JointTrajectoryPoint(
            positions=ref.q[k].tolist(), velocities=ref.qd[k].tolist(),
            effort=ref.u_ffwd[k].tolist(), time_from_start=duration_msg(k * dt_ns)))
    return msg


class DMPExecutor(Node):

    def __init__(self):
        super().__init__('dmp_executor')
        self.declare_parameter('timeout_margin', 10.0, ParameterDescriptor(
            description='seconds to wait for an evaluation beyond the episode length'))
        group = ReentrantCallbackGroup()
        self.pub_trajectory = self.create_publisher(JointTrajectory, names.JOINT_TRAJECTORY,
                                                     RELIABLE)
        self.reset_client = self.create_client(ResetTask, names.RESET, callback_group=group,
                                               qos_profile=SERVICES)
        self.create_subscription(RolloutEvaluation, names.ROLLOUT_EVALUATION, self.on_evaluation,
                                 RELIABLE, callback_group=group)
        self.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self.on_diagnostics, 10,
                                 callback_group=group)
        self._rollout_lock = threading.Lock()
        self._cv = threading.Condition()
        self._evaluations: dict[int, RolloutEvaluation] = {}   # by episode start [ns]
        self._progress: dict[int, float] = {}   # episode start [ns] -> fraction done
        self._server = ActionServer(
            self, ExecuteRollout, names.EXECUTE_ROLLOUT, execute_callback=self.execute,
            goal_callback=lambda goal: GoalResponse.ACCEPT,
            cancel_callback=lambda handle: CancelResponse.ACCEPT, callback_group=group)
        self.get_logger().info('serving execute_rollout')

    def on_evaluation(self, msg: RolloutEvaluation) -> None:
        with self._cv:
            self._evaluations[to_ns(msg.stamp)] = msg
            self._cv.notify_all()

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        """The simulator reports episode progress about every tenth of an episode. /diagnostics
        is shared by every rollout worker: only this namespace's simulator counts."""
        mine = self.get_namespace().rstrip('/') + '/sim:'
        for status in msg.status:
            if not status.name.startswith(mine):
                continue
            values = {kv.key: kv.value for kv in status.values}
            if 'steps_done' in values and 'episode_start_ns' in values:
                self._progress[int(values['episode_start_ns'])] = (
                    int(values['steps_done']) / max(1, int(values['steps'])))

    def execute(self, goal_handle) -> ExecuteRollout.Result:
        with self._rollout_lock:
            result = ExecuteRollout.Result()
            try:
                result.evaluation = self._rollout(goal_handle)
                result.success, result.message = True, 'rollout done'
                goal_handle.succeed()
            except (TaskError, ValueError, RuntimeError) as exc:
                result.success, result.message = False, str(exc)
                self.get_logger().warning(f'rollout failed: {exc}')
                if goal_handle.is_cancel_requested:
                    goal_handle.canceled()
                else:
                    goal_handle.abort()
            return result

    def _rollout(self, goal_handle) -> RolloutEvaluation:
        goal = goal_handle.request
        task = load_task(goal.task)
        task.validate_tau(np.asarray(goal.tau))
        reference = policy_for(task).reference(np.asarray(goal.theta), np.asarray(goal.tau))
        if not self.reset_client.wait_for_service(timeout_sec=5.0):
            raise RuntimeError('the simulator service sim/reset is not available')
        deadline = time.monotonic() + 5.0
        while self.pub_trajectory.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                raise RuntimeError('no controller subscribes to joint_trajectory')
            time.sleep(0.01)
        # joint order of the simulator, which the controller maps by name
        joint_names = joint_names_of(task)
        self.pub_trajectory.publish(trajectory_msg(joint_names, reference))
        if not self.pub_trajectory.wait_for_all_acked(rclpy.duration.Duration(seconds=5.0)):
            raise RuntimeError('the controller did not receive the trajectory')
        response = self._call(self.reset_client, ResetTask.Request(task=goal.task, tau=goal.tau))
        if not response.success:
            raise ValueError(response.message)
        t0 = to_ns(response.stamp)
        timeout = response.num_steps * task.control_period + self.get_parameter(
            'timeout_margin').value
        deadline = time.monotonic() + timeout
        feedback, last = ExecuteRollout.Feedback(), -1.0
        with self._cv:
            while t0 not in self._evaluations:
                if goal_handle.is_cancel_requested:
                    raise RuntimeError('rollout canceled')
                if time.monotonic() > deadline:
                    done = self._progress.get(t0)
                    raise RuntimeError(
                        f'no rollout_evaluation within {timeout:.1f} s; the simulator reported '
                        + ('no progress (is the controller running?)' if done is None else
                           f'{100 * done:.0f} % of the episode (is the reward_evaluator '
                           'running?)'))
                self._cv.wait(timeout=0.05)
                feedback.progress = float(self._progress.get(t0, 0.0))
                if feedback.progress != last:
                    goal_handle.publish_feedback(feedback)
                    last = feedback.progress
            evaluation = self._evaluations.pop(t0)
            self._evaluations.clear()
            self._progress.clear()
        return evaluation

    def _call(self, client, request):
        try:
            return wait_for(client.call_async(request), 10.0, client.srv_name)
        except TimeoutError as exc:
            raise RuntimeError(str(exc)) from exc       # a failed rollout, with the reason


def main(args=None):
    run_node(DMPExecutor, args, threads=4)    # its action waits on other callbacks


if __name__ == '__main__':
    main()
