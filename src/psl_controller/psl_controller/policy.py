"""A task's movement representation: theta -> commanded joint trajectory on the control grid.

For ``policy.kind: dmp`` the kinematics are one DMP per joint (eq. 2.23-2.24) from the task's
start posture to its goal posture; the default theta is the least-squares fit of the task's
demonstration. With ``policy.kind: gmr`` the kinematics are instead a Gaussian mixture over
[phase, q] conditioned on the phase (eq. 2.25, `psl_controller.gmr_trajectory`;
``n_components``, default 6): theta_K = the components' means and slopes, fitted to the same
demonstration by EM; start and goal are then not guaranteed, only learned. Both expose theta_K
as one flat vector (get_theta / set_theta) and ``integrate(dt, t_end)``.
With ``policy.feedforward: true`` theta is one flat vector
``[theta_K, theta_D]``: theta_K as above, theta_D the weights of the feed-forward torque
u_ffwd(t) on the DMP's basis (`psl_controller.feedforward`, same size),
default theta_D = 0. Without the option theta = theta_K and u_ffwd is zero. Imports no ROS;
the DMP executor node and batch rollouts both call `TaskPolicy.reference`.
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np

from psl_controller.dmp import DMP, demonstration_from_waypoints
from psl_controller.feedforward import FeedForward
from psl_controller.gmr_trajectory import GMRTrajectory
from psl_sim.task import TaskDefinition


KINDS = ('dmp', 'gmr')     # how theta_K encodes the joint trajectory
THETA_SPREADS = 1000.0     # a rollout's theta entries lie within this many default spreads


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
        spec = task.policy
        if spec.kind not in KINDS:
            raise ValueError(f'task {task.name!r}: unknown policy kind {spec.kind!r}; known: '
                             f'{", ".join(KINDS)}')
        self.task = task
        # the DMP's phase and basis also carry the feed-forward, whatever encodes theta_K
        self.dmp = DMP(n_dims=task.n_joints, n_basis=spec.n_basis, duration=task.duration,
                       y0=task.start_posture, goal=task.goal_posture, k_s=spec.k_s,
                       canonical=spec.canonical)
        dt = task.control_period
        t, y = demonstration_from_waypoints(task.demo_times, task.demo_positions, dt)
        self.dmp.fit(t, y, dt)
        if spec.kind == 'gmr':
            self.movement = GMRTrajectory(task.n_joints, spec.n_components, task.duration)
            self.movement.fit(t, y, seed=spec.fit_seed)
        else:
            self.movement = self.dmp
        self.feedforward = (FeedForward(self.dmp.canonical, self.dmp.basis, task.n_joints)
                            if spec.feedforward else None)
        n_kin = self.movement.num_parameters
        n_dyn = self.feedforward.num_parameters if spec.feedforward else 0
        self.kinematics = slice(0, n_kin)               # theta_K in theta
        self.dynamics = slice(n_kin, n_kin + n_dyn)     # theta_D in theta (empty without)
        self.default_theta = np.concatenate([self.movement.get_theta(), np.zeros(n_dyn)])
        # range policy of a rollout: an entry this far from the default is an absurd magnitude
        self.theta_bound = THETA_SPREADS * max(1.0, float(np.max(np.abs(self.default_theta))))

    @property
    def num_parameters(self) -> int:
        return self.default_theta.size

    @property
    def has_feedforward(self) -> bool:
        return self.feedforward is not None

    def with_feedforward(self, theta: np.ndarray, theta_d: np.ndarray) -> np.ndarray:
        """theta with its theta_D block replaced (theta_K kept). Raises ValueError for a task
        without feed-forward or sizes that do not fit."""
        if self.feedforward is None:
            raise ValueError(f'task {self.task.name!r} has no feed-forward (policy.feedforward)')
        theta = np.array(theta, dtype=float)
        theta_d = np.asarray(theta_d, dtype=float).reshape(-1)
        n_dyn = self.feedforward.num_parameters
        if theta.shape != self.default_theta.shape or theta_d.size != n_dyn:
            raise ValueError(f'theta needs {self.num_parameters} and theta_D '
                             f'{n_dyn} entries')
        theta[self.dynamics] = theta_d
        return theta

    def reference(self, theta: np.ndarray) -> Reference:
        """The commanded trajectory for theta over one episode. Raises ValueError for a
        theta of the wrong size or with NaN/inf."""
        theta = np.asarray(theta, dtype=float)
        if theta.shape != self.default_theta.shape:
            raise ValueError(f'task {self.task.name!r} takes theta with '
                             f'{self.num_parameters} entries, got {theta.size}')
        if not np.all(np.isfinite(theta)):
            raise ValueError('theta contains NaN or inf')
        far = np.abs(theta - self.default_theta) > self.theta_bound
        if np.any(far):
            i = int(np.flatnonzero(far)[0])
            raise ValueError(f'theta[{i}] = {theta[i]:g} lies more than {self.theta_bound:g} '
                             f'from the default policy ({self.default_theta[i]:g}) of task '
                             f'{self.task.name!r}: a units or scaling error')
        self.movement.set_theta(theta[self.kinematics])
        dt = self.task.control_period
        traj = self.movement.integrate(dt, self.task.num_steps * dt)
        u_ffwd = (self.feedforward.signal(theta[self.dynamics], traj.t)
                  if self.feedforward is not None else np.zeros_like(traj.y))
        return Reference(t=traj.t, q=traj.y, qd=traj.yd, u_ffwd=u_ffwd)


@functools.lru_cache(maxsize=16)
def policy_for(task: TaskDefinition) -> TaskPolicy:
    return TaskPolicy(task)
