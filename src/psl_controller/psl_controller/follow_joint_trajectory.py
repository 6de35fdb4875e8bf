"""``control_msgs/action/FollowJointTrajectory`` served for a `TrajectoryController`: the
interface of ros2_control's JointTrajectoryController (JTC), so that psl's executor drives psl's
controller and a robot's own JTC alike.

What a node that runs a `TrajectoryController` adds with `FollowJointTrajectoryServer`:

* the action ``<name>/follow_joint_trajectory``: a goal is checked as JTC checks one
  (`goal_from_msg`: the controller's joints, points with strictly increasing times, all points
  with the same fields, finite values, the last point at rest, no effort unless the command
  interface is ``effort``, a stamped trajectory that ends in the past, tolerances by joint name)
  and against the arm's limits, whoever sends it (`psl_controller.goal_limits`: its size, its
  points and the interpolation between them inside the joint ranges, the velocity bound and
  the torque limits), and rejected, or accepted and handed to the controller (which preempts
  the active goal); its
  execution answers with the controller's result (``error_code``, ``error_string``), sends
  feedback (desired, actual, error; ``desired.time_from_start`` = the sample time from the
  trajectory's start) at ``action_monitor_rate``, and a cancel request holds the position;
* the read-only parameters JTC has that tell a client what it is driving: ``joints`` (the
  controller's joint order) and ``command_interfaces`` (``['effort']``);
* ``<name>/controller_state`` (control_msgs/JointTrajectoryControllerState: reference,
  feedback, error, output), published by `publish_state` from the control loop, only while
  someone subscribes.

The node calls `deliver` with the results `TrajectoryController.update` returns.

A refused goal is **rejected**, as JTC rejects a goal it cannot run: nothing changes (the
running goal goes on, nothing is kept for it), and the reason is one error line in the node's
log, which rclpy also publishes on ``/rosout`` (rcl_interfaces/Log, ``name`` the node's): the
action protocol gives a rejected goal no result to carry it. Accepting and then aborting with
``INVALID_GOAL`` and the reason in ``error_string`` would hand the words to the client, but an
accepted goal preempts the running one in JTC's semantics (a client that reads "accepted" as
"it runs" would be wrong), and every such goal would hold a thread and its result for
``RESULT_KEPT`` s; a client written for a robot's own JTC expects rejection.

Memory: rclpy hands a goal over as a Python object per point (about 0.65 kB a point of three
joints: 64 MB for 100,000 points), before any check can refuse it. Its points are released
once read (`release`: when the controller has taken the goal, or it is rejected; the goal
handle keeps the rest of its request for ``RESULT_KEPT`` s), and after a goal of
``TRIM_POINTS`` points or more the memory freed is handed back to the system (glibc's
``malloc_trim``), so the node's memory follows the goals it holds, not the largest it read.
"""
from __future__ import annotations

import array
import ctypes
import ctypes.util
import threading
import time

import numpy as np
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointTrajectoryControllerState
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.action import CancelResponse, GoalResponse
from rclpy.node import Node
from trajectory_msgs.msg import JointTrajectoryPoint

from psl_controller.goal_limits import GoalLimits
from psl_controller.trajectory_controller import (Goal, GoalRefused, Result, Snapshot,
                                                  Tolerances, TrajectoryController)
from psl_controller.trajectory_sampling import SampledTrajectory
from psl_ros import names
from psl_ros.action_server import ActionServer
from psl_ros.qos import RELIABLE
from psl_ros.stamps import duration_msg, time_msg, to_ns

