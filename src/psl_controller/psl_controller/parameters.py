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
ROBOTS = ('sim', 'external')    # who starts an episode: psl's simulator, or psl itself


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
    max_tracking_error: float = field(default=0.0, metadata={'dynamic': True, 'doc': (
        'rad: a tracking error beyond it aborts the trajectory (the controller holds); 0 = '
        "the task's safety.max_tracking_error (default: no bound); the executor sets each "
        "rollout's task's")})
    command_joints: tuple[str, ...] = field(default=('',), metadata={'doc': (
        "the joint order of effort_command (a forward_command_controller's joints); [''] = "
        "the task's command order")})
    state_timeout: float = field(default=0.0, metadata={'doc': (
        'watchdog [s]: when no joint state came for this long the controller drops its '
        'trajectory, reports it on /diagnostics and sends on_state_loss every control '
        "period until states come again; 0 = off (psl's lockstep simulator pauses between "
        'episodes)')})
    on_state_loss: str = field(default='zero', metadata={'dynamic': True, 'doc': (
        'what the watchdog commands: zero (zero torque) | hold (the last torque sent)')})

    def __post_init__(self):
        if not self.max_tracking_error >= 0.0:          # NaN too; inf: no bound
            raise ValueError(f'max_tracking_error must be >= 0 rad, got '
                             f'{self.max_tracking_error}')
        if not (self.state_timeout >= 0.0 and math.isfinite(self.state_timeout)):
            raise ValueError(f'state_timeout must be a finite number of seconds >= 0, got '
                             f'{self.state_timeout}')
        if self.on_state_loss not in STATE_LOSS:
            raise ValueError(f'on_state_loss must be one of {", ".join(STATE_LOSS)}, got '
                             f'{self.on_state_loss!r}')


@dataclasses.dataclass(frozen=True)
class ExecutorParameters:
    """The DMP executor's: how long it waits for an evaluation, and how episodes begin."""

    timeout_margin: float = field(default=10.0, metadata={'dynamic': True, 'doc': (
        'seconds to wait for an evaluation beyond the episode length')})
    reset: str = field(default='', metadata={'dynamic': True, 'doc': (
        "how an episode begins: teleport | drive ('' = the task's homing.reset)")})
    robot: str = field(default=ROBOTS[0], metadata={'doc': (
        "sim: psl's simulator starts each episode (its sim/reset) | external: a robot that "
        'only publishes joint_states and takes effort_command; psl runs each episode itself '
        '(homing from the measured posture, the primitive, the wall clock)')})

    def __post_init__(self):
        if not (self.timeout_margin > 0.0 and math.isfinite(self.timeout_margin)):
            raise ValueError(f'timeout_margin must be a finite number of seconds > 0, got '
                             f'{self.timeout_margin}')
        if self.robot not in ROBOTS:
            raise ValueError(f'robot must be one of {", ".join(ROBOTS)}, got {self.robot!r}')
        if self.reset and self.reset not in RESETS:
            raise ValueError(f'reset must be one of {", ".join(RESETS)} or empty, got '
                             f'{self.reset!r}')
