"""The standard robot node: a task's MuJoCo model as a ros2_control robot, nothing more.

Publishes ``joint_states`` (sensor_msgs/JointState: what joint_state_broadcaster sends; stamped
with the node's clock, system time, at each tick; joints in ``joint_order`` then
``extra_joints``; effort = the torque applied in the period before) and takes
``effort_command`` (std_msgs/Float64MultiArray in ``command_joints`` order: an effort
forward_command_controller). Remap them to a real robot's names, e.g. ``--ros-args -r
joint_states:=/joint_states -r effort_command:=/effort_controller/commands``. Applies zero
torque once no command has come for ``command_timeout`` (wall clock). Reads the latched
``task_instance`` (psl_msgs/TaskInstance) of its task and places that instance in its world
(obstacles, payload) without touching the arm. No services, no /clock, no episodes: it steps on
the wall clock at the task's control rate from start to end. The physics, noise, latency, model
error and command timeout are `psl_sim.standard_robot.StandardRobot`.
"""
from __future__ import annotations

import threading
import time

from rclpy.exceptions import InvalidParameterValueException
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from psl_msgs.msg import TaskInstance
from psl_ros import names
from psl_ros.node_main import run_node
from psl_ros.parameters import check_update, declare
from psl_ros.qos import LATCHED, RELIABLE
from psl_ros.realtime import sleep_until
from psl_sim.standard_robot import CommandRefused, StandardRobot
from psl_sim.standard_robot_parameters import StandardRobotParameters
from psl_task.task import TaskError, load_task

THROTTLE = 1.0      # s between two warnings of one kind


class StandardRobotNode(Node):

    def __init__(self):
        super().__init__('standard_robot')
        self.add_on_set_parameters_callback(
            lambda params: check_update(self, StandardRobotParameters, params))
        try:
            self.parameters = declare(self, StandardRobotParameters)
        except InvalidParameterValueException as exc:   # one line from run_node, no traceback
            raise ValueError(str(exc)) from None
        # the command timeout on the wall clock, as a robot's safety layer counts it
        self.robot = StandardRobot(self.parameters, clock=time.monotonic)
        self._lock = threading.Lock()       # the robot: the loop thread and the callbacks
        self.deadline_misses = 0            # control periods the loop fell behind by
        self.refused_commands = 0
        self._joint_state = JointState()
        self.pub_joints = self.create_publisher(JointState, names.JOINT_STATES, RELIABLE)
        self.create_subscription(Float64MultiArray, names.EFFORT_COMMAND, self.on_command,
                                 RELIABLE)
        self.create_subscription(TaskInstance, names.TASK_INSTANCE, self.on_task_instance,
                                 LATCHED)
        robot, p = self.robot, self.parameters
        self.get_logger().info(
            f'standard robot: task {robot.arm.task.name!r} at {1.0 / robot.period:g} Hz; '
            f'joint_states {robot.names}, effort_command {robot.command_joints}; noise '
            f'{p.position_noise:g} rad, {p.velocity_noise:g} rad/s; latency '
            f'{p.latency_periods} period(s); command timeout {robot.command_timeout:g} s; '
            f'model error {robot.model_error}')
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def on_command(self, msg: Float64MultiArray) -> None:
        try:
            with self._lock:
                self.robot.receive(msg.data)
        except CommandRefused as exc:
            self.refused_commands += 1
            self.get_logger().warning(f'refused effort_command: {exc} '
                                      f'({self.refused_commands} refused so far)',
                                      throttle_duration_sec=THROTTLE)

    def on_task_instance(self, msg: TaskInstance) -> None:
        try:
            if load_task(msg.task).path != self.robot.arm.task.path:
                raise TaskError(f'it is of task {msg.task!r}; this robot lives in the world of '
                                f'task {self.robot.arm.task.name!r}')
            with self._lock:
                tau = self.robot.place(msg.tau)
        except TaskError as exc:
            self.get_logger().warning(f'task instance not placed: {exc}')
            return
        self.get_logger().info(f'task instance placed: tau = {tau.tolist()}')

    def _loop(self) -> None:
        """Each period: publish the state, then step; sleep to the next deadline. Behind by
        more than a period: the periods missed are counted and the loop goes on from now."""
        period = self.robot.period
        next_tick = time.perf_counter()
        js = self._joint_state
        js.name = list(self.robot.names)
        while not self._stop.is_set():
            with self._lock:
                state = self.robot.measure()
                js.header.stamp = self.get_clock().now().to_msg()
                js.position = state.position.tolist()
                js.velocity = state.velocity.tolist()
                js.effort = state.effort.tolist()
                try:
                    self.pub_joints.publish(js)
                except Exception:   # noqa: BLE001 - the context ended under us (Ctrl-C)
                    if not self.context.ok():
                        return
                    raise
                self.robot.advance()
            next_tick += period
            late = time.perf_counter() - next_tick
            if late > period:
                missed = int(late // period)
                self.deadline_misses += missed
                self.get_logger().warning(
                    f'{self.deadline_misses} control period(s) missed so far ({missed} now): '
                    'the loop goes on from now, without a burst',
                    throttle_duration_sec=THROTTLE)
                next_tick = time.perf_counter()
            else:
                sleep_until(next_tick, 0.0)

    def destroy_node(self):
        self._stop.set()
        self._thread.join(timeout=1.0)
        super().destroy_node()


def main(args=None):
    run_node(StandardRobotNode, args)


if __name__ == '__main__':
    main()
