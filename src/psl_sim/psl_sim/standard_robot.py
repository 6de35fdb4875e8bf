"""A standard ros2_control robot played by a task's MuJoCo model: the physics and the robot's own
JointTrajectoryController, without ROS.

What a real arm behind ``joint_state_broadcaster`` and a JointTrajectoryController (JTC) on the
effort interface is to psl: it measures its joints in its own order (with noise, and perhaps
joints the task does not drive), runs its trajectory controller inside its own loop, stepped
with the physics (`psl_controller.trajectory_controller.TrajectoryController`: the compliant
law ``u = Kp (q_ref - q) + Kd (qd_ref - qd) + u_ffwd`` on the *measured* state, the robot's own
gains), applies the torque a number of control periods late, and is not the model
(`ModelError`: masses, friction, damping). `psl_sim.standard_robot_node` runs it on the wall
clock and serves the controller as control_msgs/FollowJointTrajectory, as
mujoco_ros2_control and a real driver do. No DDS inside its control loop.

One control period (`step`, at robot time ``t_ns``):
1. measure: the state now, in ``names`` order, noise added, effort = the torque applied during
   the period that led to it;
2. control: the controller's torque for the measured state (task order);
3. advance: the torque due now (the one computed ``latency_periods`` periods ago; zero before)
   applied over the task's substeps (`ArmModel.step`).
Imports no ROS.
"""
from __future__ import annotations

import collections
import dataclasses

import mujoco
import numpy as np

from psl_controller.goal_limits import GoalLimits
from psl_controller.pd_law import PDLaw, law_for
from psl_controller.trajectory_controller import Result, TrajectoryController
from psl_sim.standard_robot_parameters import FROM_TASK, NOT_GIVEN, StandardRobotParameters
from psl_task.arm_model import ArmModel
from psl_task.model_error import ModelError
from psl_task.task import load_task


@dataclasses.dataclass(frozen=True)
class Measurement:
    """What joint_state_broadcaster reports at one tick."""

    time: float             # robot time of the state [s] (periods * period)
    name: list[str]         # joint_order, then the extra joints
    position: np.ndarray    # (len(name),) noisy; extra joints 0
    velocity: np.ndarray    # (len(name),) noisy; extra joints 0
    effort: np.ndarray      # (len(name),) the torque applied in the period before; extras 0


class StandardRobot:
    """A task's arm as a standard robot with its own trajectory controller (module doc).

    Raises:
        ValueError: parameters that do not fit the task (joints, initial posture outside the
            joint ranges, gains), a task that does not load (TaskError), a bad model error.
    """

    def __init__(self, parameters: StandardRobotParameters,
                 rng: np.random.Generator | None = None):
        self.parameters = p = parameters
        task = load_task(p.task)
        self.arm = arm = ArmModel(task)
        driven = list(arm.joint_names)
        p.check_against(driven)
        self.period = task.control_period
        self.period_ns = task.control_period_ns
        # the robot is not the model: changed before anything runs (ModelError.apply)
        self.model_error = ModelError.parse(p.model_error)
        self.model_error.apply(arm.model, arm.joint_ids)
        # its controller: the task's law with the robot's own gains, if given, and what a
        # goal may ask of the arm (whoever sends it)
        self.controller = TrajectoryController(driven, self._law(law_for(task)))
        self.limits = GoalLimits.of(arm, p.max_points, p.max_duration, p.max_velocity)
        # orders: index into the task's order of each joint of joint_order
        self.joint_order = driven if p.joint_order == NOT_GIVEN else list(p.joint_order)
        self._state_index = np.array([driven.index(j) for j in self.joint_order])
        self.names = self.joint_order + list(p.extras)
        self._n_extra = len(p.extras)
        # the start: the task's default instance around the arm at rest in initial_posture
        posture = (task.start_posture if p.initial_posture == FROM_TASK
                   else np.asarray(p.initial_posture, dtype=float))
        self._check_posture(posture)
        arm.reset(task.tau_default)
        arm.data.qpos[arm.qpos_adr] = posture
        mujoco.mj_forward(arm.model, arm.data)
        self.rng = rng if rng is not None else np.random.default_rng(p.seed)
        n = len(driven)
        self.periods = 0                     # advances done: robot time = periods * period
        self.applied = np.zeros(n)           # task order: the torque of the last advance
        # torques computed at the last latency_periods ticks, not yet applied (zero at start)
        self._pipeline = collections.deque(np.zeros(n) for _ in range(p.latency_periods))

    def _law(self, task_law: PDLaw) -> PDLaw:
        p, n = self.parameters, task_law.n_joints
        gains = []
        for name, default in (('kp', task_law.kp), ('kd', task_law.kd)):
            value = np.asarray(getattr(p, name), dtype=float)
            if tuple(value) == FROM_TASK:
                gains.append(default)
            elif value.shape != (n,):
                raise ValueError(f'{name} needs one gain per driven joint ({n}), got '
                                 f'{value.tolist()}')
            else:
                gains.append(value)
        return PDLaw(gains[0], gains[1], task_law.torque_low, task_law.torque_high)

    def _check_posture(self, posture: np.ndarray) -> None:
        arm = self.arm
        low, high = arm.model.jnt_range[arm.joint_ids].T
        limited = arm.model.jnt_limited[arm.joint_ids].astype(bool)
        outside = limited & ((posture < low) | (posture > high))
        if np.any(outside):
            j = int(np.flatnonzero(outside)[0])
            raise ValueError(f'initial_posture puts joint {arm.joint_names[j]!r} at '
                             f'{posture[j]:g}, outside its range [{low[j]:g}, {high[j]:g}]')

    # -- the control period -------------------------------------------------------------
    def measure(self) -> Measurement:
        """The state now, as the robot reports it."""
        arm, p = self.arm, self.parameters
        n = len(self._state_index)
        position = np.zeros(n + self._n_extra)
        velocity = np.zeros(n + self._n_extra)
        effort = np.zeros(n + self._n_extra)
        position[:n] = arm.q[self._state_index]
        velocity[:n] = arm.qd[self._state_index]
        effort[:n] = self.applied[self._state_index]
        if p.position_noise > 0.0:
            position[:n] += self.rng.normal(0.0, p.position_noise, n)
        if p.velocity_noise > 0.0:
            velocity[:n] += self.rng.normal(0.0, p.velocity_noise, n)
        return Measurement(self.periods * self.period, self.names, position, velocity, effort)

    def step(self, t_ns: int | None = None) -> tuple[Measurement, list[Result]]:
        """One control period (module doc) at robot time `t_ns` (default: periods * period):
        the state measured at its start and the controller's goals that ended."""
        state = self.measure()
        n = len(self._state_index)
        q, qd = np.empty(n), np.empty(n)
        q[self._state_index], qd[self._state_index] = state.position[:n], state.velocity[:n]
        torque, results = self.controller.update(
            self.periods * self.period_ns if t_ns is None else t_ns, q, qd)
        self._pipeline.append(torque)
        self.applied = self.arm.step(self._pipeline.popleft())
        self.periods += 1
        return state, results

    # -- the world ----------------------------------------------------------------------
    def place(self, tau) -> np.ndarray:
        """Place a task instance (obstacle, payload mass, ...) in the robot's world; the arm
        stays where it is and as it moves. TaskError for a tau the task refuses."""
        return self.arm.place(tau)
