"""A standard ros2_control robot played by a task's MuJoCo model: the physics, without ROS.

What a real arm behind ``joint_state_broadcaster`` and an effort ``forward_command_controller``
is to its controller: it measures its joints in its own order (with noise, and perhaps joints
the task does not drive), takes torques in its controller's joint order, applies them a number
of control periods late, falls back to zero torque when the commands stop (a safety layer, not
the forward_command_controller's hold-the-last), and is not the model (`ModelError`: masses,
friction, damping). `psl_sim.standard_robot_node` runs it on the wall clock.

One control period (the node calls these at each tick, in this order):
1. `measure`: the state now (robot time ``periods * period``), in ``names`` order, noise added,
   effort = the torque applied during the period that led to it;
2. `advance`: the torque due now is applied over the task's substeps (`ArmModel.step`).
Commands (`receive`) arriving between two ticks belong to the period between them; with
``latency_periods`` n, the command latest at a tick is applied n ticks later. The command
timeout is counted on the robot's `clock`: a tick at which the latest command is
``command_timeout`` old or older sends zero torque into the latency pipeline. The default clock
is robot time (deterministic: a command received after k advances is then in force at the
advances k .. k + timeout periods - 1); the node gives the wall clock (`time.monotonic`), as a
robot's safety layer counts, so a loop that falls behind does not stretch the timeout.
Imports no ROS.
"""
from __future__ import annotations

import collections
import dataclasses
from typing import Callable

import mujoco
import numpy as np

from psl_sim.standard_robot_parameters import (DEFAULT_TIMEOUT_PERIODS, FROM_TASK, NOT_GIVEN,
                                               StandardRobotParameters)
from psl_task.arm_model import ArmModel
from psl_task.model_error import ModelError
from psl_task.task import load_task


TIME_TOLERANCE = 1e-9      # s


class CommandRefused(ValueError):
    """A command the robot does not take (wrong length, NaN or inf); the torque stays."""


@dataclasses.dataclass(frozen=True)
class Measurement:
    """What joint_state_broadcaster reports at one tick."""

    time: float             # robot time of the state [s] (periods * period)
    name: list[str]         # joint_order, then the extra joints
    position: np.ndarray    # (len(name),) noisy; extra joints 0
    velocity: np.ndarray    # (len(name),) noisy; extra joints 0
    effort: np.ndarray      # (len(name),) the torque applied in the period before; extras 0


class StandardRobot:
    """A task's arm as a standard robot (see the module doc).

    Raises:
        ValueError: parameters that do not fit the task (joints, initial posture outside the
            joint ranges), a task that does not load (TaskError), a bad model error.
    """

    def __init__(self, parameters: StandardRobotParameters,
                 rng: np.random.Generator | None = None,
                 clock: Callable[[], float] | None = None):
        self.parameters = p = parameters
        task = load_task(p.task)
        self.arm = arm = ArmModel(task)
        driven = list(arm.joint_names)
        p.check_against(driven)
        self.period = task.control_period
        # the robot is not the model: changed before anything runs (ModelError.apply)
        self.model_error = ModelError.parse(p.model_error)
        self.model_error.apply(arm.model, arm.joint_ids)
        # orders: index into the task's order of each joint of joint_order / command_joints
        self.joint_order = driven if p.joint_order == NOT_GIVEN else list(p.joint_order)
        command_joints = (self.joint_order if p.command_joints == NOT_GIVEN
                          else list(p.command_joints))
        self.command_joints = command_joints
        self._state_index = np.array([driven.index(j) for j in self.joint_order])
        self._command_index = np.array([driven.index(j) for j in command_joints])
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
        self.command_timeout = p.command_timeout or DEFAULT_TIMEOUT_PERIODS * self.period
        # [s] what the timeout is counted on (`clock()`): robot time unless given
        self.clock = clock if clock is not None else lambda: self.periods * self.period
        n = len(driven)
        self.periods = 0                     # advances done: robot time = periods * period
        self.applied = np.zeros(n)           # task order: the torque of the last advance
        self._command: np.ndarray | None = None      # task order, clipped: the latest command
        self._command_time = 0.0             # clock() when it arrived
        # torques sampled at the last latency_periods ticks, not yet applied (zero at start)
        self._pipeline = collections.deque(np.zeros(n) for _ in range(p.latency_periods))

    def _check_posture(self, posture: np.ndarray) -> None:
        arm = self.arm
        low, high = arm.model.jnt_range[arm.joint_ids].T
        limited = arm.model.jnt_limited[arm.joint_ids].astype(bool)
        outside = limited & ((posture < low) | (posture > high))
        if np.any(outside):
            j = int(np.flatnonzero(outside)[0])
            raise ValueError(f'initial_posture puts joint {arm.joint_names[j]!r} at '
                             f'{posture[j]:g}, outside its range [{low[j]:g}, {high[j]:g}]')

    # -- commands -----------------------------------------------------------------------
    def receive(self, data) -> np.ndarray:
        """A forward_command_controller command: torques in `command_joints` order. Clipped
        to the torque limits, it becomes the latest command (arrived in the current period);
        returns it in the task's order. CommandRefused (the torque unchanged) for a wrong
        length or a value that is not finite."""
        command = np.asarray(data, dtype=float).reshape(-1)
        if command.shape != self._command_index.shape:
            raise CommandRefused(f'expected {len(self._command_index)} torques '
                                 f'({", ".join(self.command_joints)}), got {command.size}')
        if not np.isfinite(command).all():
            raise CommandRefused('a torque is NaN or infinite')
        torque = np.empty_like(command)
        torque[self._command_index] = command
        self._command = self.arm.clip_torque(torque)
        self._command_time = self.clock()
        return self._command

    def due(self) -> np.ndarray:
        """The latest command if it is younger than the command timeout, else zero (task
        order): what this tick sends into the latency pipeline."""
        # (a rounding tolerance: on robot time the age is a whole number of periods)
        age = self.clock() - self._command_time
        if self._command is None or age >= self.command_timeout - TIME_TOLERANCE:
            return np.zeros_like(self.applied)
        return self._command

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

    def advance(self) -> np.ndarray:
        """One control period: the torque due (latency, timeout) over the task's substeps.
        Returns it (task order)."""
        self._pipeline.append(self.due())
        self.applied = self.arm.step(self._pipeline.popleft())
        self.periods += 1
        return self.applied

    # -- the world ----------------------------------------------------------------------
    def place(self, tau) -> np.ndarray:
        """Place a task instance (obstacle, payload mass, ...) in the robot's world; the arm
        stays where it is and as it moves. TaskError for a tau the task refuses."""
        return self.arm.place(tau)