ACTION, STATE = names.FOLLOW_JOINT_TRAJECTORY, names.CONTROLLER_STATE
MONITOR_RATE = 20.0     # Hz: JTC's action_monitor_rate default (feedback, cancels)
REPORTED = ('joints', 'command_interfaces')     # JTC's parameters a client reads
# s a goal's handle (with its request: a long trajectory is tens of thousands of Python
# objects) is kept after its result; rclpy's default, rclcpp's, is 15 min, and in a Python robot
# loop the cycle collector's full passes over 15 min of goals stalled the loop for 80-390 ms
# (the 10-DOF arm on the standard robot). A client asks for the result as the goal is accepted.
RESULT_KEPT = 10.0
FLOAT_EPS = float(np.finfo(np.float32).eps)     # JTC's "zero" for the last point's velocity
TRIM_POINTS = 10_000    # a goal this long hands the memory its message took back (malloc_trim)
try:                    # glibc's: freed memory the allocator keeps is returned to the system
    _malloc_trim = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6').malloc_trim
except (OSError, AttributeError):
    _malloc_trim = None


def goal_from_msg(msg: FollowJointTrajectory.Goal, joint_names: list[str], key,
                  defaults: Tolerances, limits: GoalLimits, effort_interface: bool = True,
                  newest_ns: int | None = None) -> Goal:
    """A controller `Goal` from an action goal (points reordered to `joint_names`), its
    trajectory clamped into `limits` where it is sampled between points; GoalRefused with the
    reason JTC would log for a goal it rejects, or the limit it breaks
    (`psl_controller.goal_limits`)."""
    trajectory = msg.trajectory
    names = list(trajectory.joint_names)
    if msg.multi_dof_trajectory.joint_names or msg.multi_dof_trajectory.points:
        raise GoalRefused('this controller has no multi-DOF joints')
    if not names:
        raise GoalRefused('empty joint names on the incoming trajectory')
    if sorted(names) != sorted(joint_names):
        raise GoalRefused(f"joints {names} do not match the controller's joints {joint_names}")
    points = trajectory.points
    if not points:
        raise GoalRefused('empty trajectory received')
    limits.check_size(len(points))
    times = np.array([to_ns(p.time_from_start) for p in points], dtype=np.int64)
    if times[0] < 0 or np.any(np.diff(times) <= 0):
        raise GoalRefused('the times of the points must be >= 0 and strictly increasing')
    order = [names.index(name) for name in joint_names]
    n = len(names)

    def column(field: str) -> np.ndarray | None:
        rows = [getattr(p, field) for p in points]
        if all(len(r) == 0 for r in rows):
            return None
        if any(len(r) != n for r in rows):
            raise GoalRefused(f'every point needs {n} {field} (or none of them any)')
        if all(type(r) is array.array and r.typecode == 'd' for r in rows):    # rclpy's
            values = np.frombuffer(b''.join(rows), dtype=float).reshape(len(rows), n)
        else:
            values = np.asarray(rows, dtype=float)
        table = values[:, order]
        if not np.all(np.isfinite(table)):
            raise GoalRefused(f'the trajectory\'s {field} hold NaN or inf')
        return table

    positions, velocities = column('positions'), column('velocities')
    accelerations, effort = column('accelerations'), column('effort')
    if positions is None:
        raise GoalRefused('the points need positions')
    if effort is not None and not effort_interface:
        raise GoalRefused("trajectories with effort fields are only supported for controllers "
                          "using the 'effort' command interface")
    if accelerations is not None and velocities is None:
        raise GoalRefused('accelerations need velocities')
    if velocities is not None and np.any(np.abs(velocities[-1]) > FLOAT_EPS):
        j = int(np.argmax(np.abs(velocities[-1])))
        raise GoalRefused(f'velocity of the last point of joint {joint_names[j]} is not zero: '
                          f'{velocities[-1, j]:.15f}')
    start = to_ns(trajectory.header.stamp)
    if start and newest_ns is not None and start + int(times[-1]) < newest_ns:
        raise GoalRefused(f'the trajectory stamped {start * 1e-9:.3f} s ends in the past '
                          f'(the newest state is at {newest_ns * 1e-9:.3f} s)')
    limits.check_timing(start, int(times[-1]), newest_ns)

    def by_name(tolerances) -> dict[str, tuple[float, float]]:
        return {t.name: (t.position, t.velocity) for t in tolerances}
    if msg.component_path_tolerance or msg.component_goal_tolerance:
        raise GoalRefused('component tolerances are for multi-DOF joints, which this '
                          'controller has none of')
    tolerances = defaults.resolved(joint_names, by_name(msg.path_tolerance),
                                   by_name(msg.goal_tolerance),
                                   to_ns(msg.goal_time_tolerance) * 1e-9)
    try:
        sampled = SampledTrajectory(times, positions, velocities, effort, accelerations)
    except ValueError as exc:
        raise GoalRefused(str(exc)) from None
    limits.check(sampled, times, positions, velocities, effort)
    return Goal(key, limits.bound(sampled), start, tolerances)


