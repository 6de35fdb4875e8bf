"""Dynamic movement primitive (eq. 2.23-2.24), dmpbbo style: a transformation system composed
of a :class:`CanonicalSystem` and a :class:`NormalizedGaussianBasis`.

Per dimension d (eq. 2.23)::

    ydd = k_s (g - y) - k_d yd + f(t, theta_d)
    f(t, theta_d) = gate(t) * sum_k psi_k(x(t)) theta_dk / sum_k psi_k(x(t))     (eq. 2.24)

Integration is exact for piecewise-constant forcing: over each step of length dt the forcing is
held at its value at the start of the step, and the linear system is advanced with the
zero-order-hold discretisation from the matrix exponential. Because the system is linear, the
integrated positions are affine in theta, ``y = y_free + G theta``; ``G`` depends only on
(dt, number of steps) and is cached, so :meth:`DMP.integrate` is a few small matrix products.

A goal may change during the motion (:meth:`DMP.integrate_goal_change`): from the switch on,
the attractor follows a first-order goal filter toward the new goal (Ijspeert et al. 2013), an
input of the same linear system, so the path stays continuous up to its acceleration.

The ungated basis on the phase, ``basis.activations(canonical.phase(t))``, is exposed through
the ``canonical`` and ``basis`` properties so that a feed-forward torque signal can later be
encoded on the same basis. Pure numpy/scipy; no ROS.
"""

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from psl_controller.basis_functions import NormalizedGaussianBasis
from psl_controller.canonical_system import CanonicalSystem

# Named slices of the per-dimension state [y, yd] of the transformation system.
POS = 0
VEL = 1
_GOAL = 2  # the moving goal, in the state [y, yd, g] of a goal change

_MAX_CACHE_ENTRIES = 8


@dataclass(frozen=True, eq=False)
class DMPTrajectory:
    """Sampled DMP output: t (N+1,); y, yd, ydd (N+1, n_dims)."""

    t: np.ndarray
    y: np.ndarray
    yd: np.ndarray
    ydd: np.ndarray


@dataclass(frozen=True, eq=False)
class _GridResponse:
    """What depends only on (dt, n_steps): time grid, forcing basis and unit responses."""

    t: np.ndarray  # (N+1,)
    forcing_basis: np.ndarray  # gate(t) * activations(phase(t)): (N+1, K)
    free: np.ndarray  # response of [y - g, yd] to y0 - g = 1, theta = 0: (N+1, 2)
    gain: np.ndarray  # response of [y, yd] to a unit weight theta_k: (N+1, 2, K)


def _as_vector(value, n_dims: int, name: str) -> np.ndarray:
    vector = np.atleast_1d(np.asarray(value, dtype=float))
    if vector.shape != (n_dims,):
        raise ValueError(f'{name} must have shape ({n_dims},), got {vector.shape}')
    if not np.all(np.isfinite(vector)):
        raise ValueError(f'{name} must be finite, got {vector}')
    return vector


