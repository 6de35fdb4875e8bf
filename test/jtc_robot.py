"""A robot psl does not simulate, for the tests: MuJoCo physics on the wall clock with its own
JointTrajectoryController, as a ros2_control arm offers it, written from the jazzy branch of
ros2_controllers (joint_trajectory_controller.cpp, trajectory.cpp, tolerances.hpp). Nothing
of psl's is imported; psl_msgs' TaskInstance only with --payload.

- /joint_states (sensor_msgs/JointState, node joint_state_broadcaster) every period: the
  robot's joint order (--joints), then --extra-joint (0, 0, 0); wall-clock stamps; Gaussian
  noise on position and velocity; effort = the torque applied in the period before.
- /NAME/follow_joint_trajectory (control_msgs/action/FollowJointTrajectory, node NAME) with
  JTC's parameters (joints, command_interfaces, state_interfaces, gains.<joint>.p/d,
  constraints.*, allow_nonzero_velocity_at_trajectory_end, action_monitor_rate), feedback at
  action_monitor_rate and ~/controller_state each period while someone subscribes.
- --interface effort: u = kp e + kd e' + effort (JTC's PID adapter, feed-forward from the point),
  clipped to the model's torque limits. --interface position: the commanded positions go to
  the robot's own stiff position servo; goals that carry effort are rejected.
- One thread steps the physics and the controller, with real-time scheduling where allowed
  (as ros2_control's controller manager); goals, cancels and feedback are rclpy callbacks in
  other threads that hand over to it under a lock.
- The physics is not the model's: masses and inertias times --mass-scale, joint damping
  +0.3 N m s/rad and friction +0.05 N m; a command acts --latency-periods periods late. Brakes
  hold the arm at --start until the first command. --payload BODY:INDEX: the mass of BODY
  follows tau[INDEX] of the latched /task_instance (an operator loading the arm). SIGUSR1 stops
  the joint states for --silence seconds (a cable pulled); physics and controller go on.

Left out of JTC: speed scaling, multi-DOF and partial-joint goals, angle wraparound, the
~/joint_trajectory topic, open-loop mode, integral gains, velocity feed-forward,
decelerate_on_cancel, cmd_timeout, the query_state service; and the deviations marked
"JTC:" below.

    python jtc_robot.py --model M.xml --joints j3 j2 j1 --start 0.1 0.2 0.3 \
        --interface effort --controller arm_controller --kp 100 200 300 --kd 5 12 20
"""
import argparse
import bisect
import math
import os
import signal
import sys
import threading
import time
from collections import deque, namedtuple

import mujoco
import numpy as np
import rclpy
from builtin_interfaces.msg import Duration, Time
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointTrajectoryControllerState
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectoryPoint

Result = FollowJointTrajectory.Result
FLOAT_EPSILON = float(np.finfo(np.float32).eps)   # JTC's std::numeric_limits<float>::epsilon()
SERVO_BANDWIDTH = 0.25      # position servo: natural frequency times the period (rad)
HOLD = 'hold'               # the loop's order to hold the measured positions

Point = namedtuple('Point', 'p v a e')      # (n,) arrays; v, a, e None where the point has none


def seconds(duration) -> float:
    return duration.sec + duration.nanosec * 1e-9


