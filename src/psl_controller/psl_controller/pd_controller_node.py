"""The controller node: psl's JointTrajectoryController for a robot that takes torques.

A `psl_controller.trajectory_controller.TrajectoryController` (JTC's semantics, the compliant
law ``u = Kp (q_ref - q) + Kd (qd_ref - qd) + u_ffwd``, clipped to the torque limits) served as
``control_msgs/action/FollowJointTrajectory`` on ``pd_controller/follow_joint_trajectory``
(`psl_controller.follow_joint_trajectory`: the effort interface; ``joints`` and
``command_interfaces`` parameters; ``~/controller_state``; goals past the arm's limits or its
size bounds rejected: `psl_controller.goal_limits`). It answers every ``joint_states``
message with one ``effort_command`` (std_msgs/Float64MultiArray in ``command_joints`` order: an
effort forward_command_controller's joints; by default the task's order). The state is read by
joint name (`psl_task.joint_selection`: any order, extra joints ignored; a state that lacks a
task joint gets no command and a throttled error naming it). The state's stamp is the
controller's clock: a goal's start and its trajectory's times are on the robot's clock.

It is the controller of psl's simulator (lockstep: the simulator waits for the command that
answers each state; or the wall clock) and of a robot that offers only an effort
forward_command_controller. For the latter the watchdog is on by default (``state_timeout``;
armed by the first state): when no joint state came for that long (the wall clock), the
active goal aborts with the
reason and the controller commands ``on_state_loss`` (zero torque, or the last torque again)
every control period until states come again; then it holds the position of the first new
state. psl's simulator pauses between episodes: its graph turns the watchdog off.
"""
from __future__ import annotations

import threading
import time

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from psl_controller.follow_joint_trajectory import FollowJointTrajectoryServer
from psl_controller.goal_limits import limits_of
from psl_controller.parameters import ControllerParameters
from psl_controller.pd_law import PDLaw, law_for
from psl_controller.trajectory_controller import TrajectoryController
from psl_ros import names
from psl_ros.hot_path import HotPath
from psl_ros.matching import MatchReport
from psl_ros.node_main import run_node
from psl_ros.parameters import check_update, declare
from psl_ros.qos import NEWEST, RELIABLE
from psl_ros.realtime import raise_priority
from psl_ros.stamps import to_ns
from psl_task.arm_model import joint_names_of
from psl_task.joint_selection import JointSelection
from psl_task.task import load_task

LAW_PARAMETERS = ('kp', 'kd', 'torque_limit')


