"""A task's movement representation: theta -> commanded joint trajectory on the control grid.

For ``policy.kind: dmp`` the kinematics are one DMP per joint (eq. 2.23-2.24) from the task's
start posture to its goal posture; the default theta is the least-squares fit of the task's
demonstration. The feed-forward torque (dynamics modality) is zero for now. Imports no ROS;
the DMP executor node and batch rollouts both call `TaskPolicy.reference`.
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np

from psl_controller.dmp import DMP, demonstration_from_waypoints
from psl_sim.task import TaskDefinition


@dataclasses.dataclass(frozen=True)
class Reference:
    """Commanded trajectory sampled every control period, t = k * dt for k = 0..num_steps."""

    t: np.ndarray       # (T,)
    q: np.ndarray       # (T, n_joints)
    qd: np.ndarray      # (T, n_joints)
    u_ffwd: np.ndarray  # (T, n_joints)


class TaskPolicy:
    """theta (flat vector) -> Reference, for one task."""

    def __init__(self, task: TaskDefinition):
        cfg = task.policy
        if cfg.get('kind', 'dmp') != 'dmp':
            raise ValueError(f'task {task.name!r}: unknown policy kind {cfg.get("kind")!r}')
        self.task = task
        self.dmp = DMP(n_dims=task.n_joints, n_basis=int(cfg['n_basis']),
                       duration=task.duration, y0=task.start_posture, goal=task.goal_posture,
                       k_s=float(cfg.get('k_s', 400.0)),
                       canonical=str(cfg.get('canonical', 'linear')))
        dt = task.control_period
        t, y = demonstration_from_waypoints(task.demo_times, task.demo_positions, dt)
        self.dmp.fit(t, y, dt)
        self.default_theta = self.dmp.get_theta().copy()

    @property
    def num_parameters(self) -> int:
        return self.default_theta.size

    def reference(self, theta: np.ndarray) -> Reference:
        """The commanded trajectory for theta over one episode. Raises ValueError for a
        theta of the wrong size or with NaN/inf."""
        theta = np.asarray(theta, dtype=float)
        if theta.shape != self.default_theta.shape:
            raise ValueError(f'task {self.task.name!r} takes theta with '
                             f'{self.num_parameters} entries, got {theta.size}')
        if not np.all(np.isfinite(theta)):
            raise ValueError('theta contains NaN or inf')
        self.dmp.set_theta(theta)
        dt = self.task.control_period
        traj = self.dmp.integrate(dt, self.task.num_steps * dt)
        return Reference(t=traj.t, q=traj.y, qd=traj.yd, u_ffwd=np.zeros_like(traj.y))


@functools.lru_cache(maxsize=16)
def policy_for(task: TaskDefinition) -> TaskPolicy:
    return TaskPolicy(task)