class GatedAttractor:
    """What every DMP of this package shares, whatever its output space (a vector here, an
    orientation in `psl_controller.quaternion_dmp`): the spring-damper gains, the temporal
    scaling, the canonical system (the phase and the gate) and the normalised Gaussian basis
    the forcing is encoded on, and whether theta holds the goal.

    Raises:
        ValueError: invalid gains, time scale, basis size or canonical kind.
    """

    def __init__(self, n_basis: int, duration: float, k_s: float, k_d: float | None,
                 canonical: str, learn_goal: bool, time_scale: float) -> None:
        if k_d is None:
            k_d = 2.0 * np.sqrt(k_s)
        if not (np.isfinite(k_s) and k_s > 0.0):
            raise ValueError(f'k_s must be finite and > 0, got {k_s!r}')
        if not (np.isfinite(k_d) and k_d >= 0.0):
            raise ValueError(f'k_d must be finite and >= 0, got {k_d!r}')
        if not (np.isfinite(time_scale) and time_scale > 0.0):
            raise ValueError(f'time_scale must be finite and > 0, got {time_scale!r}')
        self._k_s = float(k_s)
        self._k_d = float(k_d)
        self._learn_goal = bool(learn_goal)
        self._time_scale = float(time_scale)
        self._canonical = CanonicalSystem(duration, kind=canonical)
        self._basis = NormalizedGaussianBasis(n_basis)

    @property
    def n_basis(self) -> int:
        return self._basis.n_basis

    @property
    def duration(self) -> float:
        return self._canonical.duration

    @property
    def k_s(self) -> float:
        return self._k_s

    @property
    def k_d(self) -> float:
        return self._k_d

    @property
    def canonical(self) -> CanonicalSystem:
        return self._canonical

    @property
    def basis(self) -> NormalizedGaussianBasis:
        return self._basis

    @property
    def learn_goal(self) -> bool:
        return self._learn_goal

    @property
    def time_scale(self) -> float:
        return self._time_scale

    @property
    def num_parameters(self) -> int:
        raise NotImplementedError

    def _population(self, thetas) -> np.ndarray:
        """thetas as a finite (P, num_parameters) array; ValueError otherwise."""
        thetas = np.asarray(thetas, dtype=float)
        if thetas.ndim != 2 or thetas.shape[1] != self.num_parameters:
            raise ValueError(f'thetas must be (P, {self.num_parameters}), got {thetas.shape}')
        if not np.all(np.isfinite(thetas)):
            raise ValueError('thetas must be finite (found NaN or inf)')
        return thetas


