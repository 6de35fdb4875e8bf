"""The parameters of the controller and the executor nodes (`psl_ros.parameters.declare` makes
them; imports no ROS)."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import field

from psl_task import DEFAULT_TASK
from psl_task.schema import RESETS

FROM_TASK = (0.0,)      # a gain or limit parameter left to the task (its YAML, its model)
STATE_LOSS = ('zero', 'hold')   # what the controller's watchdog commands
STATE_TIMEOUT = 0.3     # [s] the watchdog's default (0.105 s gaps seen in a Python robot loop on
                        # a loaded 2-core machine)
# how an episode's time runs (`psl_controller.robot_link.CLOCKS`): psl's simulator advances it
# (its sim/reset starts each episode: lockstep or realtime), or the robot's own wall clock
CLOCKS = ('simulator', 'robot')
COMMAND_INTERFACES = ('effort', 'position')     # a JointTrajectoryController's (psl's: effort)
# What a goal may ask of a controller psl serves (`psl_controller.goal_limits`): the defaults of
# pd_controller's and the standard robot's parameters. psl's own goals are a point per control
# period; the longest, homing from one end of a joint's range at homing.max_velocity, is 4,947
# points for an embedded task (reach_over_obstacle: 9.6 s + 0.3 s settling at 500 Hz) and 6,042
# for the examples (xarm7_point_reach), an episode at most 1,251 (payload_transport_timed).
# 20,000 points are 40 s at 500 Hz. A goal's message takes about 0.65 kB of Python objects per
# point of 3 joints while it is read; it is released once read.
GOAL_MAX_POINTS = 20_000
GOAL_MAX_DURATION = 600.0       # [s] as the simulator's longest episode (max_episode_duration)
# [rad/s (m/s)] the controller's own velocity bound, which can only narrow the arm's
# (`psl_task.joint_limits`: a URDF's velocity limits, else 100 rad/s; safety.max_velocity): none
GOAL_MAX_VELOCITY = float('inf')


GOAL_DOCS = {
    'max_points': 'the most points a FollowJointTrajectory goal may have (more: rejected)',
    'max_duration': ('[s] the longest a goal may last from its start to its last point, and '
                     'the latest it may start after the newest state (later: rejected)'),
    'max_velocity': ('[rad/s] a velocity bound of every joint, narrowing the arm\'s (a '
                     "URDF's <limit velocity>, else 100 rad/s; the task's safety.max_velocity): "
                     'a goal whose points or interpolation exceed it is rejected; inf = the '
                     "arm's")}


def check_goal_bounds(parameters) -> None:
    """ValueError unless `parameters`' max_points, max_duration and max_velocity are a
    whole number >= 2 and two numbers > 0 (the duration finite)."""
    points, duration, velocity = (parameters.max_points, parameters.max_duration,
                                  parameters.max_velocity)
    if isinstance(points, bool) or not isinstance(points, int) or points < 2:
        raise ValueError(f'max_points must be a whole number >= 2, got {points!r}')
    if not (duration > 0.0 and math.isfinite(duration)):
        raise ValueError(f'max_duration must be a finite number of seconds > 0, got '
                         f'{duration!r}')
    if not velocity > 0.0:
        raise ValueError(f'max_velocity must be > 0, got {velocity!r}')


@dataclasses.dataclass(frozen=True)
class ControllerParameters:
    """The PD + feed-forward controller's: the task that gives its default gains and torque
    limits, and overrides of them (checked against the task's joints by the node)."""

    task: str = field(default=DEFAULT_TASK, metadata={'doc': (
        'task whose YAML gives the default gains and whose model the default torque limits')})
    kp: tuple[float, ...] = field(default=FROM_TASK, metadata={'dynamic': True, 'doc': (
        'proportional gains [N m/rad], one per joint; [0.0] = from the task')})
    kd: tuple[float, ...] = field(default=FROM_TASK, metadata={'dynamic': True, 'doc': (
        'derivative gains [N m s/rad], one per joint; [0.0] = from the task')})
    torque_limit: tuple[float, ...] = field(default=FROM_TASK, metadata={
        'dynamic': True,
        'doc': 'symmetric torque limits [N m], one per joint; [0.0] = from the task'})
    realtime_priority: int = field(default=0, metadata={'doc': (
        'SCHED_FIFO priority of the thread that answers the states (1..99) if the machine '
        'allows it; 0 = normal scheduling')})
    command_joints: tuple[str, ...] = field(default=('',), metadata={'doc': (
        "the joint order of effort_command (a forward_command_controller's joints); [''] = "
        "the task's command order")})
    state_timeout: float = field(default=STATE_TIMEOUT, metadata={'doc': (
        'watchdog [s]: when no joint state came for this long the active goal aborts and the '
        'controller sends on_state_loss every control period until states come again; 0 = '
        "off (psl's simulator, which pauses between episodes)")})
    on_state_loss: str = field(default='zero', metadata={'dynamic': True, 'doc': (
        'what the watchdog commands: zero (zero torque) | hold (the last torque sent)')})
    max_points: int = field(default=GOAL_MAX_POINTS, metadata={'doc': GOAL_DOCS['max_points']})
    max_duration: float = field(default=GOAL_MAX_DURATION, metadata={
        'doc': GOAL_DOCS['max_duration']})
    max_velocity: float = field(default=GOAL_MAX_VELOCITY, metadata={
        'doc': GOAL_DOCS['max_velocity']})

    def __post_init__(self):
        if not (self.state_timeout >= 0.0 and math.isfinite(self.state_timeout)):
            raise ValueError(f'state_timeout must be a finite number of seconds >= 0, got '
                             f'{self.state_timeout}')
        if self.on_state_loss not in STATE_LOSS:
            raise ValueError(f'on_state_loss must be one of {", ".join(STATE_LOSS)}, got '
                             f'{self.on_state_loss!r}')
        check_goal_bounds(self)


@dataclasses.dataclass(frozen=True)
class ExecutorParameters:
    """The DMP executor's: the controller it drives, the clock of its episodes, how they begin
    and how long it waits."""

    controller: str = field(default='pd_controller', metadata={'doc': (
        'the JointTrajectoryController that moves the arm: the node whose '
        'follow_joint_trajectory action (control_msgs/FollowJointTrajectory) and parameters '
        "(joints, command_interfaces) it offers, e.g. /fr3_arm_controller; relative names are "
        "in the executor's namespace")})
    clock: str = field(default=CLOCKS[0], metadata={'doc': (
        "simulator: psl's simulator runs each episode (its sim/reset: a teleport or a drive "
        "of the episode's length) | robot: the robot's own wall clock (psl homes the arm from "
        'its measured states, then the primitive, each stamped ahead of its newest state)')})
    command_interface: str = field(default='', metadata={'doc': (
        "the controller's command interface: effort (goals carry the feed-forward torque) | "
        "position (kinematic tasks only); '' = ask the controller (its command_interfaces "
        'parameter)')})
    timeout_margin: float = field(default=10.0, metadata={'dynamic': True, 'doc': (
        'seconds to wait for an episode beyond its length')})
    reset: str = field(default='', metadata={'dynamic': True, 'doc': (
        "how an episode begins: teleport (the simulator only) | drive ('' = the task's "
        'homing.reset; a robot is always driven)')})

    def __post_init__(self):
        if not (self.timeout_margin > 0.0 and math.isfinite(self.timeout_margin)):
            raise ValueError(f'timeout_margin must be a finite number of seconds > 0, got '
                             f'{self.timeout_margin}')
        if self.clock not in CLOCKS:
            raise ValueError(f'clock must be one of {", ".join(CLOCKS)}, got {self.clock!r}')
        if self.command_interface and self.command_interface not in COMMAND_INTERFACES:
            raise ValueError(f'command_interface must be one of '
                             f'{", ".join(COMMAND_INTERFACES)} or empty, got '
                             f'{self.command_interface!r}')
        if not self.controller.strip('/'):
            raise ValueError('controller must name a node (e.g. pd_controller)')
        if self.reset and self.reset not in RESETS:
            raise ValueError(f'reset must be one of {", ".join(RESETS)} or empty, got '
                             f'{self.reset!r}')
