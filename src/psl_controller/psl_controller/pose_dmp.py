"""Pose DMP: the hand's position and orientation as two attractors on one phase.

Ude, Nemec, Petric and Morimoto (2014) move a Cartesian pose with a position DMP (eq. 2.23-
2.24 per axis, :class:`psl_controller.dmp.DMP` over the 3-D position) and an orientation DMP
on unit quaternions (their eq. 16-17, :class:`psl_controller.quaternion_dmp.QuaternionDMP`)
that share the canonical system, so that both reach their goals together and one time scale
stretches both. This class couples the two and gives the pair the interface the task's policy
uses for a movement (:class:`psl_controller.policy.TaskPolicy`):

    theta_K = [position weights (3 K), position goal (3)          (learn_goal)
               orientation weights (3 K), goal rotation vector (3)]   (learn_goal)

the goal rotation vector r relative to the default goal g0 (the demonstration's last
orientation): g = exp(r) * g0 (``QuaternionDMP``). Without ``learn_goal`` the two goal blocks
are absent. `integrate` returns a :class:`PoseTrajectory` on the control grid; a goal change
(`integrate_goal_change`) moves the position goal and, given a new orientation too, turns the
orientation goal with the same goal filter.

Imports no ROS.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psl_controller.dmp import DMP, DMPTrajectory
from psl_controller.quaternion_dmp import QuaternionDMP


@dataclass(frozen=True, eq=False)
class PoseTrajectory(DMPTrajectory):
    """Sampled pose DMP output: t (N+1,); the position y, yd, ydd (..., N+1, 3) [m, m/s,
    m/s^2] as `DMPTrajectory`; the orientation quat (..., N+1, 4) (unit quaternions [w, x, y,
    z]) and omega (..., N+1, 3) [rad/s, base frame]."""

    quat: np.ndarray = None
    omega: np.ndarray = None


class PoseDMP:
    """A 3-D position DMP and an orientation DMP on the same phase (module docstring).

    Args:
        position: the position DMP (n_dims 3).
        orientation: the orientation DMP, with the position DMP's duration, number of basis
            functions, canonical system, time scale and ``learn_goal``.

    Raises:
        ValueError: a position DMP that is not 3-D, or two DMPs on different phases.
    """

    def __init__(self, position: DMP, orientation: QuaternionDMP):
        if position.n_dims != 3:
            raise ValueError(f'the position DMP of a pose must be 3-D, got {position.n_dims}')
        for name in ('duration', 'n_basis', 'time_scale', 'learn_goal'):
            if getattr(position, name) != getattr(orientation, name):
                raise ValueError(f'the position and orientation DMPs of a pose need the same '
                                 f'{name}: {getattr(position, name)!r} and '
                                 f'{getattr(orientation, name)!r}')
        if type(position.canonical) is not type(orientation.canonical):
            raise ValueError('the position and orientation DMPs of a pose need the same '
                             'canonical system')
        self.position, self.orientation = position, orientation
        n_position = position.num_parameters
        self._split = n_position
        # the learned goals in theta (empty slices without learn_goal)
        self.position_goal = slice(position.num_weights, n_position)
        self.orientation_goal = slice(n_position + orientation.num_weights,
                                      n_position + orientation.num_parameters)

    @property
    def num_parameters(self) -> int:
        return self.position.num_parameters + self.orientation.num_parameters

    @property
    def n_dims(self) -> int:
        """The size of a goal change's new goal: the hand point (3,)."""
        return 3

    def get_theta(self) -> np.ndarray:
        return np.concatenate([self.position.get_theta(), self.orientation.get_theta()])

    def set_theta(self, theta) -> None:
        """Set both DMPs' parameters from the flat theta_K (module docstring).

        Raises:
            ValueError: a theta of the wrong size or not finite.
        """
        theta = np.asarray(theta, dtype=float).reshape(-1)
        if theta.size != self.num_parameters:
            raise ValueError(f'a pose DMP takes theta with {self.num_parameters} entries '
                             f'({self.position.num_parameters} position, '
                             f'{self.orientation.num_parameters} orientation), got {theta.size}')
        self.position.set_theta(theta[:self._split])
        self.orientation.set_theta(theta[self._split:])

    def fit(self, t: np.ndarray, y: np.ndarray, quat: np.ndarray, dt: float) -> 'PoseDMP':
        """Fit both DMPs to a demonstrated pose path: positions y (T, 3), orientations
        quat (T, 4) at times t (T,) (`DMP.fit`, `QuaternionDMP.fit`)."""
        self.position.fit(t, y, dt)
        self.orientation.fit(t, quat, dt)
        return self

    def integrate(self, dt: float, t_end: float | None = None) -> PoseTrajectory:
        """Both DMPs on the grid t = k dt, k = 0..round(t_end / dt)."""
        return self._pose(self.position.integrate(dt, t_end),
                          self.orientation.integrate(dt, t_end))

    def integrate_population(self, dt: float, thetas: np.ndarray,
                             t_end: float | None = None) -> PoseTrajectory:
        """`integrate` for P thetas (P, num_parameters) at once: arrays with a leading
        population axis (`DMP.integrate_population`, `QuaternionDMP.integrate_population`)."""
        thetas = np.asarray(thetas, dtype=float)
        if thetas.ndim != 2 or thetas.shape[1] != self.num_parameters:
            raise ValueError(f'thetas must be (P, {self.num_parameters}), got {thetas.shape}')
        return self._pose(self.position.integrate_population(dt, thetas[:, :self._split], t_end),
                          self.orientation.integrate_population(dt, thetas[:, self._split:],
                                                                t_end))

    def integrate_goal_change(self, dt: float, t_switch: float, new_goal,
                              t_end: float | None = None) -> PoseTrajectory:
        """`integrate` with the goal changing from ``t_switch`` on: ``new_goal`` (3,) the
        hand point [m] (`DMP.integrate_goal_change`; the orientation as integrated), or (7,)
        the point and the hand's orientation as a unit quaternion [w, x, y, z], which turns
        with the same goal filter (`QuaternionDMP.integrate_goal_change`).

        Raises:
            ValueError: a new goal of another size, not finite, or a quaternion part that is
            not of unit norm; the errors of the two DMPs' goal changes.
        """
        new_goal = np.atleast_1d(np.asarray(new_goal, dtype=float))
        if new_goal.shape not in ((3,), (7,)):
            raise ValueError(f'a pose goal is the hand point (3 values) or the point and a unit '
                             f'quaternion [w, x, y, z] (7 values), got {new_goal.size}')
        position = self.position.integrate_goal_change(dt, t_switch, new_goal[:3], t_end)
        orientation = (self.orientation.integrate(dt, t_end) if new_goal.size == 3 else
                       self.orientation.integrate_goal_change(
                           dt, t_switch, new_goal[3:], t_end, self.position.alpha_goal))
        return self._pose(position, orientation)

    @staticmethod
    def _pose(position: DMPTrajectory, orientation) -> PoseTrajectory:
        return PoseTrajectory(t=position.t, y=position.y, yd=position.yd, ydd=position.ydd,
                              quat=orientation.q, omega=orientation.omega)
