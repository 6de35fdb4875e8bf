"""The simulator node's parameters (`psl_ros.parameters.declare` makes them; imports no ROS)."""
from __future__ import annotations

import dataclasses
from dataclasses import field

from psl_ros.graph import SIM_MODES
from psl_task import DEFAULT_TASK

MAX_POSE_NOISE = 1.0    # m: a motion capture's noise beyond this is a units error


@dataclasses.dataclass(frozen=True)
class SimParameters:
    """What the simulator loads and how it advances; the dynamic ones may be set while it
    runs (`check`)."""

    task: str = field(default=DEFAULT_TASK, metadata={'doc': (
        'task loaded at start (name or YAML path); a reset may name another')})
    mode: str = field(default=SIM_MODES[0], metadata={'doc': (
        'lockstep (a step per command, as fast as the loop goes) | realtime (the wall clock)')})
    episode_duration: float = field(default=0.0, metadata={'dynamic': True, 'doc': (
        'episode length [s]; 0 = the task duration plus its settle time')})
    max_episode_duration: float = field(default=600.0, metadata={'dynamic': True, 'doc': (
        'the longest episode a reset may ask for [s]')})
    scene_rate: float = field(default=30.0, metadata={'dynamic': True, 'doc': (
        'scene markers per second of simulated time while someone subscribes [Hz]; 0 = only '
        'at resets and episode ends')})
    world_pose_noise: float = field(default=0.0, metadata={'dynamic': True, 'doc': (
        'standard deviation [m] of Gaussian noise on the published positions of the bodies a '
        'task observes (world/<body>/pose), as a motion capture measures them; 0 = exact')})
    realtime_priority: int = field(default=0, metadata={'doc': (
        'realtime: SCHED_FIFO priority of the control loop (1..99) if the machine allows it; '
        '0 = normal scheduling')})
    spin_margin: float = field(default=0.0, metadata={'doc': (
        'realtime: the loop sleeps until this long before each deadline [s], then spins to '
        'it (0: sleep only; docs/benchmarks.md measured no gain)')})

    def __post_init__(self):
        if self.mode not in SIM_MODES:
            raise ValueError(f'mode must be one of {", ".join(SIM_MODES)}, got {self.mode!r}')
        if not self.episode_duration >= 0.0:
            raise ValueError('episode_duration must be >= 0 seconds')
        if not 0.0 < self.max_episode_duration < 1e6:
            raise ValueError('max_episode_duration must be in (0, 1e6) s')
        if not 0.0 <= self.world_pose_noise <= MAX_POSE_NOISE:
            raise ValueError(f'world_pose_noise must be in [0, {MAX_POSE_NOISE:g}] m, got '
                             f'{self.world_pose_noise!r}')
        if not self.scene_rate >= 0.0:
            raise ValueError('scene_rate must be >= 0 Hz')
        if not self.spin_margin >= 0.0:
            raise ValueError('spin_margin must be >= 0 s')
