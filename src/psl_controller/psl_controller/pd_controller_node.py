"""The low-level controller node: PD + feed-forward on a sampled joint trajectory.

Answers every ``joint_states`` message with one ``effort_command``
(std_msgs/Float64MultiArray, in ``command_joints`` order: a forward_command_controller's
joints; by default the task's command order). The state is read by joint name
(`psl_task.joint_selection`): any order, extra joints ignored, a state that lacks a task joint
gets no command and a throttled error naming it. The law:
``u = Kp (q_ref - q) + Kd (qd_ref - qd) + u_ffwd``, clipped to the torque limits.
The reference comes from ``joint_trajectory`` (trajectory_msgs/JointTrajectory; effort field =
feed-forward, the ros2_control convention) sampled at the state's time stamp. A trajectory
stamped zero starts at the first state received after it; otherwise at its stamp, and until
then the trajectory that ran before goes on (its last point: a homing's hold keeps its torque,
and the new trajectory's first feed-forward does not push the arm early). A trajectory
stamped with the start of the one that runs replaces it from the next state on (a
goal change): it is refused, with an error, unless it passes exactly through the reference of
the last state served, so the reference the controller tracks never jumps. With no
trajectory the controller holds the position of the first state it saw; after the end it
holds the last point. Each command's reference is published on ``reference``
(sensor_msgs/JointState: position = q_ref, velocity = qd_ref, effort = u_ffwd) with the
state's stamp, so the tracking error can be computed and recorded.

A tracking error beyond ``max_tracking_error`` (the rollout's task's ``safety.max_tracking_error``,
set by the executor as the gains) while a trajectory runs aborts it: the controller holds
where the arm is and reports it on /diagnostics (``tracking abort``, with the excess error);
the executor counts the rollout as the task's penalty minus that excess, with the reason.

A trajectory stamped with a start the states have passed already (a robot's clock runs on while
it travels) is refused and reported on /diagnostics (``late trajectory``, with its start): the
executor sends it again with a later start. A stamped trajectory taken is acknowledged there
(level OK, ``trajectory taken``, with its start): the executor waits for one or the other.

Watchdog (``state_timeout`` > 0, for a robot that never waits for the controller): when no
joint state came for that long (the wall clock), the controller drops its trajectory, reports
the loss on /diagnostics (level ERROR, ``trajectory_start_ns`` of the trajectory it dropped, so
the executor fails that rollout with the reason) and commands ``on_state_loss`` (zero torque,
or the last torque again) every control period until states come again; then it holds the
position of the first new state.
"""
from __future__ import annotations

import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from psl_controller.parameters import ControllerParameters
from psl_controller.pd_law import PDLaw, law_for
from psl_controller.trajectory_sampling import SampledTrajectory
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
from psl_task.safety_check import abort_reason
from psl_task.task import load_task


def trajectory_from_msg(msg: JointTrajectory, joint_names: list[str]) -> SampledTrajectory:
    """Reorder a JointTrajectory to the given joint order and make it sampleable.
    Raises ValueError for unknown joints, ragged points or non-finite values."""
    if sorted(msg.joint_names) != sorted(joint_names):
        raise ValueError(f'trajectory joints {list(msg.joint_names)} do not match the '
                         f'robot joints {joint_names}')
    if not msg.points:
        raise ValueError('trajectory has no points')
    order = [list(msg.joint_names).index(name) for name in joint_names]
    n = len(joint_names)

    def column(field: str) -> np.ndarray | None:
        rows = [getattr(p, field) for p in msg.points]
        if all(len(r) == 0 for r in rows):
            return None
        if any(len(r) != n for r in rows):
            raise ValueError(f'every trajectory point needs {n} {field} (or none)')
        return np.asarray(rows, dtype=float)[:, order]

    times = np.array([to_ns(p.time_from_start) for p in msg.points], dtype=np.int64)
    positions = column('positions')
    if positions is None:
        raise ValueError('trajectory points need positions')
    arrays = [positions, column('velocities'), column('effort')]
    if not all(a is None or np.all(np.isfinite(a)) for a in arrays):
        raise ValueError('trajectory contains NaN or inf')
    return SampledTrajectory(times, *arrays)


