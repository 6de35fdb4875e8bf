"""The parameters of the standard robot node (`psl_ros.parameters.declare` makes them; imports
no ROS). ``('',)`` and ``(0.0,)`` stand for "not given" in the list parameters: a ROS parameter
cannot be declared as an empty list of a type."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import field

from psl_controller.parameters import (GOAL_DOCS, GOAL_MAX_DURATION, GOAL_MAX_POINTS,
                                       GOAL_MAX_VELOCITY, check_goal_bounds)
from psl_task import DEFAULT_TASK
from psl_task.model_error import ModelError

NOT_GIVEN = ('',)           # a string list left to the task (or empty)
FROM_TASK = (0.0,)          # initial_posture, kp, kd: the task's
REALTIME_PRIORITY = 50      # ros2_control's controller manager's default (its thread_priority)


@dataclasses.dataclass(frozen=True)
class StandardRobotParameters:
    """A ros2_control robot played by the task's MuJoCo model: its joint order, its extra
    joints, its controller's gains and what goals it takes, and how it differs from the model
    (noise, latency, model error). The joint lists are checked against the task's driven
    joints."""

    task: str = field(default=DEFAULT_TASK, metadata={'doc': (
        'task whose model is the robot (name or YAML path); it is never switched')})
    joint_order: tuple[str, ...] = field(default=NOT_GIVEN, metadata={'doc': (
        "the order of the driven joints in joint_states (a permutation of the task's); "
        "[''] = the task's order")})
    extra_joints: tuple[str, ...] = field(default=NOT_GIVEN, metadata={'doc': (
        'joints reported after those in joint_states that the task does not drive (e.g. a '
        "gripper finger), always at position 0, velocity 0, effort 0; [''] = none")})
    position_noise: float = field(default=0.0, metadata={'doc': (
        'standard deviation of the Gaussian noise on each measured position [rad or m]')})
    velocity_noise: float = field(default=0.0, metadata={'doc': (
        'standard deviation of the Gaussian noise on each measured velocity [rad/s or m/s]')})
    latency_periods: int = field(default=0, metadata={'doc': (
        "the controller's torque is applied this many control periods after the state it "
        'answers was measured')})
    kp: tuple[float, ...] = field(default=FROM_TASK, metadata={'doc': (
        "its trajectory controller's proportional gains [N m/rad], one per driven joint in "
        "the task's order; [0.0] = the task's controller.kp")})
    kd: tuple[float, ...] = field(default=FROM_TASK, metadata={'doc': (
        "its trajectory controller's derivative gains [N m s/rad]; [0.0] = the task's")})
    model_error: str = field(default='', metadata={'doc': (
        "how the robot differs from the task's model, e.g. "
        "'mass_scale=1.3,frictionloss=0.05,damping=0.3' (psl_task.model_error); '' = none")})
    seed: int = field(default=0, metadata={'doc': 'seed of the measurement noise'})
    realtime_priority: int = field(default=REALTIME_PRIORITY, metadata={'doc': (
        "SCHED_FIFO priority of its control loop (1..99) where the machine allows it, as "
        "ros2_control's controller manager runs its loop; 0 = normal scheduling")})
    initial_posture: tuple[float, ...] = field(default=FROM_TASK, metadata={'doc': (
        "joint positions at start, in the task's joint order (its start_posture's); "
        "[0.0] = the task's start_posture")})
    max_points: int = field(default=GOAL_MAX_POINTS, metadata={'doc': GOAL_DOCS['max_points']})
    max_duration: float = field(default=GOAL_MAX_DURATION, metadata={
        'doc': GOAL_DOCS['max_duration']})
    max_velocity: float = field(default=GOAL_MAX_VELOCITY, metadata={
        'doc': GOAL_DOCS['max_velocity']})

    def __post_init__(self):
        check_goal_bounds(self)
        for name in ('position_noise', 'velocity_noise'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0.0):
                raise ValueError(f'{name} must be a finite standard deviation >= 0, got '
                                 f'{value!r}')
        if isinstance(self.latency_periods, bool) or not isinstance(self.latency_periods, int) \
                or self.latency_periods < 0:
            raise ValueError(f'latency_periods must be a whole number >= 0, got '
                             f'{self.latency_periods!r}')
        for name in ('kp', 'kd'):
            value = getattr(self, name)
            if not all(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0.0
                       for v in value):
                raise ValueError(f'{name} must be finite gains >= 0, got {list(value)}')
        if isinstance(self.realtime_priority, bool) or not isinstance(
                self.realtime_priority, int) or not 0 <= self.realtime_priority <= 99:
            raise ValueError(f'realtime_priority must be a whole number in 0..99, got '
                             f'{self.realtime_priority!r}')
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f'seed must be a whole number >= 0, got {self.seed!r}')
        ModelError.parse(self.model_error)      # ValueError naming what is wrong
        if not all(isinstance(v, (int, float)) and math.isfinite(v)
                   for v in self.initial_posture):
            raise ValueError(f'initial_posture must be finite numbers, got '
                             f'{list(self.initial_posture)}')
        if (self.joint_order, self.extra_joints, self.initial_posture, self.kp,
                self.kd) != (NOT_GIVEN, NOT_GIVEN, FROM_TASK, FROM_TASK, FROM_TASK):
            self.check_against(self.driven_joints())

    def driven_joints(self) -> list[str]:
        """The task's driven joints in its order (TaskError, a ValueError, if it does not
        load)."""
        from psl_task.arm_model import joint_names_of
        from psl_task.task import load_task
        return list(joint_names_of(load_task(self.task)))

    def check_against(self, driven: list[str]) -> None:
        """ValueError unless the joint lists fit the task's driven joints `driven`."""
        for name in ('joint_order',):
            order = getattr(self, name)
            if order != NOT_GIVEN and sorted(order) != sorted(driven):
                missing = sorted(set(driven) - set(order))
                unknown = sorted(set(order) - set(driven))
                raise ValueError(
                    f'{name} must name each of the task\'s driven joints {driven} once, got '
                    f'{list(order)}' + (f'; missing {missing}' if missing else '')
                    + (f'; not driven by the task: {unknown}' if unknown else '')
                    + ('; repeated' if not (missing or unknown) else ''))
        extra = self.extras
        if '' in extra or len(set(extra)) != len(extra) or set(extra) & set(driven):
            raise ValueError(f'extra_joints must be distinct non-empty names of joints the '
                             f'task does not drive ({driven}), got {list(self.extra_joints)}')
        for name in ('initial_posture', 'kp', 'kd'):
            value = getattr(self, name)
            if value != FROM_TASK and len(value) != len(driven):
                raise ValueError(f'{name} must have one entry per driven joint '
                                 f'({len(driven)}: {driven}), got {list(value)}')

    @property
    def extras(self) -> tuple[str, ...]:
        """The extra joints given (none for the default)."""
        return () if self.extra_joints == NOT_GIVEN else tuple(self.extra_joints)