class PDController(Node):

    def __init__(self):
        super().__init__('pd_controller')
        self.parameters = declare(self, ControllerParameters)
        task = load_task(self.parameters.task)
        self.default_law = law_for(task)
        self.n_joints = self.default_law.n_joints
        self.period = task.control_period
        self.joint_names = joint_names_of(task)       # the task's joints, the command order
        self.selection = JointSelection(self.joint_names)
        self.command_order = self._command_order(self.parameters.command_joints)
        self.controller = TrajectoryController(self.joint_names, self._law(
            {name: getattr(self.parameters, name) for name in LAW_PARAMETERS}))
        self.add_on_set_parameters_callback(self.on_set_parameters)

        # watchdog: the wall time of the last state, and whether their loss is reported
        self._state_lock = threading.Lock()
        self._last_state: float | None = None   # armed by the first state: none yet, none lost
        self._lost = False
        self._last_torque = np.zeros(self.n_joints)
        self.matches = MatchReport(self)        # what the loop's endpoints matched
        p = self.parameters
        self.server = FollowJointTrajectoryServer(
            self, self.controller, ReentrantCallbackGroup(),
            limits_of(task, p.max_points, p.max_duration, p.max_velocity), matches=self.matches)
        self.pub_command = self.matches.create_publisher(Float64MultiArray, names.EFFORT_COMMAND,
                                                         RELIABLE)
        self._command = Float64MultiArray()     # refilled every step (publish copies it)
        # the hot path's thread inherits the scheduling of the thread that starts it
        scheduling = raise_priority(self.parameters.realtime_priority)
        self.hot_path = HotPath(self)
        self.state_timeout = self.parameters.state_timeout
        # a robot on the wall clock (the watchdog on): answer the newest state, never work
        # through a backlog of old ones (a late answer is stale; psl's simulator waits for each)
        self.matches.subscribe(self.hot_path, JointState, names.JOINT_STATES, self.on_state,
                               NEWEST if self.state_timeout > 0.0 else RELIABLE)
        self.hot_path.start()
        self.watchdog = (self.create_timer(self.period, self.on_watchdog)
                         if self.state_timeout > 0.0 else None)
        law = self.controller.law
        self.get_logger().info(
            f'JointTrajectoryController (effort), kp={law.kp.tolist()} kd={law.kd.tolist()} '
            f'limits={law.torque_low.tolist()}..{law.torque_high.tolist()}, watchdog '
            f'{f"{self.state_timeout:g} s" if self.state_timeout else "off"}; {scheduling}')

    def _law(self, values: dict) -> PDLaw:
        """The law with the given parameter values ([0.0] = the task's); ValueError if one is
        not n_joints finite values >= 0."""
        chosen = {}
        for name, value in values.items():
            value = np.asarray(value, dtype=float).ravel()
            if value.size == 1 and value[0] == 0.0:
                continue
            if value.size != self.n_joints or not np.all(np.isfinite(value)) \
                    or np.any(value < 0):
                raise ValueError(f'{name} needs {self.n_joints} finite values >= 0')
            chosen[name] = value
        d = self.default_law
        limit = chosen.get('torque_limit')
        return PDLaw(chosen.get('kp', d.kp), chosen.get('kd', d.kd),
                     d.torque_low if limit is None else -limit,
                     d.torque_high if limit is None else limit)

    def _command_order(self, command_joints) -> np.ndarray:
        """Index into the task's joints of each effort_command entry (ValueError unless
        `command_joints` is a permutation of the task's joints, or [''])."""
        if tuple(command_joints) == ('',):
            return np.arange(self.n_joints)
        if sorted(command_joints) != sorted(self.joint_names):
            raise ValueError(f'command_joints {list(command_joints)} must name each of the '
                             f"task's joints {self.joint_names} once")
        return np.array([self.joint_names.index(name) for name in command_joints])

    def on_set_parameters(self, params) -> SetParametersResult:
        checked = check_update(self, ControllerParameters, params)
        if not checked.successful:
            return checked
        values = {name: self.get_parameter(name).value for name in LAW_PARAMETERS}
        values.update({p.name: p.value for p in params if p.name in LAW_PARAMETERS})
        try:
            law = self._law(values)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.controller.law = law       # one object: a step sees the old law or the new one
        return SetParametersResult(successful=True)

    def on_state(self, msg: JointState) -> None:
        with self._state_lock:
            self._last_state = time.monotonic()
            if self._lost:
                self._lost = False
                self.get_logger().warning('joint states come again: holding the position')
        try:
            q = self.selection.pick(msg.name, msg.position)
            qd = self.selection.pick(msg.name, msg.velocity)
        except ValueError as exc:            # MissingJoints too
            self.get_logger().error(f'no command: {exc}', throttle_duration_sec=1.0)
            return
        if q.shape != (self.n_joints,) or qd.shape != q.shape:
            self.get_logger().warning('no command: joint_states lacks positions or velocities',
                                      throttle_duration_sec=1.0)
            return
        if not (np.isfinite(q).all() and np.isfinite(qd).all()):
            self.get_logger().warning('no command: joint_states holds NaN or inf',
                                      throttle_duration_sec=1.0)
            return
        torque, results = self.controller.update(to_ns(msg.header.stamp), q, qd)
        self._last_torque = torque
        command = self._command
        command.data = torque[self.command_order].tolist()
        self.pub_command.publish(command)
        self.server.deliver(results)
        self.server.publish_state(self.controller.last)

    def on_watchdog(self) -> None:
        """Every control period: states lost for state_timeout? Then the goal aborts (once)
        and on_state_loss is commanded."""
        timeout = self.state_timeout
        with self._state_lock:
            if self._last_state is None:
                return                  # no state yet: the robot's brakes hold it, not psl
            silent = time.monotonic() - self._last_state
            if silent <= timeout:
                return
            first, self._lost = not self._lost, True
        mode = self.get_parameter('on_state_loss').value
        if first:
            reason = (f'joint states stopped: none for {silent:.3f} s (state_timeout '
                      f'{timeout:g} s); the controller aborted the goal and commands '
                      f'{"zero torque" if mode == "zero" else "the last torque"}')
            self.get_logger().error(reason)
            self.server.deliver(self.controller.stop(reason))
        torque = np.zeros(self.n_joints) if mode == 'zero' else self._last_torque
        self.pub_command.publish(Float64MultiArray(data=torque[self.command_order].tolist()))

    def destroy_node(self):
        self.hot_path.stop()
        self.server.destroy()
        super().destroy_node()


def main(args=None):
    run_node(PDController, args, threads=4)    # a goal's execution waits for its result


if __name__ == '__main__':
    main()
