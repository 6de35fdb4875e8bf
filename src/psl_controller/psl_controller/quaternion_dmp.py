"""Orientation DMP on unit quaternions (Ude et al. 2014), on the phase of the position DMP.

Ude, Nemec, Petric and Morimoto (2014, Sec. III) write the point attractor of eq. 2.23 for an
orientation: a unit quaternion q ``[w, x, y, z]`` (body to base frame) with the angular
velocity omega (base frame, rad/s) and its scaled form ``eta = tau omega``::

    tau eta_dot = k_s 2 log(g * conj(q)) - k_d eta + f(t)                        (eq. 16)
    tau q_dot   = 1/2 eta * q                                                    (eq. 17)

where ``*`` is the quaternion product, eta enters the product as the pure quaternion
``[0, eta]`` and ``2 log(g * conj(q))`` is the rotation vector that turns q into the goal g
(:func:`psl_task.quaternion.log_map`, the shorter way). The paper's gains
``alpha_z (beta_z 2 log(...) - eta)`` are ``k_s = alpha_z beta_z``, ``k_d = alpha_z``; tau is
:class:`~psl_controller.dmp.DMP`'s ``time_scale``, so that per axis, near the goal, the system
is eq. 2.23 with the same gains: ``tau^2 omega_dot = k_s e - k_d tau omega + f``.

The forcing term has one row of weights per rotation axis j = 1..3, on the same
:class:`CanonicalSystem` and :class:`NormalizedGaussianBasis` as :class:`DMP`, with its gate::

    f_j(t) = gate(t) * sum_k psi_k(x(t)) theta_jk / sum_k psi_k(x(t))            (eq. 2.24)

The paper scales f by ``D_o = diag(2 log(g * conj(q0)))`` and gates it with the phase; like
:class:`DMP` here, this module does not scale by the start-goal offset, and its gate is the
canonical system's (exactly 0 from ``duration`` on).

Integration on the grid t = k dt, the paper's step ``q(t + dt) = exp(dt/2 eta / tau) * q(t)``
with the rotation the step actually turns: the forcing is held over each step at its value at
the step's start, and within the step the rotation error is taken as ``e_k - d(t)``, with d the
rotation vector turned since the step's start (``d_dot = omega``). Per axis this is eq. 2.23's
linear system, advanced exactly with the zero-order-hold discretisation
``expm([[A, B], [0, 0]] dt) = [[A_d, B_d], [0, 1]]``, ``A = [[0, 1], [-k_s, -k_d tau] / tau^2]``,
``B = [0, 1]``, as :class:`DMP` does::

    e_k         = log_map(g * conj(q_k))
    u_k         = (k_s e_k + f_k) / tau^2                      (acceleration input of the step)
    omega_dot_k = u_k - k_d omega_k / tau                      (eq. 16 at grid point k)
    [d_k, omega_{k+1}] = A_d [0, omega_k] + B_d u_k
    q_{k+1}     = exp_map(d_k) * q_k                (the paper's exp(d_k / 2), exact unit norm)

About one fixed axis (zero weights, or forcing along the start-goal axis) the error stays on
that axis and this is :class:`DMP`'s exact integration of the angle; in general the error's
change within a step is linearised, which is first order in dt.

Fitting (the paper's forcing targets, eq. 16 solved for f): the demonstration, resampled on the
grid along great circles, gives the rotations of the steps ``d_k = log_map(q_{k+1} * conj(q_k))``;
from rest (omega_0 = 0), each step's input ``u_k = (d_k - A_d[0, 1] omega_k) / B_d[0]`` and
``omega_{k+1} = A_d[1, 1] omega_k + B_d[1] u_k`` invert the integration step, and the targets
are ``f_k = tau^2 u_k - k_s log_map(g * conj(q_k))``: a forcing equal to them reproduces the
resampled demonstration exactly. The weights solve a ridge problem over the gated basis, with
the penalty and solver of :meth:`DMP.fit`.

Equation numbers are those of the paper as far as known (eq. 16 is the number the literature
cites for the transformation system); every equation is written out above, so the code can be
checked without them. Eq. 2.23-2.24 are those of :mod:`psl_controller.dmp`. Numpy and scipy
(the matrix exponential, as in :mod:`psl_controller.dmp`); no ROS.

References
----------
Ude, A., Nemec, B., Petric, T., Morimoto, J. (2014). Orientation in Cartesian space dynamic
movement primitives. IEEE International Conference on Robotics and Automation (ICRA),
2997-3004. doi:10.1109/ICRA.2014.6907291
"""

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from psl_task import quaternion
from psl_controller.dmp import GatedAttractor