class PDController(Node):

    def __init__(self):
        super().__init__('pd_controller')
        self.parameters = declare(self, ControllerParameters)
        task = load_task(self.parameters.task)
        self.default_law = law_for(task)
        self.n_joints = self.default_law.n_joints
        self.period = task.control_period
        # the task's joints (command order) by name in each state
        self.joint_names = joint_names_of(task)
        self.selection = JointSelection(self.joint_names)
        self.command_order = self._command_order(self.parameters.command_joints)
        self.task_bound = task.safety.max_tracking_error       # rad; inf: no bound
        self.max_tracking_error = self.parameters.max_tracking_error or self.task_bound
        self.law = self._law({name: getattr(self.parameters, name)
                              for name in ('kp', 'kd', 'torque_limit')})
        self.add_on_set_parameters_callback(self.on_set_parameters)

        self.trajectory: SampledTrajectory | None = None
        self.trajectory_msg: JointTrajectory | None = None
        self.start_ns: int | None = None
        self.served_ns: int | None = None     # time of the last state served, from start_ns
        self.before: tuple | None = None      # (trajectory, start_ns) served until start_ns
        self.hold: np.ndarray | None = None
        self.last_state_ns = 0                # stamp of the newest state served

        # watchdog: the wall time of the last state, and whether their loss is reported
        self._state_lock = threading.Lock()
        self._last_state = time.monotonic()
        self._lost = False
        self._last_torque = np.zeros(self.n_joints)
        self.matches = MatchReport(self)        # what the loop's endpoints matched
        self.pub_command = self.matches.create_publisher(Float64MultiArray, names.EFFORT_COMMAND,
                                                         RELIABLE)
        self.pub_reference = self.matches.create_publisher(JointState, names.REFERENCE, RELIABLE)
        # one message each, refilled every step (publish copies it)
        self._command, self._reference = Float64MultiArray(), JointState()
        self.pub_diag = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 10)
        self._reports: list[tuple] = []       # (level, what, reason, values) to send
        self._reports_lock = threading.Lock()
        self._send = self.create_guard_condition(self._send_reports)
        # one thread serves both, the trajectory first when both are ready: a trajectory
        # published before an episode starts is in place for the episode's first state
        # the hot path's thread inherits the scheduling of the thread that starts it
        scheduling = raise_priority(self.parameters.realtime_priority)
        self.hot_path = HotPath(self)
        self.matches.subscribe(self.hot_path, JointTrajectory, names.JOINT_TRAJECTORY,
                               self.on_trajectory, RELIABLE)
        # a robot on the wall clock (the watchdog on): answer the newest state, never work
        # through a backlog of old ones (a late answer is stale; psl's simulator waits for each)
        self.matches.subscribe(self.hot_path, JointState, names.JOINT_STATES, self.on_state,
                               NEWEST if self.parameters.state_timeout > 0.0 else RELIABLE)
        self.hot_path.start()
        self.state_timeout = self.parameters.state_timeout
        self.watchdog = (self.create_timer(self.period, self.on_watchdog)
                         if self.state_timeout > 0.0 else None)
        law = self.law
        self.get_logger().info(
            f'PD + feed-forward controller, kp={law.kp.tolist()} kd={law.kd.tolist()} '
            f'limits={law.torque_low.tolist()}..{law.torque_high.tolist()}; {scheduling}')

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
        names = ('kp', 'kd', 'torque_limit')
        values = {name: self.get_parameter(name).value for name in names}
        values.update({p.name: p.value for p in params if p.name in names})
        try:
            law = self._law(values)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.law = law                  # one object: a step sees the old law or the new one
        for p in params:
            if p.name == 'max_tracking_error':
                self.max_tracking_error = float(p.value) or self.task_bound
        return SetParametersResult(successful=True)

    def on_trajectory(self, msg: JointTrajectory) -> None:
        self.trajectory_msg = msg
        self._load_trajectory()

    def _load_trajectory(self) -> None:
        msg, self.trajectory_msg = self.trajectory_msg, None
        try:
            trajectory = trajectory_from_msg(msg, self.joint_names)
        except ValueError as exc:
            self.get_logger().error(f'refused trajectory: {exc}')
            return
        start = to_ns(msg.header.stamp)
        if 0 < start < self.last_state_ns and start != self.start_ns:
            # a robot's clock has passed the start already: following it would jump
            self._report('late trajectory', start, (
                f'the trajectory came {(self.last_state_ns - start) * 1e-9:.3f} s after its '
                'start (stamp): refused, the controller holds'))
            return
        if start > 0 and start == self.start_ns and self.served_ns is not None:
            # a replacement of the running trajectory: the steps served stay as they were
            old, new = self.trajectory.sample(self.served_ns), trajectory.sample(self.served_ns)
            if not all(np.array_equal(a, b) for a, b in zip(old, new)):
                self.get_logger().error(
                    'refused a replacement trajectory: it leaves the reference served at '
                    f'{self.served_ns * 1e-9:.3f} s of the episode (it would jump)')
                return
        else:
            self.served_ns = None
            # until a stamped trajectory's start, what ran goes on (a hold's torque stays)
            self.before = (self.trajectory, self.start_ns) if (
                start > 0 and self.trajectory is not None and self.start_ns is not None) else None
        self.trajectory = trajectory
        self.start_ns = start if start > 0 else None   # None: the next state starts it
        if start > 0:
            self._report('trajectory taken', start, 'taken', DiagnosticStatus.OK)

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
        t = to_ns(msg.header.stamp)
        self.last_state_ns = t
        trajectory = self.trajectory        # the watchdog may drop it meanwhile
        if trajectory is not None:
            if self.start_ns is None:
                self.start_ns = t
            self.served_ns = t - self.start_ns
            before = self.before
            if self.served_ns < 0 and before is not None:
                q_ref, qd_ref, u_ffwd = before[0].sample(t - before[1])
            else:
                self.before = None
                q_ref, qd_ref, u_ffwd = trajectory.sample(self.served_ns)
            if self.served_ns >= 0 and np.abs(q - q_ref).max() > self.max_tracking_error:
                q_ref, qd_ref, u_ffwd = self._abort(q, q_ref)
        else:
            if self.hold is None:
                self.hold = q.copy()
            q_ref, qd_ref, u_ffwd = self.hold, np.zeros_like(q), np.zeros_like(q)
        u = self.law.torque(q, qd, q_ref, qd_ref, u_ffwd)
        self._last_torque = u
        command = self._command
        command.data = u[self.command_order].tolist()
        self.pub_command.publish(command)
        ref = self._reference
        ref.header.stamp = msg.header.stamp
        ref.name = self.joint_names
        ref.position, ref.velocity, ref.effort = q_ref.tolist(), qd_ref.tolist(), u_ffwd.tolist()
        self.pub_reference.publish(ref)

    def on_watchdog(self) -> None:
        """Every control period: states lost for state_timeout? Then the trajectory is
        dropped (reported once) and on_state_loss is commanded."""
        timeout = self.state_timeout
        with self._state_lock:
            silent = time.monotonic() - self._last_state
            if silent <= timeout:
                return
            first, self._lost = not self._lost, True
        if first:
            start = self.start_ns or 0
            # the next state starts from scratch: hold where the arm is then
            self.trajectory, self.start_ns, self.served_ns, self.hold = None, None, None, None
            self.before = None
            mode = self.get_parameter('on_state_loss').value
            reason = (f'joint states stopped: none for {silent:.3f} s (state_timeout '
                      f'{timeout:g} s); the controller dropped its trajectory and commands '
                      f'{"zero torque" if mode == "zero" else "the last torque"}')
            self._report('state loss', start, reason)
        torque = (np.zeros(self.n_joints) if self.get_parameter('on_state_loss').value == 'zero'
                  else self._last_torque)
        self.pub_command.publish(Float64MultiArray(data=torque[self.command_order].tolist()))

    def _abort(self, q: np.ndarray, q_ref: np.ndarray) -> tuple:
        """The tracking error passed the task's safety.max_tracking_error: drop the trajectory,
        hold where the arm is, report it for the episode; the reference to serve now."""
        j = int(np.argmax(np.abs(q - q_ref)))
        error = float(abs(q[j] - q_ref[j]))
        self._report('tracking abort', self.start_ns, abort_reason(
            self.joint_names[j], error, self.served_ns * 1e-9, self.max_tracking_error)
            + '; the controller holds', violation=error - self.max_tracking_error)
        self.trajectory, self.hold = None, q.copy()
        return self.hold, np.zeros_like(q), np.zeros_like(q)

    def _report(self, what: str, start_ns: int, reason: str,
                level: bytes = DiagnosticStatus.ERROR, violation: float | None = None) -> None:
        """Report `reason` on /diagnostics (``<node>: <what>``) for the trajectory that starts
        at `start_ns` (an error, also logged: the executor fails that rollout with it; OK:
        ``trajectory taken``, the acknowledgement the executor waits for on a robot).
        Sent from the node's executor (`_send_reports`), never from the hot path's thread:
        a publish there that waits (the middleware, the log's /rosout) delays the commands."""
        values = [KeyValue(key='trajectory_start_ns', value=str(start_ns))]
        if violation is not None:
            values.append(KeyValue(key='violation', value=repr(float(violation))))
        with self._reports_lock:
            self._reports.append((level, what, reason, values))
        self._send.trigger()

    def _send_reports(self) -> None:
        with self._reports_lock:
            reports, self._reports = self._reports, []
        for level, _, reason, _ in reports:
            if level == DiagnosticStatus.ERROR:
                self.get_logger().error(reason)
        if reports:
            self.pub_diag.publish(DiagnosticArray(status=[DiagnosticStatus(
                level=level, name=f'{self.get_fully_qualified_name()}: {what}', message=reason,
                values=values) for level, what, reason, values in reports]))

    def destroy_node(self):
        self.hot_path.stop()
        super().destroy_node()


def main(args=None):
    run_node(PDController, args)


if __name__ == '__main__':
    main()