def time_msg(ns: int) -> Time:
    return Time(sec=ns // 10**9, nanosec=ns % 10**9)


def duration_msg(s: float) -> Duration:
    ns = round(s * 1e9)
    return Duration(sec=ns // 10**9, nanosec=ns % 10**9)


def segment(a: Point, b: Point, T: float):
    """trajectory.cpp interpolate_between_points from a to b, T s apart, as polynomials in the
    time since a: positions (6, n: coefficients of s^0..s^5) linear, cubic (both points have
    velocities) or quintic (and accelerations); effort (2, n) linear (absent counts 0)."""
    zero = np.zeros_like(a.p)
    ea, eb = (zero if a.e is None else a.e), (zero if b.e is None else b.e)
    p0, p1 = a.p, b.p
    if a.v is not None and b.v is not None and a.a is not None and b.a is not None:
        v0, v1, a0, a1 = a.v, b.v, a.a, b.a
        c3 = (-20 * p0 + 20 * p1 - 3 * a0 * T**2 + a1 * T**2 - 12 * v0 * T - 8 * v1 * T) \
            / (2 * T**3)
        c4 = (30 * p0 - 30 * p1 + 3 * a0 * T**2 - 2 * a1 * T**2 + 16 * v0 * T + 14 * v1 * T) \
            / (2 * T**4)
        c5 = (-12 * p0 + 12 * p1 - a0 * T**2 + a1 * T**2 - 6 * v0 * T - 6 * v1 * T) \
            / (2 * T**5)
        c = [p0, v0, 0.5 * a0, c3, c4, c5]
    elif a.v is not None and b.v is not None:
        v0, v1 = a.v, b.v
        c = [p0, v0, (-3 * p0 + 3 * p1 - 2 * v0 * T - v1 * T) / T**2,
             (2 * p0 - 2 * p1 + v0 * T + v1 * T) / T**3, zero, zero]
    else:
        # JTC: points with accelerations but without velocities get all-zero samples (no
        # branch of interpolate_between_points takes them); here they are linear
        c = [p0, (p1 - p0) / T, zero, zero, zero, zero]
    return np.array(c), np.array([ea, (eb - ea) / T])


def evaluate(coefficients, s: float) -> Point:
    """A segment's point s s after its start (0 <= s < T: sample() never asks for another;
    trajectory.cpp holds the segment's ends there)."""
    c, e = coefficients
    s2, s3 = s * s, s * s * s
    p, v, a = np.array([[1.0, s, s2, s3, s2 * s2, s3 * s2],
                        [0.0, 1.0, 2 * s, 3 * s2, 4 * s3, 5 * s2 * s2],
                        [0.0, 0.0, 2.0, 6 * s, 12 * s2, 20 * s3]]) @ c
    return Point(p, v, a, e[0] + e[1] * s)


class Trajectory:
    """A trajectory in the controller's joint order (trajectory.cpp's Trajectory): `points` at
    `t` s after `start_ns` (0: start at the first sample); `goal` the action goal it serves
    (None: a hold)."""

    def __init__(self, points: list, t: list, start_ns: int = 0, goal=None, tolerances=None):
        self.points, self.t, self.start_ns = points, list(t), start_ns
        self.goal, self.tolerances = goal, tolerances
        self.t_before = None        # when it was first sampled (s after the start)
        self.segments = {}          # i: segment from point i to i + 1 (-1: from the state)
        p, v, a, e = points[-1]
        zero = np.zeros_like(p)
        self.last = Point(p, zero if v is None else v, zero if a is None else a,
                          zero if e is None else e)

    def begin(self, now_ns: int, q: np.ndarray, qd: np.ndarray, effort: np.ndarray) -> None:
        """The first sample (set_point_before_trajectory_msg): the measured state (with the
        last effort command, as JTC reads it from the command interface) is the point the
        trajectory starts from; a trajectory stamped 0 starts now."""
        if self.start_ns == 0:
            self.start_ns = now_ns
        self.t_before = (now_ns - self.start_ns) * 1e-9
        first = self.points[0]
        if self.t_before < self.t[0]:
            before = Point(q, qd if first.v is not None else None,
                           np.zeros_like(q) if first.a is not None else None, effort)
            self.segments[-1] = segment(before, first, self.t[0] - self.t_before)

    def sample(self, t: float) -> tuple[Point, bool]:
        """The point at t s after the start, and whether t is before the last point."""
        if t < self.t[0]:       # from the state at the first sample to the first point
            return evaluate(self.segments[-1], t - self.t_before), True
        if t >= self.t[-1]:     # played out: the last point, absent fields zero
            return self.last, False
        i = bisect.bisect_right(self.t, t) - 1
        if i not in self.segments:
            self.segments[i] = segment(self.points[i], self.points[i + 1],
                                       self.t[i + 1] - self.t[i])
        return evaluate(self.segments[i], t - self.t[i]), True


class Goal:
    """An accepted action goal, between the action server's threads and the loop."""

    def __init__(self, handle):
        self.handle, self.done, self.outcome = handle, threading.Event(), None


class JointTrajectoryController(Node):
    """JTC's action interface and its update(), run by the robot's loop."""

    def __init__(self, name: str, joints: list, interface: str, kp, kd, period: float):
        super().__init__(name)
        self.joints, self.n, self.period = list(joints), len(joints), period
        self.effort = interface == 'effort'
        fixed = ParameterDescriptor(read_only=True)
        self.declare_parameter('joints', self.joints, fixed)
        self.declare_parameter('command_interfaces', [interface], fixed)
        self.declare_parameter('state_interfaces', ['position', 'velocity'], fixed)
        self.declare_parameter('action_monitor_rate', 20.0, fixed)
        self.declare_parameter('allow_nonzero_velocity_at_trajectory_end', False)
        self.declare_parameter('constraints.goal_time', 0.0)
        self.declare_parameter('constraints.stopped_velocity_tolerance', 0.01)
        for j in self.joints:
            self.declare_parameter(f'constraints.{j}.trajectory', 0.0)
            self.declare_parameter(f'constraints.{j}.goal', 0.0)
        self.kp, self.kd = np.asarray(kp, float), np.asarray(kd, float)
        if self.effort:
            for j, p, d in zip(self.joints, self.kp, self.kd):
                self.declare_parameter(f'gains.{j}.p', float(p))
                self.declare_parameter(f'gains.{j}.d', float(d))
        self.add_on_set_parameters_callback(self.on_set_gains)

        self.lock = threading.Lock()
        self.inbox = None       # a Trajectory or HOLD for the loop
        self.active = None      # the Goal whose trajectory runs (or is in the inbox)
        self.accepted = {}      # goal id: Goal, accepted and not yet executing
        self.traj = None        # the loop's trajectory; None: not commanded yet
        self.command = np.zeros(self.n)     # the last output (effort or position)
        self.snapshot = None    # the loop's latest sample, for feedback
        group = ReentrantCallbackGroup()
        ActionServer(self, FollowJointTrajectory, f'{name}/follow_joint_trajectory',
                     execute_callback=self.execute, goal_callback=self.on_goal,
                     handle_accepted_callback=self.on_accepted,
                     cancel_callback=self.on_cancel, callback_group=group,
                     result_timeout=10)    # s; rclcpp's 15 min of goals stalls Python's gc
        self.state_pub = self.create_publisher(JointTrajectoryControllerState,
                                               '~/controller_state', 10)
        self.create_timer(1.0 / self.get_parameter('action_monitor_rate').value,
                          self.send_feedback, callback_group=group)

    # -- parameters -------------------------------------------------------------------------
    def on_set_gains(self, params) -> SetParametersResult:
        kp, kd = self.kp.copy(), self.kd.copy()
        for p in params:
            name = p.name.split('.')
            if name[0] == 'gains' and len(name) == 3:
                if not math.isfinite(p.value):
                    return SetParametersResult(successful=False, reason=f'{p.name}: not finite')
                (kp if name[2] == 'p' else kd)[self.joints.index(name[1])] = p.value
        self.kp, self.kd = kp, kd           # JTC updates its PIDs in the next update()
        return SetParametersResult(successful=True)

    def default_tolerances(self):
        """tolerances.hpp get_segment_tolerances(params): path and goal (n, 3: position,
        velocity, acceleration; 0 = not checked) and the goal time tolerance."""
        get = lambda name: self.get_parameter(name).value      # noqa: E731
        path, goal = np.zeros((self.n, 3)), np.zeros((self.n, 3))
        path[:, 0] = [get(f'constraints.{j}.trajectory') for j in self.joints]
        goal[:, 0] = [get(f'constraints.{j}.goal') for j in self.joints]
        goal[:, 1] = get('constraints.stopped_velocity_tolerance')
        return path, goal, get('constraints.goal_time')

    def tolerances(self, request):
        """tolerances.hpp get_segment_tolerances(goal): a goal's value > 0 replaces the
        default, 0 keeps it, -1 erases it; any other value or an unknown joint: the defaults.
        Returned as (path, goal) thresholds with inf where nothing is checked, goal_time."""
        defaults = self.default_tolerances()

        def resolve(default, value):
            if value > 0.0:
                return value
            if abs(value + 1.0) < FLOAT_EPSILON:
                return 0.0
            if value < 0.0:
                raise ValueError(value)
            return default
        try:
            path, goal = defaults[0].copy(), defaults[1].copy()
            goal_time = resolve(defaults[2], seconds(request.goal_time_tolerance))
            for given, table, default in ((request.path_tolerance, path, defaults[0]),
                                          (request.goal_tolerance, goal, defaults[1])):
                for tol in given:
                    i = self.joints.index(tol.name)
                    table[i] = [resolve(d, x) for d, x in zip(
                        default[i], (tol.position, tol.velocity, tol.acceleration))]
        except ValueError as e:
            self.get_logger().error(f'illegal tolerance in the goal ({e}): default tolerances')
            path, goal, goal_time = defaults
        inf = lambda x: np.where(x > 0.0, x, np.inf)            # noqa: E731
        return inf(path), inf(goal), goal_time

    # -- the action ---------------------------------------------------------------------------
    def invalid(self, traj) -> str | None:
        """validate_trajectory_msg: why a trajectory is refused, or None."""
        if sorted(traj.joint_names) != sorted(self.joints):
            return "Joints on incoming trajectory don't match the controller joints."
        if not traj.points:
            return 'Empty trajectory received.'
        last = traj.points[-1]
        if (not self.get_parameter('allow_nonzero_velocity_at_trajectory_end').value
                and any(abs(v) > FLOAT_EPSILON for v in last.velocities)):
            return 'Velocity of last trajectory point is not zero'
        start = traj.header.stamp.sec * 10**9 + traj.header.stamp.nanosec
        end = start + round(seconds(last.time_from_start) * 1e9)
        if start != 0 and end < self.get_clock().now().nanoseconds:
            return 'Received trajectory with non-zero start time that ends in the past'
        times = [seconds(p.time_from_start) for p in traj.points]
        if any(b <= a for a, b in zip(times, times[1:])):
            return 'Time between points is not strictly increasing'
        for i, p in enumerate(traj.points):
            if len(p.positions) != self.n or any(
                    len(f) not in (0, self.n) for f in (p.velocities, p.accelerations)):
                return f'Mismatch between joint_names size and a field at point #{i}.'
            if p.effort and not self.effort:
                return ('Trajectories with effort fields are only supported for controllers '
                        "using the 'effort' command interface.")
            # JTC: neither checks the size of effort nor that values are finite
            if p.effort and len(p.effort) != self.n:
                return f'Mismatch between joint_names size and effort at point #{i}.'
            if not np.all(np.isfinite(np.concatenate(
                    [p.positions, p.velocities, p.accelerations, p.effort]))):
                return f'A value at point #{i} is not finite.'
        return None

    def on_goal(self, request) -> GoalResponse:
        self.get_logger().info('Received new action goal')
        reason = self.invalid(request.trajectory)
        if reason is not None:
            self.get_logger().error(reason)
            return GoalResponse.REJECT
        self.get_logger().info('Accepted new action goal')
        return GoalResponse.ACCEPT

    def on_accepted(self, handle) -> None:
        """goal_accepted_callback: the goal preempts the active one; its trajectory, sorted
        into the controller's joint order, goes to the loop."""
        msg = handle.request.trajectory
        order = [list(msg.joint_names).index(j) for j in self.joints]
        field = lambda f: np.asarray(f, float)[order] if len(f) else None  # noqa: E731
        points = [Point(field(p.positions), field(p.velocities), field(p.accelerations),
                        field(p.effort)) for p in msg.points]
        goal = Goal(handle)
        traj = Trajectory(points, [seconds(p.time_from_start) for p in msg.points],
                          msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec, goal,
                          self.tolerances(handle.request))
        with self.lock:
            if self.active is not None:
                self.finish(self.active, 'aborted', Result.INVALID_GOAL,
                            'Current goal preempted by new incoming action.')
            self.active, self.inbox = goal, traj
            self.accepted[bytes(handle.goal_id.uuid)] = goal
        handle.execute()

    def on_cancel(self, handle) -> CancelResponse:
        self.get_logger().info('Got request to cancel goal')
        with self.lock:
            if self.active is not None and self.active.handle == handle:
                self.finish(self.active, 'canceled', Result.SUCCESSFUL, '')
                self.inbox = HOLD
        return CancelResponse.ACCEPT

    def finish(self, goal: Goal, outcome: str, code: int, text: str) -> None:
        """The goal's end (under the lock): its execute callback reports it."""
        goal.outcome = (outcome, code, text)
        goal.done.set()
        if self.active is goal:
            self.active = None

    def execute(self, handle) -> Result:
        """Waits (in an executor thread) for what the loop, a preemption or a cancel made of
        the goal, and reports it."""
        with self.lock:
            goal = self.accepted.pop(bytes(handle.goal_id.uuid))
        goal.done.wait()
        outcome, code, text = goal.outcome
        if outcome == 'canceled':
            # the cancel callback ran; the server marks the goal CANCELING right after it
            deadline = time.monotonic() + 5.0
            while not handle.is_cancel_requested and time.monotonic() < deadline:
                time.sleep(0.001)
            handle.canceled()
        elif outcome == 'succeeded':
            handle.succeed()
        else:
            handle.abort()
        return Result(error_code=code, error_string=text)

    def send_feedback(self) -> None:
        """The feedback of the active goal: the loop's latest sample (runNonRealtime)."""
        snapshot = self.snapshot
        if snapshot is None or snapshot[0].done.is_set():
            return
        goal, now_ns, tfs, desired, q, qd = snapshot
        fb = FollowJointTrajectory.Feedback(joint_names=self.joints)
        fb.header.stamp = time_msg(now_ns)
        fb.desired = JointTrajectoryPoint(
            positions=desired.p.tolist(), velocities=desired.v.tolist(),
            accelerations=desired.a.tolist(), effort=desired.e.tolist(),
            time_from_start=duration_msg(tfs))
        fb.actual = JointTrajectoryPoint(positions=q.tolist(), velocities=qd.tolist(),
                                         time_from_start=duration_msg(tfs))
        fb.error = JointTrajectoryPoint(
            positions=(desired.p - q).tolist(),
            velocities=(desired.v - qd if self.effort else np.zeros(self.n)).tolist())
        goal.handle.publish_feedback(fb)

    # -- the update, in the robot's loop ------------------------------------------------------
    def update(self, now_ns: int, q: np.ndarray, qd: np.ndarray) -> np.ndarray | None:
        """JointTrajectoryController::update at `now_ns` on the measured state: the command
        (effort or position) for the hardware, None before the first goal."""
        with self.lock:
            new, self.inbox = self.inbox, None
        if new is HOLD:
            self.traj = self.hold(q)
        elif new is not None:
            self.traj = new
        traj = self.traj
        if traj is None:
            return None
        first_sample = traj.t_before is None
        if first_sample:
            traj.begin(now_ns, q, qd, self.command if self.effort else np.zeros(self.n))
        t = (now_ns - traj.start_ns) * 1e-9
        desired, before_last = traj.sample(t)
        # JTC: the PID acts on the error now, the output is for the next cycle: its position,
        # or its effort as feed-forward (command_next_ sampled at traj_time_ + update_period_)
        following, _ = traj.sample(t + self.period)
        error_p = desired.p - q
        # JTC computes velocity errors only with a velocity or effort command interface
        error_v = desired.v - qd if self.effort else np.zeros(self.n)
        goal = traj.goal
        violated, outside, in_time = False, False, True
        if goal is not None:        # not holding: tolerances
            path, final, goal_time = traj.tolerances
            if before_last or first_sample:
                violated = bool(np.any(np.abs(error_p) > path[:, 0])
                                or np.any(np.abs(error_v) > path[:, 1]))
            if not before_last:
                outside = bool(np.any(np.abs(error_p) > final[:, 0])
                               or np.any(np.abs(error_v) > final[:, 1]))
                in_time = not (outside and goal_time != 0.0 and t - traj.t[-1] > goal_time)
        if not violated and in_time:
            self.command = (self.kp * error_p + self.kd * error_v + following.e if self.effort
                            else following.p)
        if self.state_pub.get_subscription_count() > 0:
            self.publish_state(now_ns, t, desired, q, qd, error_p, error_v)
        if goal is None:
            return self.command
        self.snapshot = (goal, now_ns, t, desired, q, qd)
        if violated:
            self.end(goal, 'aborted', Result.PATH_TOLERANCE_VIOLATED,
                     'Aborted due to path tolerance violation', self.hold(q))
        elif not before_last and not outside:
            self.end(goal, 'succeeded', Result.SUCCESSFUL, 'Goal successfully reached!',
                     Trajectory([traj.points[-1]], [0.0]))    # the last point, held
        elif not in_time:
            self.end(goal, 'aborted', Result.GOAL_TOLERANCE_VIOLATED,
                     f'Aborted due to goal_time_tolerance exceeding by '
                     f'{t - traj.t[-1]:f} seconds', self.hold(q))
        return self.command

    def hold(self, q: np.ndarray) -> Trajectory:
        """set_hold_position: the measured positions, velocity and effort zero."""
        return Trajectory([Point(q.copy(), None, None, None)], [0.0])

    def end(self, goal: Goal, outcome: str, code: int, text: str, then: Trajectory) -> None:
        with self.lock:
            if self.active is goal:     # else preempted or canceled meanwhile
                self.finish(goal, outcome, code, text)
        if code == Result.SUCCESSFUL:
            self.get_logger().info(text)
        else:       # (one call site, one severity: rclpy's loggers insist)
            self.get_logger().warning(text)
        self.traj = then            # a newer goal in the inbox replaces it next period

    def publish_state(self, now_ns, t, desired, q, qd, error_p, error_v) -> None:
        msg = JointTrajectoryControllerState(joint_names=self.joints, speed_scaling_factor=1.0)
        msg.header.stamp = time_msg(now_ns)
        msg.reference = JointTrajectoryPoint(
            positions=desired.p.tolist(), velocities=desired.v.tolist(),
            accelerations=desired.a.tolist(), time_from_start=duration_msg(t))
        msg.feedback = JointTrajectoryPoint(positions=q.tolist(), velocities=qd.tolist(),
                                            time_from_start=duration_msg(t))
        msg.error = JointTrajectoryPoint(positions=error_p.tolist(), velocities=error_v.tolist())
        msg.output = (JointTrajectoryPoint(effort=self.command.tolist()) if self.effort
                      else JointTrajectoryPoint(positions=self.command.tolist()))
        self.state_pub.publish(msg)

    def shut_down(self) -> None:
        """on_deactivate: aborts the active goal, and gives its execute callback a second to
        report that before ROS goes."""
        with self.lock:
            goal = self.active
            if goal is not None:
                self.finish(goal, 'aborted', Result.INVALID_GOAL,
                            'Current goal cancelled during deactivate transition.')
        deadline = time.monotonic() + 1.0
        while goal is not None and goal.handle.is_active and time.monotonic() < deadline:
            time.sleep(0.01)


def torque_limits(model, joint_ids) -> tuple[np.ndarray, np.ndarray]:
    """The torque each joint can get: its actuatorfrcrange and those of the motors on it
    (ctrlrange or forcerange times gear); +-inf where the model sets none."""
    lo, hi = np.full(len(joint_ids), -np.inf), np.full(len(joint_ids), np.inf)
    for k, j in enumerate(joint_ids):
        ranges = [model.jnt_actfrcrange[j]] if model.jnt_actfrclimited[j] else []
        for i in range(model.nu):
            if model.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT and \
                    model.actuator_trnid[i, 0] == j:
                gear = model.actuator_gear[i, 0]
                if model.actuator_ctrllimited[i]:
                    ranges.append(model.actuator_ctrlrange[i] * model.actuator_gainprm[i, 0] * gear)
                if model.actuator_forcelimited[i]:
                    ranges.append(model.actuator_forcerange[i] * gear)
        for r in ranges:
            lo[k], hi[k] = max(lo[k], min(r)), min(hi[k], max(r))
    return lo, hi


class PositionServo:
    """The robot's own position loop, under JTC's position interface (as a UR or a Kinova
    runs one): PD scaled by each joint's inertia, natural frequency SERVO_BANDWIDTH / period,
    the velocity reference from the command's steps, bias forces compensated; on the true
    state (its own encoders). It follows a smooth command within a few mrad."""

    def __init__(self, model, qpos, dofs, period: float):
        self.model, self.qpos, self.dofs, self.period = model, qpos, dofs, period
        self.wn = SERVO_BANDWIDTH / period
        self.inertia = np.zeros((model.nv, model.nv))
        self.last = None            # the previous command

    def torque(self, data, command: np.ndarray) -> np.ndarray:
        velocity = 0.0 if self.last is None else (command - self.last) / self.period
        self.last = command
        mujoco.mj_fullM(self.model, data, self.inertia)
        return self.inertia[self.dofs, self.dofs] * (
            self.wn**2 * (command - data.qpos[self.qpos])
            + 2 * self.wn * (velocity - data.qvel[self.dofs])) + data.qfrc_bias[self.dofs]


def realtime(priority: int) -> bool:
    """SCHED_FIFO at `priority` for the calling thread (and the threads it starts), if allowed."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except PermissionError:
        return False


def arguments():
    args = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    args.add_argument('--model', required=True)
    args.add_argument('--joints', nargs='+', required=True)
    args.add_argument('--start', nargs='+', type=float, required=True)
    args.add_argument('--interface', choices=['effort', 'position'], required=True)
    args.add_argument('--controller', required=True, help='the controller node (its name)')
    args.add_argument('--kp', nargs='+', type=float, help='effort: gains.<joint>.p')
    args.add_argument('--kd', nargs='+', type=float, help='effort: gains.<joint>.d')
    args.add_argument('--mass-scale', type=float, default=1.3)
    args.add_argument('--noise-position', type=float, default=1e-3)
    args.add_argument('--noise-velocity', type=float, default=1e-2)
    args.add_argument('--latency-periods', type=int, default=1)
    args.add_argument('--extra-joint', default='gripper_finger')
    args.add_argument('--payload', help='BODY:INDEX: the mass of BODY is tau[INDEX]')
    args.add_argument('--silence', type=float, default=0.0)
    args.add_argument('--rate', type=float, help='Hz; default: 1 / the model timestep')
    a = args.parse_args()
    n = len(a.joints)
    if len(a.start) != n:
        args.error(f'--start needs {n} values')
    if a.interface == 'effort' and (a.kp is None or a.kd is None
                                    or len(a.kp) != n or len(a.kd) != n):
        args.error(f'--interface effort needs --kp and --kd, {n} values each')
    if a.interface == 'position' and (a.kp or a.kd):
        args.error('--kp and --kd are gains of the effort interface')
    if a.latency_periods < 0:
        args.error('--latency-periods must be >= 0')
    return a


def main():
    a = arguments()
    model = mujoco.MjModel.from_xml_path(a.model)
    if a.rate:
        model.opt.timestep = 1.0 / a.rate
    period, n = model.opt.timestep, len(a.joints)
    model.body_mass[1:] *= a.mass_scale
    model.body_inertia[1:] *= a.mass_scale
    ids = [model.joint(name).id for name in a.joints]
    qpos, dofs = model.jnt_qposadr[ids], model.jnt_dofadr[ids]
    model.dof_damping[dofs] += 0.3          # N m s/rad: joints the model does not know
    model.dof_frictionloss[dofs] += 0.05    # N m
    lo, hi = torque_limits(model, ids)
    data = mujoco.MjData(model)
    data.qpos[qpos] = a.start
    mujoco.mj_forward(model, data)
    rng = np.random.default_rng(0)

    # Ctrl-C: a KeyboardInterrupt in the loop, which ends the goal before ROS shuts down
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    jtc = JointTrajectoryController(a.controller, a.joints, a.interface, a.kp or [0.0] * n,
                                    a.kd or [0.0] * n, period)
    broadcaster = Node('joint_state_broadcaster')
    # a second of states kept for a reader that falls behind (ros2_control's broadcaster keeps
    # 10): on a loaded machine a test's process was starved 0.33 s and lost the states of
    # the motion it compares (reliable delivery resends only what the writer still keeps)
    states = broadcaster.create_publisher(
        JointState, '/joint_states',
        QoSProfile(depth=int(round(1.0 / period)), reliability=ReliabilityPolicy.RELIABLE))
    names = list(a.joints) + ([a.extra_joint] if a.extra_joint else [])
    extra = [0.0] * (len(names) - n)
    payload = {}                            # the mass the operator put on the arm
    if a.payload:
        from psl_msgs.msg import TaskInstance
        body, index = a.payload.rsplit(':', 1)
        body_id, index = model.body(body).id, int(index)
        broadcaster.create_subscription(
            TaskInstance, '/task_instance',
            lambda m: payload.__setitem__('mass', m.tau[index] * a.mass_scale)
            if len(m.tau) > index else None,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
    silent_until = [0.0]
    signal.signal(signal.SIGUSR1, lambda *_: silent_until.__setitem__(
        0, time.monotonic() + a.silence))
    # one thread, the loop below: measure, publish, control, step; the executor's threads (goals,
    # cancels, feedback, parameters) hand over to it under a lock. As ros2_control's controller
    # manager, the loop runs with real-time scheduling (SCHED_FIFO 50) where allowed; the
    # executor's threads just below it, so that a thread holding the GIL is not starved by
    # other processes while the loop waits for it; the GIL changes hands within a tenth of a
    # period (Python's default: 5 ms)
    sys.setswitchinterval(period / 10)
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(jtc)
    executor.add_node(broadcaster)
    threading.Thread(target=lambda: (realtime(49), executor.spin()), daemon=True).start()
    if not realtime(50):
        jtc.get_logger().warning('no real-time scheduling allowed: the loop may be late at times')
    commands = deque([None] * a.latency_periods)
    servo = PositionServo(model, qpos, dofs, period) if a.interface == 'position' else None
    applied = np.zeros(n)
    deadline = time.monotonic()
    try:
        while rclpy.ok():
            now_ns = jtc.get_clock().now().nanoseconds      # the wall clock
            q = data.qpos[qpos] + rng.normal(0.0, a.noise_position, n)
            qd = data.qvel[dofs] + rng.normal(0.0, a.noise_velocity, n)
            if time.monotonic() >= silent_until[0]:
                msg = JointState(name=names, position=q.tolist() + extra,
                                 velocity=qd.tolist() + extra, effort=applied.tolist() + extra)
                msg.header.stamp = time_msg(now_ns)
                states.publish(msg)
            commands.append(jtc.update(now_ns, q, qd))
            command = commands.popleft()    # a command acts latency_periods late
            if 'mass' in payload:
                model.body_mass[body_id] = payload.pop('mass')
            if command is None:             # brakes on until the first command
                data.qpos[qpos], data.qvel[dofs] = a.start, 0.0
                mujoco.mj_forward(model, data)
                applied = np.zeros(n)
            else:
                applied = np.clip(command if servo is None else servo.torque(data, command),
                                  lo, hi)
                data.qfrc_applied[dofs] = applied
                mujoco.mj_step(model, data)
            deadline += period
            now = time.monotonic()
            if deadline < now:              # late: go on from now, no burst to catch up
                deadline = now
            time.sleep(deadline - now)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        jtc.shut_down()
        executor.shutdown(timeout_sec=1.0)
        jtc.destroy_node()
        broadcaster.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