class DMP(GatedAttractor):
    """Point-attractor DMP with gated normalised-Gaussian forcing (eq. 2.23-2.24).

    Args:
        n_dims: number of output dimensions (e.g. joints), >= 1.
        n_basis: number of Gaussians K per dimension, >= 1.
        duration: motion duration in seconds; the forcing term is exactly 0 afterwards.
        y0: start position, shape (n_dims,); the start velocity is zero.
        goal: attractor g, shape (n_dims,).
        k_s: spring constant (> 0).
        k_d: damping constant (>= 0); default ``2 sqrt(k_s)`` (critically damped).
        canonical: canonical system kind, ``"linear"`` or ``"exponential"``.
        learn_goal: the goal is part of theta: ``theta = [weights, goal]`` (dmpbbo's
            selectable parameters), else theta holds the weights only.
        time_scale: temporal scaling tau_s > 0 (Ijspeert et al.'s tau):
            ``tau_s^2 ydd = k_s (g - y) - k_d tau_s yd + f``; the same theta then gives the
            same path ``tau_s`` times slower. A DMP of duration T0 stretched to duration T
            has ``duration=T, time_scale=T / T0``.
        alpha_goal: rate [1/s] of the goal filter of a goal change (> 0; Ijspeert et al.'s
            alpha_g): ``tau_s gdot = alpha_goal (g_new - g)`` from the switch on (see
            :meth:`integrate_goal_change`). The default 10/s brings g within 1 % of g_new in
            0.46 s, slower than the transformation system (sqrt(k_s) = 20/s by default), so the
            filter, not the spring, sets how gently the path turns to the new goal.

    Raises:
        ValueError: invalid sizes, gains or canonical kind.
    """

    def __init__(self, n_dims: int, n_basis: int, duration: float, y0, goal,
                 k_s: float = 400.0, k_d: float | None = None,
                 canonical: str = 'linear', learn_goal: bool = False,
                 time_scale: float = 1.0, alpha_goal: float = 10.0) -> None:
        if isinstance(n_dims, bool) or int(n_dims) != n_dims or n_dims < 1:
            raise ValueError(f'n_dims must be an integer >= 1, got {n_dims!r}')
        super().__init__(n_basis, duration, k_s, k_d, canonical, learn_goal, time_scale)
        if not (np.isfinite(alpha_goal) and alpha_goal > 0.0):
            raise ValueError(f'alpha_goal must be finite and > 0, got {alpha_goal!r}')
        self._n_dims = int(n_dims)
        self._alpha_goal = float(alpha_goal)
        # Transformation system in error coordinates e = [y - g, yd]: edot = A e + B f, the
        # gains of the time-scaled system (k_s / tau_s^2, k_d / tau_s, forcing / tau_s^2).
        s2 = self._time_scale ** 2
        self._ks_eff, self._kd_eff = self._k_s / s2, self._k_d / self._time_scale
        self._a = np.array([[0.0, 1.0], [-self._ks_eff, -self._kd_eff]])  # (2, 2)
        self._b = np.array([0.0, 1.0 / s2])  # (2,)
        self._cache: dict[tuple[float, int], _GridResponse] = {}
        self._y0 = _as_vector(y0, self._n_dims, 'y0')
        self._goal = _as_vector(goal, self._n_dims, 'goal')
        self._theta = np.zeros((self._n_dims, self._basis.n_basis))  # (n_dims, K)

    # -- constants ----------------------------------------------------------------------------
    @property
    def n_dims(self) -> int:
        return self._n_dims

    @property
    def alpha_goal(self) -> float:
        return self._alpha_goal

    @property
    def num_weights(self) -> int:
        return self._n_dims * self._basis.n_basis

    @property
    def num_parameters(self) -> int:
        return self.num_weights + (self._n_dims if self._learn_goal else 0)

    # -- changing state -----------------------------------------------------------------------
    @property
    def y0(self) -> np.ndarray:
        return self._y0.copy()

    @y0.setter
    def y0(self, value) -> None:
        self._y0 = _as_vector(value, self._n_dims, 'y0')

    @property
    def goal(self) -> np.ndarray:
        return self._goal.copy()

    @goal.setter
    def goal(self, value) -> None:
        self._goal = _as_vector(value, self._n_dims, 'goal')

    def get_theta(self) -> np.ndarray:
        """Flat weights, shape (n_dims * n_basis,), row-major over (n_dims, n_basis), then
        the goal (n_dims,) when the goal is learned."""
        weights = self._theta.reshape(-1)
        return np.concatenate([weights, self._goal]) if self._learn_goal else weights.copy()

    def set_theta(self, theta) -> None:
        """Set the flat weights (row-major over (n_dims, n_basis)), then the goal when the
        goal is learned.

        Raises:
            ValueError: wrong size or non-finite entries.
        """
        theta = np.asarray(theta, dtype=float).reshape(-1)
        if theta.size != self.num_parameters:
            goal = f' + {self._n_dims} (goal)' if self._learn_goal else ''
            raise ValueError(f'theta must have {self.num_parameters} = n_dims * n_basis{goal} '
                             f'= {self._n_dims} * {self.n_basis}{goal} entries, got '
                             f'{theta.size}')
        if not np.all(np.isfinite(theta)):
            raise ValueError('theta must be finite (found NaN or inf)')
        self._theta = theta[:self.num_weights].reshape(self._n_dims, self.n_basis).copy()
        if self._learn_goal:
            self._goal = theta[self.num_weights:].copy()

    # -- evaluation ---------------------------------------------------------------------------
    def forcing(self, t: np.ndarray) -> np.ndarray:
        """Forcing term f(t, theta) of eq. 2.24 (gated), shape (T, n_dims) for t of shape (T,)."""
        t = np.atleast_1d(np.asarray(t, dtype=float)).reshape(-1)  # (T,)
        phi = self._basis.activations(self._canonical.phase(t))  # (T, K)
        return self._b[VEL] * self._canonical.gate(t)[:, None] * (phi @ self._theta.T)

    def point_attractor_solution(self, t: np.ndarray) -> DMPTrajectory:
        """Analytical solution of eq. 2.23 with theta = 0 and zero start velocity.

        ``[y - g, yd](t) = expm(A t) [y0 - g, 0]`` with ``A = [[0, 1], [-k_s, -k_d]]``; for the
        default critically damped gains this is ``g + (y0 - g)(1 + w t) exp(-w t)``, w = sqrt(k_s).

        Args:
            t: times in seconds, shape (T,), >= 0.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float)).reshape(-1)  # (T,)
        transition = expm(self._a[None, :, :] * t[:, None, None])  # (T, 2, 2)
        offset = self._y0 - self._goal  # (n_dims,)
        y = self._goal + transition[:, POS, POS, None] * offset  # (T, n_dims)
        yd = transition[:, VEL, POS, None] * offset  # (T, n_dims)
        ydd = self._ks_eff * (self._goal - y) - self._kd_eff * yd
        return DMPTrajectory(t=t, y=y, yd=yd, ydd=ydd)

    def integrate(self, dt: float, t_end: float | None = None) -> DMPTrajectory:
        """Integrate eq. 2.23 from (y0, 0) on the grid t = k dt, k = 0..N, N = round(t_end / dt).

        Exact for forcing held constant over each step at its value at the step's start
        (zero-order hold); ``ydd`` at a grid point uses the forcing at that point.

        Args:
            dt: step in seconds (> 0).
            t_end: end time in seconds (>= 0); default ``duration``.
        """
        grid = self._grid_response(dt, t_end)
        y, yd, ydd = self._response(grid, self._theta[None], self._goal[None])
        return DMPTrajectory(t=grid.t.copy(), y=y[0], yd=yd[0], ydd=ydd[0])

    def integrate_population(self, dt: float, thetas: np.ndarray,
                             t_end: float | None = None) -> DMPTrajectory:
        """`integrate` for B thetas at once (the DMP's own theta is not changed): y, yd, ydd
        of shape (B, N+1, n_dims), row b `integrate` after ``set_theta(thetas[b])`` within
        rounding: the products have other shapes, which BLAS may sum in another order, by CPU
        (docs/testing.md, "What is equal to what").

        Args:
            dt: step in seconds (> 0).
            thetas: (B, num_parameters), each laid out as `set_theta` takes it.
            t_end: end time in seconds (>= 0); default ``duration``.

        Raises:
            ValueError: thetas not (B, num_parameters) or not finite, or the errors of
            `integrate`.
        """
        thetas = self._population(thetas)
        weights = thetas[:, :self.num_weights].reshape(len(thetas), self._n_dims, self.n_basis)
        goals = (thetas[:, self.num_weights:] if self._learn_goal
                 else np.broadcast_to(self._goal, (len(thetas), self._n_dims)))
        grid = self._grid_response(dt, t_end)
        y, yd, ydd = self._response(grid, weights, goals)
        return DMPTrajectory(t=grid.t.copy(), y=y, yd=yd, ydd=ydd)

    def _response(self, grid: '_GridResponse', weights: np.ndarray,
                  goals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """y, yd, ydd (B, N+1, n_dims) on the grid for weights (B, n_dims, K) and goals
        (B, n_dims): the affine solution ``y = y_free + G theta`` and eq. 2.23 for ydd.

        Computed with the population's dimensions side by side, (N+1, B n_dims), so every
        product is one matrix product and every sum runs along long rows; the results are
        then laid out (B, N+1, n_dims), contiguous."""
        count = len(weights)
        goal = goals.reshape(1, -1)  # (1, B n_dims)
        offset = (self._y0 - goals).reshape(1, -1)
        theta_t = weights.reshape(-1, self.n_basis).T  # (K, B n_dims)
        y = goal + grid.free[:, POS, None] * offset + grid.gain[:, POS, :] @ theta_t
        yd = grid.free[:, VEL, None] * offset + grid.gain[:, VEL, :] @ theta_t
        ydd = (self._ks_eff * (goal - y) - self._kd_eff * yd
               + self._b[VEL] * (grid.forcing_basis @ theta_t))  # (N+1, B n_dims)
        return tuple(np.ascontiguousarray(x.reshape(len(x), count, self._n_dims)
                                          .transpose(1, 0, 2)) for x in (y, yd, ydd))

    def integrate_goal_change(self, dt: float, t_switch: float, new_goal,
                              t_end: float | None = None) -> DMPTrajectory:
        """`integrate` with the goal moving smoothly to ``new_goal`` from ``t_switch`` on.

        From the switch time ``t_s = k_s dt``, the first grid time at or after ``t_switch``, the
        attractor of eq. 2.23 is no longer constant but the output of a first-order goal
        filter (Ijspeert et al. 2013, the goal change of a DMP; dmpbbo's delayed goal)::

            tau_s^2 ydd = k_s (g - y) - k_d tau_s yd + f,    tau_s gdot = alpha_goal (g_new - g),
            g(t_s) = goal

        so g is continuous, and with it y, yd and ydd (only the jerk changes at t_s). The goal
        is one more input of the same linear system; since the system is linear, the path is
        the unchanged path plus ``(g_new - goal) r(t - t_s)``, where r is the response of
        ``[y, yd, g]`` to a unit step of the filter's target from rest, discretised exactly
        (matrix exponential; the target is constant, the forcing is held as in `integrate`).
        Up to and including ``t_s`` the result is bit for bit that of `integrate`.

        Args:
            dt: step in seconds (> 0).
            t_switch: when the goal starts moving, seconds from the start, in [0, t_end].
            new_goal: the goal the attractor moves to, shape (n_dims,).
            t_end: end time in seconds (>= 0); default ``duration``.

        Returns:
            The trajectory on the grid of `integrate` (its ``ydd`` uses the moving goal).

        Raises:
            ValueError: a new goal of the wrong shape or not finite, a switch time that is not
            finite or outside [0, t_end], or the errors of `integrate`.

        References
        ----------
        Ijspeert, A. J., Nakanishi, J., Hoffmann, H., Pastor, P., Schaal, S. (2013). Dynamical
        movement primitives: learning attractor models for motor behaviors. Neural
        Computation 25(2), 328-373. doi:10.1162/NECO_a_00393
        """
        new_goal = _as_vector(new_goal, self._n_dims, 'new_goal')
        base = self.integrate(dt, t_end)
        n_steps = len(base.t) - 1
        if not (np.isfinite(t_switch) and 0.0 <= t_switch <= n_steps * dt * (1.0 + 1e-12)):
            raise ValueError(f't_switch must lie in [0, {n_steps * dt:g}] s (the integrated '
                             f'span), got {t_switch!r}')
        k_s = min(n_steps, int(np.ceil(t_switch / dt - 1e-9)))
        response = self._goal_step_response(dt, n_steps - k_s)  # (N+1-k_s, 3)
        change = new_goal - self._goal  # (n_dims,)
        # [y, yd, ydd] of the unit response; its g column only enters ydd
        r_acc = (self._ks_eff * (response[:, _GOAL] - response[:, POS])
                 - self._kd_eff * response[:, VEL])
        y, yd, ydd = base.y.copy(), base.yd.copy(), base.ydd.copy()
        after = slice(k_s + 1, None)  # rows up to t_s stay as integrated
        y[after] += response[1:, POS, None] * change
        yd[after] += response[1:, VEL, None] * change
        ydd[after] += r_acc[1:, None] * change
        return DMPTrajectory(t=base.t, y=y, yd=yd, ydd=ydd)

    def fit(self, t: np.ndarray, y: np.ndarray, dt: float,
            regularization: float = 1e-9) -> 'DMP':
        """Fit theta to a demonstration so that ``integrate(dt)`` reproduces its positions.

        The demonstration is resampled (linear interpolation) on the integration grid
        t = k dt, k = 0..round(duration / dt); y0 and goal are set to its first and last
        resampled values. Since the integrated positions are affine in theta,
        ``y = y_free + G theta``, theta solves the ridge problem
        ``min ||G theta_d - (y_d - y_free_d)||^2 + regularization ||theta_d||^2`` per dimension.

        Args:
            t: demonstration times in seconds, shape (T,), strictly increasing, covering
                [0, duration].
            y: demonstration positions, shape (T, n_dims) (or (T,) when n_dims = 1).
            dt: integration step in seconds (> 0).
            regularization: ridge penalty (>= 0).

        Returns:
            self.

        Raises:
            ValueError: bad shapes, non-finite values, or a demonstration not covering the grid.
        """
        t = np.asarray(t, dtype=float)
        y = np.asarray(y, dtype=float)
        if y.ndim == 1 and self._n_dims == 1:
            y = y[:, None]
        if t.ndim != 1 or t.size < 2 or y.shape != (t.size, self._n_dims):
            raise ValueError(f't must have shape (T,) with T >= 2 and y shape '
                             f'(T, {self._n_dims}); got {t.shape} and {y.shape}')
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
            raise ValueError('demonstration must be finite')
        if np.any(np.diff(t) <= 0.0):
            raise ValueError('demonstration times must be strictly increasing')
        if not (np.isfinite(regularization) and regularization >= 0.0):
            raise ValueError(f'regularization must be finite and >= 0, got {regularization!r}')
        grid = self._grid_response(dt, None)
        tolerance = 1e-9 * max(1.0, self.duration)
        if t[0] > grid.t[0] + tolerance or t[-1] < grid.t[-1] - tolerance:
            raise ValueError(f'demonstration spans [{t[0]}, {t[-1]}] s but must cover the '
                             f'integration grid [0, {grid.t[-1]}] s')
        target = np.column_stack([np.interp(grid.t, t, y[:, d])
                                  for d in range(self._n_dims)])  # (N+1, n_dims)
        self._y0 = target[0].copy()
        self._goal = target[-1].copy()
        y_free = self._goal + grid.free[:, POS, None] * (self._y0 - self._goal)  # (N+1, n_dims)
        gain = grid.gain[:, POS, :]  # G: (N+1, K)
        k = self.n_basis
        design = np.vstack([gain, np.sqrt(regularization) * np.eye(k)])  # (N+1+K, K)
        rhs = np.vstack([target - y_free, np.zeros((k, self._n_dims))])  # (N+1+K, n_dims)
        theta_t, *_ = np.linalg.lstsq(design, rhs, rcond=None)  # (K, n_dims)
        if not np.all(np.isfinite(theta_t)):
            raise ValueError('the fit to the demonstration is not finite')
        self._theta = theta_t.T.copy()          # the weights; the goal was set above
        return self

    # -- cached discretisation ----------------------------------------------------------------
    def _grid_response(self, dt: float, t_end: float | None) -> _GridResponse:
        if not (np.isfinite(dt) and dt > 0.0):
            raise ValueError(f'dt must be finite and > 0, got {dt!r}')
        if t_end is None:
            t_end = self.duration
        if not (np.isfinite(t_end) and t_end >= 0.0):
            raise ValueError(f't_end must be finite and >= 0, got {t_end!r}')
        key = (float(dt), int(round(t_end / dt)))
        if key not in self._cache:
            if len(self._cache) >= _MAX_CACHE_ENTRIES:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = self._compute_grid_response(*key)
        return self._cache[key]

    def _goal_step_response(self, dt: float, n_steps: int) -> np.ndarray:
        """[y, yd, g] (n_steps+1, 3) on the grid k dt of the transformation system with the
        goal filter, from rest (y = yd = g = 0) after a unit step of the filter's target:
        ``sdot = A_g s + b_g`` with ``A_g = [[0, 1, 0], [-k_s, -k_d, k_s], [0, 0, -a_g]]`` and
        ``b_g = [0, 0, a_g]`` (time-scaled gains, ``a_g = alpha_goal / tau_s``), advanced with
        the exact discretisation ``expm([[A_g, b_g], [0, 0]] dt)``."""
        a_g = self._alpha_goal / self._time_scale
        augmented = np.zeros((4, 4))
        augmented[:2, :2] = self._a
        augmented[VEL, _GOAL] = self._ks_eff
        augmented[_GOAL, _GOAL] = -a_g
        augmented[_GOAL, 3] = a_g
        discrete = expm(augmented * dt)
        a_d, b_d = discrete[:3, :3], discrete[:3, 3]  # (3, 3), (3,)
        state = np.zeros((n_steps + 1, 3))
        for n in range(n_steps):
            state[n + 1] = a_d @ state[n] + b_d
        return state

    def _compute_grid_response(self, dt: float, n_steps: int) -> _GridResponse:
        # Zero-order hold: expm([[A, B], [0, 0]] dt) = [[Ad, Bd], [0, 1]].
        augmented = np.zeros((3, 3))
        augmented[:2, :2] = self._a
        augmented[:2, 2] = self._b
        discrete = expm(augmented * dt)
        a_d = discrete[:2, :2]  # (2, 2)
        b_d = discrete[:2, 2]  # (2,)
        t = np.arange(n_steps + 1) * dt  # (N+1,)
        forcing_basis = (self._canonical.gate(t)[:, None]
                         * self._basis.activations(self._canonical.phase(t)))  # (N+1, K)
        # Columns of the state: 0 = free response to y0 - g = 1, 1..K = response to theta_k.
        state = np.zeros((n_steps + 1, 2, 1 + self.n_basis))  # (N+1, 2, 1+K)
        state[0, POS, 0] = 1.0
        for n in range(n_steps):
            state[n + 1] = a_d @ state[n]
            state[n + 1, :, 1:] += b_d[:, None] * forcing_basis[n]
        return _GridResponse(t=t, forcing_basis=forcing_basis,
                             free=state[:, :, 0].copy(), gain=state[:, :, 1:].copy())


def demonstration_from_waypoints(times, positions, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth demonstration through waypoints: clamped cubic spline (zero end velocities).

    Args:
        times: waypoint times in seconds, shape (W,), strictly increasing, W >= 2.
        positions: waypoint positions, shape (W, n_dims) or (W,).
        dt: sampling step in seconds (> 0).

    Returns:
        t: times[0] + k dt for k = 0..round((times[-1] - times[0]) / dt), shape (N+1,);
        y: spline positions, shape (N+1, n_dims) (grid times past times[-1] are clamped to it).

    Raises:
        ValueError: bad shapes, non-increasing times or non-positive dt.
    """
    times = np.asarray(times, dtype=float)
    positions = np.asarray(positions, dtype=float)
    if positions.ndim == 1:
        positions = positions[:, None]
    if times.ndim != 1 or times.size < 2 or positions.shape[0] != times.size:
        raise ValueError(f'need times (W,) with W >= 2 and positions (W, n_dims); '
                         f'got {times.shape} and {positions.shape}')
    if np.any(np.diff(times) <= 0.0):
        raise ValueError('waypoint times must be strictly increasing')
    if not (np.isfinite(dt) and dt > 0.0):
        raise ValueError(f'dt must be finite and > 0, got {dt!r}')
    from scipy.interpolate import CubicSpline   # here: 0.4 s of every process's start else
    spline = CubicSpline(times, positions, bc_type='clamped', axis=0)
    n_steps = int(round((times[-1] - times[0]) / dt))
    t = times[0] + np.arange(n_steps + 1) * dt  # (N+1,)
    return t, spline(np.minimum(t, times[-1]))