def release(msg: FollowJointTrajectory.Goal) -> None:
    """Let go of a goal's points once read (module docstring, "Memory"); after a long goal,
    hand the memory they took back to the system."""
    n = len(msg.trajectory.points)
    msg.trajectory.points = []
    if n >= TRIM_POINTS and _malloc_trim is not None:
        _malloc_trim(0)


def point_msg(values, time_from_start_ns: int | None = None) -> JointTrajectoryPoint:
    """A JointTrajectoryPoint of a TrajectorySample (or any (q, qd, qdd, effort) tuple)."""
    point = JointTrajectoryPoint()
    for field, value in zip(('positions', 'velocities', 'accelerations', 'effort'), values):
        if value is not None:
            setattr(point, field, np.asarray(value, dtype=float).tolist())
    if time_from_start_ns is not None:     # negative before the start: sec < 0 <= nanosec
        point.time_from_start = duration_msg(time_from_start_ns)
    return point


class FollowJointTrajectoryServer:
    """Serves a `TrajectoryController` to FollowJointTrajectory clients (module docstring).

    Args:
        node: the node that holds the action (``<node>/follow_joint_trajectory``), the
            parameters and the state topic.
        controller: the controller the node's loop updates.
        callback_group: a reentrant group (goals execute while others arrive).
        limits: what a goal may ask of the arm (`psl_controller.goal_limits`).
        effort_interface: whether goals may carry effort (the command interface).
        monitor_rate: [Hz] of the feedback (JTC's action_monitor_rate).
        matches: the node's `psl_ros.matching.MatchReport`, which then reports the state
            publisher's matches.
    """

    def __init__(self, node: Node, controller: TrajectoryController, callback_group,
                 limits: GoalLimits, effort_interface: bool = True,
                 monitor_rate: float = MONITOR_RATE, matches=None):
        if list(limits.joint_names) != list(controller.joint_names):
            raise ValueError(f'the limits are of joints {list(limits.joint_names)}, the '
                             f'controller drives {controller.joint_names}')
        self.node, self.controller, self.limits = node, controller, limits
        self.effort_interface = effort_interface
        self.monitor_period = 1.0 / monitor_rate
        self._results: dict = {}            # goal key -> Result, until its execution ends
        self._cv = threading.Condition()
        self._parsed: dict[int, tuple] = {}     # id(goal msg) -> (msg, Goal or GoalRefused)
        for name, value in zip(REPORTED, (list(controller.joint_names),
                                          ['effort' if effort_interface else 'position'])):
            node.declare_parameter(name, value, ParameterDescriptor(
                read_only=True, description="JTC's parameter: what this controller drives"))
        self.state_publisher = (node if matches is None else matches).create_publisher(
            JointTrajectoryControllerState, f'~/{STATE}', RELIABLE)
        self._state = JointTrajectoryControllerState(joint_names=list(controller.joint_names))
        self._server = ActionServer(
            node, FollowJointTrajectory, f'~/{ACTION}', execute_callback=self._execute,
            goal_callback=self._on_goal, before_answer=self._take,
            dropped=lambda handle: self.deliver(self.controller.cancel(
                bytes(handle.goal_id.uuid))),
            cancel_callback=self._on_cancel, callback_group=callback_group,
            result_timeout=RESULT_KEPT)

    def destroy(self) -> None:
        self._server.destroy()

    # -- results --------------------------------------------------------------------------
    def deliver(self, results: list[Result]) -> None:
        """Results of the controller's goals (from `update`, `cancel`, `stop`)."""
        if results:
            with self._cv:
                for result in results:
                    self._results[result.key] = result
                self._cv.notify_all()

    # -- the action -----------------------------------------------------------------------
    def _parse(self, msg) -> Goal:
        key = bytes(0)
        last = self.controller.last
        return goal_from_msg(msg, self.controller.joint_names, key, self.controller.defaults,
                             self.limits, self.effort_interface,
                             None if last is None else last.t_ns)

    def _on_goal(self, msg) -> GoalResponse:
        try:
            goal = self._parse(msg)
        except GoalRefused as exc:
            self.node.get_logger().error(f'goal rejected: {exc}')
            release(msg)
            return GoalResponse.REJECT
        if len(self._parsed) > 16:      # goals accepted here but dropped by the server
            self._parsed.clear()
        self._parsed[id(msg)] = (msg, goal)
        return GoalResponse.ACCEPT

    def _take(self, goal_handle) -> None:
        """An accepted goal goes to the controller before the client hears it was accepted
        (JTC takes it right after): a client that then starts the robot's clock (psl's
        lockstep simulator) finds it in place."""
        msg = goal_handle.request
        kept = self._parsed.pop(id(msg), None)
        goal = kept[1] if kept is not None and kept[0] is msg else self._parse(msg)
        key = bytes(goal_handle.goal_id.uuid)
        goal = Goal(key, goal.trajectory, goal.start_ns, goal.tolerances)
        self.deliver(self.controller.submit(goal))
        release(msg)

    def _on_cancel(self, goal_handle) -> CancelResponse:
        self.deliver(self.controller.cancel(bytes(goal_handle.goal_id.uuid)))
        return CancelResponse.ACCEPT

    def _execute(self, goal_handle) -> FollowJointTrajectory.Result:
        key = bytes(goal_handle.goal_id.uuid)
        feedback = FollowJointTrajectory.Feedback(joint_names=list(self.controller.joint_names))
        sent = None
        with self._cv:
            while key not in self._results:
                # the first feedback as soon as the goal is served (or waits for its start):
                # a client learns at once whether it came in time
                self._cv.wait(timeout=self.monitor_period if sent else 0.005)
                if key in self._results:
                    break
                last = self.controller.last
                if last is not None and last.key == key and last is not sent:
                    sent = last
                    self._fill_feedback(feedback, last)
                    goal_handle.publish_feedback(feedback)
            result = self._results.pop(key)
        if result.canceled:
            deadline = time.monotonic() + 1.0       # the cancel request's state transition
            while not goal_handle.is_cancel_requested and time.monotonic() < deadline:
                time.sleep(0.001)
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
            else:
                goal_handle.abort()
        elif result.error_code == 0:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return FollowJointTrajectory.Result(error_code=result.error_code,
                                            error_string=result.error_string)

    @staticmethod
    def _fill_feedback(feedback, last: Snapshot) -> None:
        feedback.header.stamp = time_msg(last.t_ns)
        feedback.desired = point_msg(last.desired, last.time_from_start_ns)
        feedback.actual = point_msg((last.q, last.qd, None, None), last.time_from_start_ns)
        error, error_d = last.error
        feedback.error = point_msg((error, error_d, None, None), last.time_from_start_ns)

    # -- controller_state -----------------------------------------------------------------
    def publish_state(self, last: Snapshot) -> None:
        """The controller's state (from the control loop), if someone subscribes."""
        if not self.state_publisher.get_subscription_count():
            return
        state = self._state
        state.header.stamp = time_msg(last.t_ns)
        state.reference = point_msg(last.desired, last.time_from_start_ns)
        state.feedback = point_msg((last.q, last.qd, None, None), last.time_from_start_ns)
        error, error_d = last.error
        state.error = point_msg((error, error_d, None, None))
        state.output = point_msg((None, None, None, last.torque))
        self.state_publisher.publish(state)