AXES = 3  # one forcing row per rotation axis

# Named entries of the per-axis state [d, omega] of a step (d: rotation turned in the step).
ROT = 0
VEL = 1

_MAX_CACHE_ENTRIES = 8


@dataclass(frozen=True, eq=False)
class QuaternionTrajectory:
    """Sampled orientation DMP output: t (N+1,); q (..., N+1, 4) unit quaternions;
    omega (..., N+1, 3) angular velocity [rad/s] and omega_dot (..., N+1, 3) angular
    acceleration [rad/s^2], both in the base frame. The leading axis is the population's."""

    t: np.ndarray
    q: np.ndarray
    omega: np.ndarray
    omega_dot: np.ndarray


class QuaternionDMP(GatedAttractor):
    """Unit-quaternion point attractor with gated normalised-Gaussian forcing (Ude et al.
    2014, eq. 16-17; forcing per axis as eq. 2.24).

    Args:
        n_basis: number of Gaussians K per rotation axis, >= 1.
        duration: motion duration in seconds; the forcing term is exactly 0 afterwards.
        q0: start orientation [w, x, y, z], unit; the start angular velocity is zero.
        goal: default goal orientation [w, x, y, z], unit.
        k_s: spring constant (> 0), as :class:`DMP`'s.
        k_d: damping constant (>= 0); default ``2 sqrt(k_s)`` (critically damped near the
            goal), as :class:`DMP`'s.
        canonical: canonical system kind, ``"linear"`` or ``"exponential"``.
        learn_goal: theta holds the weights and then the goal as a rotation vector r relative
            to the default goal, ``goal = exp_map(r) * default_goal``; else the weights only.
        time_scale: tau > 0 of eq. 16-17; the same theta gives the same path tau times slower
            (with ``duration`` stretched by tau, as for :class:`DMP`).

    Quaternions within ``quaternion.UNIT_TOLERANCE`` of unit norm are accepted and normalised.

    Raises:
        ValueError: invalid sizes, gains, canonical kind, or a start or goal that is not a
        finite unit quaternion.
    """

    def __init__(self, n_basis: int, duration: float, q0, goal, k_s: float = 400.0,
                 k_d: float | None = None, canonical: str = 'linear',
                 learn_goal: bool = False, time_scale: float = 1.0) -> None:
        super().__init__(n_basis, duration, k_s, k_d, canonical, learn_goal, time_scale)
        self._q0 = quaternion.as_unit_quaternion(q0, 'q0')
        self._default_goal = quaternion.as_unit_quaternion(goal, 'goal')
        self._goal_offset = np.zeros(AXES)  # rotation vector, learned when learn_goal
        self._theta = np.zeros((AXES, self._basis.n_basis))  # (3, K)
        self._steps: dict[float, tuple[np.ndarray, np.ndarray]] = {}  # dt -> (A_d, B_d)

    # -- constants ----------------------------------------------------------------------------
    @property
    def num_weights(self) -> int:
        return AXES * self._basis.n_basis

    @property
    def num_parameters(self) -> int:
        return self.num_weights + (AXES if self._learn_goal else 0)

    # -- changing state -----------------------------------------------------------------------
    @property
    def q0(self) -> np.ndarray:
        return self._q0.copy()

    @q0.setter
    def q0(self, value) -> None:
        self._q0 = quaternion.as_unit_quaternion(value, 'q0')

    @property
    def default_goal(self) -> np.ndarray:
        """The goal that theta's goal part is relative to (the constructor's ``goal``)."""
        return self._default_goal.copy()

    @default_goal.setter
    def default_goal(self, value) -> None:
        self._default_goal = quaternion.as_unit_quaternion(value, 'goal')

    @property
    def goal(self) -> np.ndarray:
        """The attractor g: ``exp_map(r) * default_goal`` with theta's goal part r (r = 0
        without learn_goal)."""
        return quaternion.product(quaternion.exp_map(self._goal_offset), self._default_goal)

    def get_theta(self) -> np.ndarray:
        """Flat weights, shape (3 * n_basis,), row-major over (3 axes, n_basis), then the goal
        as a rotation vector relative to the default goal (3,) when the goal is learned."""
        weights = self._theta.reshape(-1)
        return (np.concatenate([weights, self._goal_offset]) if self._learn_goal
                else weights.copy())

    def set_theta(self, theta) -> None:
        """Set the flat weights (row-major over (3 axes, n_basis)), then the goal rotation
        vector relative to the default goal when the goal is learned.

        Raises:
            ValueError: wrong size or non-finite entries.
        """
        theta = np.asarray(theta, dtype=float).reshape(-1)
        if theta.size != self.num_parameters:
            goal = f' + {AXES} (goal)' if self._learn_goal else ''
            raise ValueError(f'theta must have {self.num_parameters} = 3 axes * n_basis{goal} '
                             f'= 3 * {self.n_basis}{goal} entries, got {theta.size}')
        if not np.all(np.isfinite(theta)):
            raise ValueError('theta must be finite (found NaN or inf)')
        self._theta = theta[:self.num_weights].reshape(AXES, self.n_basis).copy()
        if self._learn_goal:
            self._goal_offset = theta[self.num_weights:].copy()

    # -- evaluation ---------------------------------------------------------------------------
    def forcing(self, t: np.ndarray) -> np.ndarray:
        """Forcing term f(t) of eq. 16, per axis as eq. 2.24 (gated), shape (T, 3) for t (T,)."""
        t = np.atleast_1d(np.asarray(t, dtype=float)).reshape(-1)  # (T,)
        return self._forcing_basis(t) @ self._theta.T

    def integrate(self, dt: float, t_end: float | None = None) -> QuaternionTrajectory:
        """Integrate eq. 16-17 from (q0, omega = 0) on the grid t = k dt, k = 0..N,
        N = round(t_end / dt): forcing held over each step, the step's linear system advanced
        exactly and q turned by the exponential map (module docstring). ``omega_dot`` at a
        grid point is eq. 16 at that point.

        Args:
            dt: step in seconds (> 0).
            t_end: end time in seconds (>= 0); default ``duration``.

        Returns:
            t (N+1,); q (N+1, 4); omega, omega_dot (N+1, 3).
        """
        t, phi = self._grid(dt, t_end)
        q, omega, omega_dot = self._rollout(dt, phi, self._theta[None], self.goal[None])
        return QuaternionTrajectory(t=t, q=q[0], omega=omega[0], omega_dot=omega_dot[0])

    def integrate_population(self, dt: float, thetas: np.ndarray,
                             t_end: float | None = None) -> QuaternionTrajectory:
        """`integrate` for P thetas at once (the DMP's own theta is not changed): one time loop,
        each step vectorised over the population; q (P, N+1, 4), omega and omega_dot
        (P, N+1, 3), row p `integrate` after ``set_theta(thetas[p])`` within rounding (numpy's
        loops may take other SIMD paths for arrays of another length).

        Args:
            dt: step in seconds (> 0).
            thetas: (P, num_parameters), each laid out as `set_theta` takes it.
            t_end: end time in seconds (>= 0); default ``duration``.

        Raises:
            ValueError: thetas not (P, num_parameters) or not finite, or the errors of
            `integrate`.
        """
        thetas = self._population(thetas)
        weights = thetas[:, :self.num_weights].reshape(len(thetas), AXES, self.n_basis)
        if self._learn_goal:
            goals = quaternion.product(quaternion.exp_map(thetas[:, self.num_weights:]),
                                       self._default_goal)  # (P, 4)
        else:
            goals = np.broadcast_to(self.goal, (len(thetas), 4))
        t, phi = self._grid(dt, t_end)
        q, omega, omega_dot = self._rollout(dt, phi, weights, goals)
        return QuaternionTrajectory(t=t, q=q, omega=omega, omega_dot=omega_dot)

    def integrate_goal_change(self, dt: float, t_switch: float, new_goal,
                              t_end: float | None = None, alpha_goal: float = 10.0
                              ) -> QuaternionTrajectory:
        """`integrate` with the goal turning smoothly to ``new_goal`` from ``t_switch`` on:
        the first-order goal filter of `DMP.integrate_goal_change` (Ijspeert et al. 2013) on
        the sphere, ``tau gdot = alpha_goal 2 log(g_new * conj(g))`` (the rotation toward the
        new goal, in the base frame), whose solution turns about one fixed axis::

            g(t) = exp_map((1 - exp(-alpha_goal (t - t_s) / tau)) r) * g,
            r = log_map(g_new * conj(g)),  t >= t_s

        held over each step like the forcing. g is continuous, and with it q and omega; up to
        the grid point after ``t_s`` the result is bit for bit that of `integrate`.

        Args:
            dt: step in seconds (> 0).
            t_switch: when the goal starts turning, seconds from the start, in [0, t_end].
            new_goal: unit quaternion [w, x, y, z].
            t_end: end time in seconds (>= 0); default ``duration``.
            alpha_goal: rate of the goal filter (> 0; the position DMP's, for a pose).

        Raises:
            ValueError: a new goal that is not a finite unit quaternion, a switch time outside
            [0, t_end], alpha_goal not > 0, or the errors of `integrate`.
        """
        new_goal = quaternion.as_unit_quaternion(new_goal, 'new_goal')
        if not (np.isfinite(alpha_goal) and alpha_goal > 0.0):
            raise ValueError(f'alpha_goal must be finite and > 0, got {alpha_goal!r}')
        t, phi = self._grid(dt, t_end)
        if not (np.isfinite(t_switch) and 0.0 <= t_switch <= t[-1] * (1.0 + 1e-12)):
            raise ValueError(f't_switch must lie in [0, {t[-1]:g}] s (the integrated span), '
                             f'got {t_switch!r}')
        k_s = min(len(t) - 1, int(np.ceil(t_switch / dt - 1e-9)))
        goal = self.goal
        turn = quaternion.log_map(quaternion.product(new_goal, quaternion.conjugate(goal)))
        share = np.zeros(len(t))
        share[k_s:] = 1.0 - np.exp(-alpha_goal * (t[k_s:] - t[k_s]) / self._time_scale)
        goals = quaternion.product(quaternion.exp_map(share[:, None] * turn), goal)  # (N+1, 4)
        goals[:k_s + 1] = goal                  # exactly the goal of `integrate` up to t_s
        q, omega, omega_dot = self._rollout(dt, phi, self._theta[None], goals[None])
        return QuaternionTrajectory(t=t, q=q[0], omega=omega[0], omega_dot=omega_dot[0])

    def fit(self, t: np.ndarray, q: np.ndarray, dt: float,
            regularization: float = 1e-9) -> 'QuaternionDMP':
        """Fit the weights (and the goal when learned) to a demonstration of orientations.

        The demonstration is resampled along great circles (:func:`quaternion.interpolate`) on
        the integration grid t = k dt, k = 0..round(duration / dt); q0 is set to its first
        resampled orientation and the goal to its last: the default goal without learn_goal,
        else theta's goal part ``log_map(q_end * conj(default_goal))`` (the default goal
        stays). The forcing targets f_k (module docstring: eq. 16 solved for f, with the
        angular velocities and accelerations that invert the integration step) give the
        weights of each axis j by the ridge problem
        ``min ||Phi theta_j - f_j||^2 + regularization ||theta_j||^2``,
        ``Phi = gate(t) * activations(phase(t))`` (N+1, K).

        Args:
            t: demonstration times in seconds, shape (T,), strictly increasing, covering
                [0, duration].
            q: demonstration orientations [w, x, y, z], shape (T, 4), unit (either sign).
            dt: integration step in seconds (> 0).
            regularization: ridge penalty (>= 0).

        Returns:
            self.

        Raises:
            ValueError: bad shapes, non-finite values, quaternions that are not unit, or a
            demonstration not covering the grid.
        """
        t = np.asarray(t, dtype=float)
        q = np.asarray(q, dtype=float)
        if t.ndim != 1 or t.size < 2 or q.shape != (t.size, 4):
            raise ValueError(f't must have shape (T,) with T >= 2 and q shape (T, 4); '
                             f'got {t.shape} and {q.shape}')
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
            raise ValueError('demonstration must be finite')
        norms = np.linalg.norm(q, axis=1)
        worst = int(np.argmax(np.abs(norms - 1.0)))
        if abs(norms[worst] - 1.0) > quaternion.UNIT_TOLERANCE:
            raise ValueError(f'demonstration orientations must be unit quaternions (|q| within '
                             f'{quaternion.UNIT_TOLERANCE:g} of 1), got |q[{worst}]| = '
                             f'{norms[worst]:.9g}')
        if np.any(np.diff(t) <= 0.0):
            raise ValueError('demonstration times must be strictly increasing')
        if not (np.isfinite(regularization) and regularization >= 0.0):
            raise ValueError(f'regularization must be finite and >= 0, got {regularization!r}')
        grid, phi = self._grid(dt, None)
        tolerance = 1e-9 * max(1.0, self.duration)
        if t[0] > grid[0] + tolerance or t[-1] < grid[-1] - tolerance:
            raise ValueError(f'demonstration spans [{t[0]}, {t[-1]}] s but must cover the '
                             f'integration grid [0, {grid[-1]}] s')
        target = quaternion.interpolate(t, q / norms[:, None], grid)  # (N+1, 4)
        self._q0 = target[0].copy()
        if self._learn_goal:
            self._goal_offset = quaternion.log_map(
                quaternion.product(target[-1], quaternion.conjugate(self._default_goal)))
        else:
            self._default_goal = target[-1].copy()
        a_d, b_d = self._step(dt)
        turns = quaternion.log_map(
            quaternion.product(target[1:], quaternion.conjugate(target[:-1])))  # d_k: (N, 3)
        inputs = np.zeros((len(grid), AXES))  # u_k; the last row is gated out (gate = 0)
        omega = np.zeros(AXES)  # from rest
        for n, turn in enumerate(turns):
            inputs[n] = (turn - a_d[ROT, VEL] * omega) / b_d[ROT]
            omega = a_d[VEL, VEL] * omega + b_d[VEL] * inputs[n]
        error = quaternion.log_map(quaternion.product(self.goal, quaternion.conjugate(target)))
        forces = self._time_scale**2 * inputs - self._k_s * error  # f_k: (N+1, 3)
        forces[-1] = 0.0
        k = self.n_basis
        design = np.vstack([phi, np.sqrt(regularization) * np.eye(k)])  # (N+1+K, K)
        rhs = np.vstack([forces, np.zeros((k, AXES))])  # (N+1+K, 3)
        theta_t, *_ = np.linalg.lstsq(design, rhs, rcond=None)  # (K, 3)
        if not np.all(np.isfinite(theta_t)):
            raise ValueError('the fit to the demonstration is not finite')
        self._theta = theta_t.T.copy()
        return self

    # -- integration --------------------------------------------------------------------------
    def _forcing_basis(self, t: np.ndarray) -> np.ndarray:
        """gate(t) * activations(phase(t)), (T, K): f = this @ theta^T (eq. 2.24)."""
        return (self._canonical.gate(t)[:, None]
                * self._basis.activations(self._canonical.phase(t)))

    def _grid(self, dt: float, t_end: float | None) -> tuple[np.ndarray, np.ndarray]:
        """Grid t (N+1,) and forcing basis (N+1, K)."""
        if not (np.isfinite(dt) and dt > 0.0):
            raise ValueError(f'dt must be finite and > 0, got {dt!r}')
        if t_end is None:
            t_end = self.duration
        if not (np.isfinite(t_end) and t_end >= 0.0):
            raise ValueError(f't_end must be finite and >= 0, got {t_end!r}')
        t = np.arange(int(round(t_end / dt)) + 1) * float(dt)  # (N+1,)
        return t, self._forcing_basis(t)

    def _step(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """A_d (2, 2) and B_d (2,) of one step of the per-axis system [d, omega] (module
        docstring): zero-order hold, ``expm([[A, B], [0, 0]] dt) = [[A_d, B_d], [0, 1]]``."""
        key = float(dt)
        if key not in self._steps:
            if len(self._steps) >= _MAX_CACHE_ENTRIES:
                self._steps.pop(next(iter(self._steps)))
            tau = self._time_scale
            augmented = np.zeros((3, 3))
            augmented[ROT, VEL] = 1.0
            augmented[VEL, ROT] = -self._k_s / tau**2
            augmented[VEL, VEL] = -self._k_d / tau
            augmented[VEL, 2] = 1.0
            discrete = expm(augmented * key)
            self._steps[key] = (discrete[:2, :2], discrete[:2, 2])
        return self._steps[key]

    def _rollout(self, dt: float, phi: np.ndarray, weights: np.ndarray,
                 goals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q (P, N+1, 4), omega and omega_dot (P, N+1, 3) for weights (P, 3, K) and goals
        (P, 4), or (P, N+1, 4) a goal per grid point: one loop over time per row, in Python
        floats (a step is a few dozen scalar operations: numpy's per-call overhead on arrays
        of 3 and 4 would be ten times that),
        and the steps of a row do not depend on the other rows (only the forcing's matrix
        product is one for the population: BLAS may sum it in another order for another
        population size)."""
        count, n_points = len(weights), len(phi)
        tau = self._time_scale
        a_d, b_d = self._step(dt)
        constants = (self._k_s / tau**2, self._k_d / tau, 1.0 / tau**2, float(a_d[ROT, VEL]),
                     float(b_d[ROT]), float(a_d[VEL, VEL]), float(b_d[VEL]))
        forces = np.matmul(phi, weights.transpose(0, 2, 1))  # f of eq. 16: (P, N+1, 3)
        q = np.empty((count, n_points, 4))
        omega = np.empty((count, n_points, AXES))
        omega_dot = np.empty((count, n_points, AXES))
        for p in range(count):
            goal = goals[p].tolist()
            per_step = goal if goals.ndim == 3 else [goal] * n_points
            q[p], omega[p], omega_dot[p] = _rollout_row(
                constants, forces[p].tolist(), self._q0.tolist(), per_step)
        return q, omega, omega_dot


def _rollout_row(constants: tuple, forces: list, q0: list, goals: list
                 ) -> tuple[list, list, list]:
    """One row of `QuaternionDMP._rollout` (module docstring, "Integration"): the states
    of eq. 16-17 on the grid, from q0 at rest toward the goals (N+1 quaternions, one per grid
    point, held over its step), with the forcing forces (N+1 lists of 3). constants:
    (k_s / tau^2, k_d / tau, 1 / tau^2, A_d[0, 1], B_d[0], A_d[1, 1], B_d[1])."""
    ks_tau2, kd_tau, inv_tau2, a01, b0, a11, b1 = constants
    qw, qx, qy, qz = q0
    wx = wy = wz = 0.0                                  # omega, from rest
    q_out, omega_out, omega_dot_out = [], [], []
    last = len(forces) - 1
    for k, ((fx, fy, fz), (gw, gx, gy, gz)) in enumerate(zip(forces, goals)):
        q_out.append((qw, qx, qy, qz))
        omega_out.append((wx, wy, wz))
        # the error: log_map(g * conj(q)), the shorter way
        ew = gw * qw + gx * qx + gy * qy + gz * qz
        ex = qw * gx - gw * qx - (gy * qz - gz * qy)
        ey = qw * gy - gw * qy - (gz * qx - gx * qz)
        ez = qw * gz - gw * qz - (gx * qy - gy * qx)
        if ew < 0.0:
            ew, ex, ey, ez = -ew, -ex, -ey, -ez
        sv = math.sqrt(ex * ex + ey * ey + ez * ez)
        factor = 2.0 * math.atan2(sv, ew) / sv if sv > 0.0 else 0.0
        ux = ks_tau2 * factor * ex + inv_tau2 * fx      # u_k = (k_s e_k + f_k) / tau^2
        uy = ks_tau2 * factor * ey + inv_tau2 * fy
        uz = ks_tau2 * factor * ez + inv_tau2 * fz
        omega_dot_out.append((ux - kd_tau * wx, uy - kd_tau * wy, uz - kd_tau * wz))
        if k == last:
            break
        dx, dy, dz = a01 * wx + b0 * ux, a01 * wy + b0 * uy, a01 * wz + b0 * uz   # d_k
        wx, wy, wz = a11 * wx + b1 * ux, a11 * wy + b1 * uy, a11 * wz + b1 * uz
        # q <- exp_map(d_k) * q, renormalised against rounding
        angle = math.sqrt(dx * dx + dy * dy + dz * dz)
        half = math.sin(0.5 * angle) / angle if angle > 1e-8 else 0.5 - angle * angle / 48.0
        rw, rx, ry, rz = math.cos(0.5 * angle), half * dx, half * dy, half * dz
        nw = rw * qw - rx * qx - ry * qy - rz * qz
        nx = rw * qx + qw * rx + (ry * qz - rz * qy)
        ny = rw * qy + qw * ry + (rz * qx - rx * qz)
        nz = rw * qz + qw * rz + (rx * qy - ry * qx)
        norm = math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
        qw, qx, qy, qz = nw / norm, nx / norm, ny / norm, nz / norm
    return q_out, omega_out, omega_dot_out
