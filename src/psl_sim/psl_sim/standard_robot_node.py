"""The standard robot node: a task's MuJoCo model as a ros2_control robot with its own
JointTrajectoryController, nothing more.

Publishes ``joint_states`` (sensor_msgs/JointState: what joint_state_broadcaster sends;
stamped with the robot's time, the system time at its start plus the periods since, at each
tick; joints in ``joint_order`` then ``extra_joints``; effort = the torque applied in the
period before) and serves
``standard_robot/follow_joint_trajectory`` (control_msgs/FollowJointTrajectory, the effort
interface: `psl_controller.follow_joint_trajectory`, with JTC's ``joints`` and
``command_interfaces`` parameters and ``~/controller_state``; goals past the arm's limits or its
size bounds rejected: `psl_controller.goal_limits`). The trajectory controller runs
inside the robot's loop, stepped with the physics on the measured state
(`psl_sim.standard_robot.StandardRobot`), as a robot's own JTC runs in ros2_control's real-time
loop: no DDS inside the control loop. Reads the latched ``task_instance``
(psl_msgs/TaskInstance) of its task and places that instance in its world (obstacles,
payload) without touching the arm. No services of its own, no /clock, no episodes: it steps
on the wall clock at the task's control rate from start to end: each tick measures, runs the
controller on the measurement and steps the physics, so a torque is always the answer to the
state of its own period; a tick late against the wall clock delays only when the state is
published (a loop behind catches up; one `MAX_BEHIND` behind skips the periods passed, the robot
standing still). A step that ends a period or more after its period's end is a deadline miss;
every `REPORT_PERIOD` s it reports on /diagnostics (for people and tools: ``psl bench graph``)
the periods run, the misses, the periods skipped and the
lateness of the steps (p99, max). Remap ``joint_states`` to a robot's name, e.g. ``--ros-args -r
joint_states:=/joint_states``.
"""
from __future__ import annotations

import gc
import math
import sys
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.exceptions import InvalidParameterValueException
from rclpy.node import Node
from sensor_msgs.msg import JointState

from psl_controller.follow_joint_trajectory import FollowJointTrajectoryServer
from psl_msgs.msg import TaskInstance
from psl_ros import names
from psl_ros.matching import MatchReport
from psl_ros.node_main import run_node
from psl_ros.parameters import check_update, declare
from psl_ros.qos import LATCHED, RELIABLE
from psl_ros.realtime import raise_priority, sleep_until
from psl_ros.stamps import time_msg
from psl_sim.standard_robot import StandardRobot
from psl_sim.standard_robot_parameters import StandardRobotParameters
from psl_task.task import TaskError, load_task

THROTTLE = 1.0      # s between two warnings of one kind
REPORT_PERIOD = 1.0     # s between two reports of the loop's timing on /diagnostics
SWITCH_INTERVAL = 0.05  # of a control period: how long another thread may hold the interpreter
MAX_BEHIND = 0.05       # s: a loop further behind the wall clock skips periods (else catches up)


class StandardRobotNode(Node):

    def __init__(self):
        super().__init__('standard_robot')
        self.add_on_set_parameters_callback(
            lambda params: check_update(self, StandardRobotParameters, params))
        try:
            self.parameters = declare(self, StandardRobotParameters)
        except InvalidParameterValueException as exc:   # one line from run_node, no traceback
            raise ValueError(str(exc)) from None
        self.robot = StandardRobot(self.parameters)
        self._lock = threading.Lock()       # the robot's world: the loop and task instances
        self.periods = 0                    # control periods since the start (run, skipped)
        self.deadline_misses = 0            # periods whose step ended a period or more late
        self.skipped = 0                    # periods skipped after a stall (MAX_BEHIND)
        # (stamp of the newest state, periods, deadline misses, skipped) as of its period,
        # replaced whole each period: a report reads counts that belong together
        self._counts = (0, 0, 0, 0)
        self._lateness: list[float] = []    # [s] end of each step minus its period's end,
                                            # since the last report (negative: in time)
        self._joint_state = JointState()
        self.matches = MatchReport(self)    # what its endpoints matched
        self.server = FollowJointTrajectoryServer(self, self.robot.controller,
                                                  ReentrantCallbackGroup(), self.robot.limits,
                                                  matches=self.matches)
        self.pub_joints = self.matches.create_publisher(JointState, names.JOINT_STATES,
                                                        RELIABLE)
        self.matches.create_subscription(TaskInstance, names.TASK_INSTANCE,
                                         self.on_task_instance, LATCHED)
        robot, p = self.robot, self.parameters
        law = robot.controller.law
        self.get_logger().info(
            f'standard robot: task {robot.arm.task.name!r} at {1.0 / robot.period:g} Hz; '
            f'joint_states {robot.names}; its JointTrajectoryController (effort) kp '
            f'{law.kp.tolist()} kd {law.kd.tolist()}; noise {p.position_noise:g} rad, '
            f'{p.velocity_noise:g} rad/s; latency {p.latency_periods} period(s); model error '
            f'{robot.model_error}')
        self.pub_diag = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 10)
        self.create_timer(REPORT_PERIOD, self._report)
        # the loop wakes every period and needs the interpreter at once: a thread of the
        # executor holding it would keep it up to Python's switch interval (5 ms) otherwise
        sys.setswitchinterval(SWITCH_INTERVAL * robot.period)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _report(self) -> None:
        """The loop's timing since the start (periods, misses, skipped periods, as of the
        newest state's stamp) and since the last report (lateness p99 and max) on
        /diagnostics."""
        lateness, self._lateness = self._lateness, []
        late = np.array(lateness) if lateness else np.zeros(1)
        stamp, periods, misses, skipped = self._counts
        values = {'periods': periods, 'deadline_misses': misses, 'skipped': skipped,
                  'stamp_ns': stamp,
                  'late_p99_us': f'{1e6 * np.percentile(late, 99):.1f}',
                  'late_max_us': f'{1e6 * late.max():.1f}'}
        self.pub_diag.publish(DiagnosticArray(status=[DiagnosticStatus(
            level=DiagnosticStatus.OK, name=f'{self.get_fully_qualified_name()}: loop',
            message=f'{periods} periods, {misses} deadline misses',
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]))

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
        """Each period: measure, publish the state, control and step; sleep to the next
        deadline. Behind by more than a period: the periods missed are counted and the loop
        goes on from now."""
        robot = self.robot
        period = robot.period
        scheduling = raise_priority(self.parameters.realtime_priority)
        self.get_logger().info(f'control loop: {scheduling}')
        gc.freeze()         # what exists now is never collected: a full collection stays short
        next_tick = time.perf_counter()
        js = self._joint_state
        js.name = list(robot.names)
        clock = self.get_clock()
        # the stamps are the robot's time, the instants its physics has reached: the wall
        # clock at the start plus the periods run (the wall clock read at each step would
        # add the loop's jitter to the measurements' times, not to the motion)
        base = clock.now().nanoseconds
        while not self._stop.is_set():
            stamp = base + robot.periods * robot.period_ns
            with self._lock:
                state, results = robot.step(stamp)
            js.header.stamp = time_msg(stamp)
            js.position = state.position.tolist()
            js.velocity = state.velocity.tolist()
            js.effort = state.effort.tolist()
            try:
                self.pub_joints.publish(js)
                self.server.deliver(results)
                self.server.publish_state(robot.controller.last)
            except Exception:   # noqa: BLE001 - the context ended under us (Ctrl-C)
                if not self.context.ok():
                    return
                raise
            next_tick += period                 # the end of this period
            late = time.perf_counter() - next_tick
            self.periods += 1
            self._lateness.append(late)
            if late > period:                   # the robot's time a period behind the wall's
                self.deadline_misses += 1
            if late > MAX_BEHIND:               # a stall: catching up would burst too long;
                skipped = math.ceil(late / period)  # the periods passed are skipped
                self.periods += skipped
                self.skipped += skipped
                self.get_logger().warning(
                    f'{late * 1e3:.1f} ms behind: {skipped} period(s) skipped ({self.skipped} '
                    'so far), the robot stood still', throttle_duration_sec=THROTTLE)
                next_tick += skipped * period
                base += skipped * robot.period_ns   # its time goes on from the next tick
            self._counts = (stamp, self.periods, self.deadline_misses, self.skipped)
            if late < 0.0:                      # else the next period at once: catching up
                sleep_until(next_tick, 0.0)

    def destroy_node(self):
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.server.destroy()
        super().destroy_node()


def main(args=None):
    run_node(StandardRobotNode, args, threads=4)    # a goal's execution waits for its result


if __name__ == '__main__':
    main()
