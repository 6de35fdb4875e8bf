"""Differential inverse kinematics of a population of Cartesian paths, side by side.

`PopulationIK.solve` is `DifferentialIK.solve` (`psl_task.inverse_kinematics`: its module
docstring states the algorithm and its settings) with every sample solved (``knot_step`` 0:
no knots) for P paths x_ref (P, T, 3) at once: the
same damped least-squares step with the error-scaled damping of Sugihara (2011) and the
selective damping of the directions near a singular posture (Maciejewski and Klein 1988), the
null-space pull toward q_rest in the first step of a sample, further steps while |e| >
``tolerance`` up to ``iterations``, a step that makes the error worse halved back (at most
8 times), the one-pass saturation at the margin-narrowed joint limits (Flacco 2015), qd by
``numpy.gradient``, errors reported in `IKResult`. The settings are those of the
`DifferentialIK` it is made from. What is a branch per sample there is a mask over the
population here: the first step is taken by every row, a further step by the rows whose
error is still above the tolerance, the re-solve at a limit by the rows that would cross one,
the halving by the rows whose error grew; each runs on the rows it concerns only.

The kinematics without MuJoCo calls in the loop are `psl_task.site_chain.SiteChain`'s (its
module docstring).

Orientation (optional; issue 26): with ``orientation_ref`` (P, T, 4), unit quaternions
[w, x, y, z] of the site's orientation, the error is six-dimensional,

    e = [x_ref - x ; w_o log(q_ref (x) conj(q_site))]              (6,) [m]

(log: the rotation vector of the shortest rotation, w_o = ``orientation_weight`` [m/rad]),
and J stacks the position Jacobian on w_o times the rotational one; damping, tolerance and
the "worse" test then measure the stacked error. Without it the path is the position-only
one, the very same operations. `IKResult.error` stays the position error [m]; the
orientation error of a result is ``orientation_error(pose(q)[1], orientation_ref)``.

Agreement with `DifferentialIK` (test_population_ik.py): the same algorithm in another
floating-point order (LU instead of Cholesky, other summation orders, Rodrigues instead of
quaternions), so not bit for bit: q agrees to <= 3e-14 rad along paths in reach (joints on
limits included), <= 2e-10 rad along paths that pin joints and leave the reach, and every
single sample, started from DifferentialIK's previous q, to <= 6e-12 rad. Where the target
crosses the edge of the reach DifferentialIK's own output depends on the last bit of x_ref
(the stretched arm amplifies any difference tenfold per sample): there no other rounding can
follow it over the whole path, only step by step. Row-wise arithmetic only: a candidate's
q, qd and error do not depend on the other candidates, bit for bit.

Speed (point_reach_3d: 7 joints, 751 samples = 1 s motion + 0.5 s settle at 500 Hz, default
settings; hand paths of CMA-ES candidates theta = centre + scale (z_default + sigma N(0, I))
in the learner's coordinates (`search_normalisation`); CPU time per candidate, best of 5, over
3 runs, on the development machine (2 cores) beside a robot experiment that loads both):

    candidates P                        10 (SearchSettings.popsize)   15 (4 + 3 ln 53)
    sigma 0.1:  DifferentialIK               5.8 - 5.9 ms                  5.8 - 6.0 ms
                PopulationIK                 3.5 - 3.7 ms                  2.8 - 3.0 ms
    sigma 0.3:  DifferentialIK               6.2 - 6.3 ms                  7.1 - 7.4 ms
                PopulationIK                 5.2 - 5.8 ms                  5.3 - 5.6 ms

(the physics of such a rollout, `BatchRollouts.simulation_seconds`: 2.5 ms). Where the time
goes: a sample of the whole population takes ~50 numpy calls of ~1 us each (48 us at P = 10,
58 us at P = 15), the kinematics ~60 % of it, the damped least-squares step with its 3 x 3
solves ~20 %, masks and bookkeeping ~20 %: per-call overhead, growing slowly with P, so the
cost per candidate falls nearly as 1 / P, and <= 3 ms per candidate needs P >= ~15 with
numpy. Rows that need more than the first step (a further iteration, a halving, a limit:
candidates at the edge of the reach, as with sigma 0.3) cost the population 50 - 100 us per
such sample however few they are, against ~10 us in DifferentialIK: populations with such
candidates gain little. Measured with::

    import time
    import numpy as np
    from psl_controller.policy import policy_for
    from psl_optimizer.learning import search_normalisation
    from psl_task.population_ik import PopulationIK
    from psl_task.task import load_task

    task = load_task('point_reach_3d')
    policy = policy_for(task)
    ik, population, dt = policy.ik, PopulationIK(policy.ik), task.control_period
    centre, scale = search_normalisation(task, policy.default_theta)
    z0 = (policy.default_theta - centre) / scale
    rng = np.random.default_rng(0)

    def best(f, runs=5):
        times = []
        for _ in range(runs):
            start = time.process_time()
            f()
            times.append(time.process_time() - start)
        return min(times)

    for P in (10, 15):
        for sigma in (0.1, 0.3):
            theta = centre + scale * (z0 + sigma * rng.standard_normal((P, z0.size)))
            x = policy.dmp.integrate_population(dt, theta[:, policy.kinematics],
                                                task.num_steps_of(None) * dt).y
            serial = best(lambda: [ik.solve(path, task.start_posture, dt) for path in x])
            side = best(lambda: population.solve(x, task.start_posture, dt))
            print(P, sigma, serial / P, side / P)

Keeps no state between calls (the chain is constant; the `DifferentialIK` it is made from is
only read for its settings). Deterministic: the same input gives bit-identical output.
Imports no ROS; calls MuJoCo only to build the chain.

References
----------
Nakamura, Y., Hanafusa, H. (1986). Inverse kinematic solutions with singularity robustness
for robot manipulator control. Journal of Dynamic Systems, Measurement, and Control, 108(3),
163-171.

Sugihara, T. (2011). Solvability-unconcerned inverse kinematics by the Levenberg-Marquardt
method. IEEE Transactions on Robotics, 27(5), 984-991.

Flacco, F., De Luca, A., Khatib, O. (2015). Control of redundant robots under hard joint
constraints: saturation in the null space. IEEE Transactions on Robotics, 31(3), 637-654.

Bar-Itzhack, I. Y. (2000). New method for extracting the quaternion from a rotation matrix.
Journal of Guidance, Control, and Dynamics, 23(6), 1085-1087.
"""
from __future__ import annotations

import numpy as np

from psl_task.inverse_kinematics import (ORIENTATION_WEIGHT, QUATERNION_NORM_TOLERANCE,
                                         DifferentialIK, IKError, IKResult)
from psl_task.site_chain import _HINGE, _SLIDE, SiteChain, _left_conjugate, rotation_vector

_HALVINGS = 8              # as in DifferentialIK
_HALF_POWERS = 0.5 ** np.arange(1, _HALVINGS + 1)[:, None, None]   # (H, 1, 1): 1/2 .. 1/256
_WORSE = 1.0 + 1e-9        # as in DifferentialIK
try:    # the gufunc behind numpy.linalg.solve, without its checks (5 of its 7 us on 10 3x3
    # systems); a is symmetric positive definite here (lam2 >= damping^2 > 0)
    from numpy.linalg._umath_linalg import solve as _solve
except ImportError:     # pragma: no cover - another numpy layout
    _solve = np.linalg.solve
def _step(jt: np.ndarray, e: np.ndarray, z: np.ndarray | None, lam2: np.ndarray,
          region2: float = 0.0, damping2: float = 0.0) -> np.ndarray:
    """Damped least-squares steps dq (R, n) = z + J^T (J J^T + lam2 I)^-1 (e - J z) of R rows:
    jt (R, n, m) the transposed Jacobians, e (R, m), z (R, n) or None, lam2 (R,); a row whose
    J J^T has an eigenvalue below region2 [m^2] takes the selectively damped step of
    `psl_task.inverse_kinematics` (damping2 [m^2] at a singular posture)."""
    rows, _, m = jt.shape
    jac = jt.swapaxes(1, 2)                                     # (R, m, n)
    a = jac @ jt                                                # (R, m, m)
    r = e if z is None else e - (jac @ z[..., None])[..., 0]
    y = np.empty((rows, m))
    near = np.zeros(rows, dtype=bool)
    if region2 > 0.0:
        sigma2, basis = np.linalg.eigh(a)                       # (R, m), (R, m, m)
        near = sigma2[:, 0] < region2
        if near.any():
            s2, u = sigma2[near], basis[near]
            extra = damping2 * np.maximum(0.0, 1.0 - s2 / region2)
            y[near] = (u @ ((u.swapaxes(1, 2) @ r[near][..., None])[..., 0]
                            / (s2 + lam2[near][:, None] + extra))[..., None])[..., 0]
    far = ~near
    if far.any():
        a_far = a[far]
        a_far.reshape(-1, m * m)[:, ::m + 1] += lam2[far][:, None]
        y[far] = _solve(a_far, r[far][..., None])[..., 0]
    dq = (jt @ y[..., None])[..., 0]
    if z is not None:
        dq += z
    return dq


def _dot(e: np.ndarray) -> np.ndarray:
    """Row-wise e . e (R,) of e (R, m)."""
    return np.einsum('ij,ij->i', e, e)


class PopulationIK:
    """`DifferentialIK.solve` for a population of paths at once, with the settings of ``ik``
    (module docstring).

    Args:
        ik: the serial solver whose model, site, joints, rest posture and settings are used
            (it stays the fallback for models this class refuses).

    Raises:
        IKError: a model whose chain it cannot follow (ball or free joints on the chain from
            the world to the site, arm joints off it): use ``ik`` instead.
    """

    def __init__(self, ik: DifferentialIK):
        model = ik.model
        joints = []
        for adr in ik.qpos_adr.tolist():
            found = np.flatnonzero((model.jnt_qposadr == adr)
                                   & np.isin(model.jnt_type, (_HINGE, _SLIDE)))
            joints.append(int(found[0]))     # DifferentialIK checked: exactly one
        self.ik = ik
        self.n = ik.n
        self.chain = SiteChain(model, ik.site, joints)
        order = self.chain.order
        self._q_rest, self._low, self._high = ik.q_rest[order], ik.low[order], ik.high[order]

    def forward(self, q) -> np.ndarray:
        """Site positions (..., 3) [m] at joint angles q (..., n)."""
        return self.chain.forward(q)

    def pose(self, q) -> tuple[np.ndarray, np.ndarray]:
        """Site positions (..., 3) and quaternions (..., 4) at joint angles q (..., n)."""
        return self.chain.pose(q)

    # -- input ---------------------------------------------------------------------------
    @staticmethod
    def _finite(array: np.ndarray, name: str) -> None:
        if not np.all(np.isfinite(array)):
            bad = np.argwhere(~np.all(np.isfinite(array), axis=-1))[0]
            raise IKError(f'{name} must be finite; candidate {bad[0]} is not at sample {bad[1]}')

    def _paths(self, x_ref, orientation_ref, orientation_weight):
        x_ref = np.asarray(x_ref, dtype=float)
        if x_ref.ndim != 3 or x_ref.shape[2] != 3 or 0 in x_ref.shape:
            raise IKError(f'x_ref must have shape (P, T, 3) with P, T >= 1, got {x_ref.shape}')
        self._finite(x_ref, 'x_ref')
        if orientation_ref is None:
            return x_ref, None
        quat = np.asarray(orientation_ref, dtype=float)
        if quat.shape != x_ref.shape[:2] + (4,):
            raise IKError(f'orientation_ref must have shape {x_ref.shape[:2] + (4,)} (P, T, 4) '
                          f'like x_ref, got {quat.shape}')
        self._finite(quat, 'orientation_ref')
        norm = np.sqrt(np.sum(quat * quat, axis=-1))
        if np.any(np.abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE):
            p, k = np.argwhere(np.abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE)[0]
            raise IKError(f'orientation_ref must hold unit quaternions [w, x, y, z]; candidate '
                          f'{p} at sample {k} has norm {norm[p, k]!r}')
        if not (np.isfinite(orientation_weight) and orientation_weight > 0):
            raise IKError(f'orientation_weight must be finite and > 0, got '
                          f'{orientation_weight!r}')
        return x_ref, quat / norm[..., None]

    def _start(self, q0, population: int) -> np.ndarray:
        q0 = np.array(q0, dtype=float)
        if q0.shape == (self.n,):
            q0 = np.repeat(q0[None], population, axis=0)
        if q0.shape != (population, self.n):
            raise IKError(f'q0 must have shape ({self.n},) or ({population}, {self.n}), '
                          f'got {q0.shape}')
        if not np.all(np.isfinite(q0)):
            raise IKError(f'q0 must be finite; candidate '
                          f'{np.flatnonzero(~np.all(np.isfinite(q0), axis=1))[0]} is not')
        return np.clip(q0[:, self.chain.order], self._low, self._high)

    # -- the paths -----------------------------------------------------------------------
    def solve(self, x_ref, q0, dt: float, orientation_ref=None,
              orientation_weight: float = ORIENTATION_WEIGHT) -> list[IKResult]:
        """The joint references of P Cartesian references, each as `DifferentialIK.solve`.

        Args:
            x_ref: (P, T, 3) site positions [m] of P paths on the control grid.
            q0: (n,) joint angles at the start of every path, or (P, n) one per path
                (clipped into the limits).
            dt: grid step [s].
            orientation_ref: None (position only), or (P, T, 4) unit quaternions
                [w, x, y, z] of the site's orientation along each path.
            orientation_weight: w_o [m/rad], the rotation error's weight (only with
                orientation_ref).

        Returns:
            P IKResults, q and qd (T, n), error (T,) the position error [m].

        Raises:
            IKError: shapes other than the above, non-finite input, quaternions that are not
                of unit norm, dt or orientation_weight not > 0.
        """
        x_ref, quat_ref = self._paths(x_ref, orientation_ref, orientation_weight)
        population, length = x_ref.shape[:2]
        q = self._start(q0, population)
        if not (np.isfinite(dt) and dt > 0):
            raise IKError(f'dt must be finite and > 0, got {dt!r}')
        ik, n = self.ik, self.n
        weight = None if quat_ref is None else float(orientation_weight)
        targets = np.ascontiguousarray(x_ref.swapaxes(0, 1))             # (T, P, 3)
        # per sample and candidate the map q_site -> q_ref (x) conj(q_site): (T, P, 4, 4)
        rotations = (None if quat_ref is None
                     else np.ascontiguousarray(_left_conjugate(quat_ref).swapaxes(0, 1)))
        solver = _Stepper(self.chain, weight, ik, min(1.0, ik.nullspace_gain * dt),
                       self._q_rest, self._low, self._high)
        q_out = np.empty((length, population, n))
        x_out = np.empty((length, population, 3))
        x, jt, quat = self.chain.evaluate(q, weight)
        tolerance2 = ik.tolerance ** 2
        everyone = slice(None)
        for k in range(length):
            goal = (targets[k], None if rotations is None else rotations[k])
            e = solver.error(goal, x, quat)
            ee = _dot(e)
            q, x, jt, quat, e, ee = solver.iterate(everyone, goal, q, x, jt, quat, e, ee, True)
            for _ in range(1, ik.iterations):
                going = ee > tolerance2
                if not going.any():
                    break
                rows = np.flatnonzero(going)
                out = solver.iterate(rows, goal, q[rows], x[rows], jt[rows],
                                     None if quat is None else quat[rows], e[rows], ee[rows],
                                     False)
                for array, part in zip((q, x, jt, quat, e, ee), out):
                    if array is not None:
                        array[rows] = part
            q_out[k] = q
            x_out[k] = x
        q_all = np.ascontiguousarray(q_out.swapaxes(0, 1)[:, :, self.chain.rank])  # (P, T, n)
        x_all = x_out.swapaxes(0, 1)
        error = np.sqrt(np.sum((x_all - x_ref) ** 2, axis=-1))                   # (P, T)
        qd = (np.gradient(q_all, dt, axis=1) if length > 1
              else np.zeros((population, 1, n)))
        return [IKResult(q=q_all[p], qd=qd[p], error=error[p]) for p in range(population)]


class _Stepper:
    """One damped least-squares step of a set of rows (candidates) toward one sample's goal:
    the step, the saturation at the limits, the halving of a step that made the error worse
    (`DifferentialIK.solve`, `_respect_limits`, `DifferentialIK._backtrack`)."""

    def __init__(self, chain: SiteChain, weight: float | None, ik: DifferentialIK,
                 pull: float, q_rest: np.ndarray, low: np.ndarray, high: np.ndarray):
        self.chain, self.weight = chain, weight
        self.damping2, self.tolerance2 = ik.damping ** 2, ik.tolerance ** 2
        self.region2, self.singular2 = ik.singular_region ** 2, ik.singular_damping ** 2
        self.pull, self.pulled_rest = pull, pull * q_rest
        self.low, self.high = low, high

    def error(self, goal, x: np.ndarray, quat: np.ndarray | None) -> np.ndarray:
        """e (R, 3) = x_ref - x, or (R, 6) with w_o log(q_ref (x) conj(q_site)) below."""
        target, rotation = goal
        if quat is None:
            return target - x
        e = np.empty((len(x), 6))
        np.subtract(target, x, out=e[:, :3])
        e[:, 3:] = self.weight * rotation_vector((rotation @ quat[..., None])[..., 0])
        return e

    def iterate(self, rows, goal, q, x, jt, quat, e, ee, first: bool):
        """One step of the rows (an index array, or slice(None) for all) from q (R, n) with
        site x (R, 3), jt (R, n, m), quat (R, 4) or None, error e (R, m), ee = e.e (R,);
        returns the same six after the step."""
        goal = goal if isinstance(rows, slice) else (
            goal[0][rows], None if goal[1] is None else goal[1][rows])
        lam2 = self.damping2 + 0.5 * ee
        z = self.pulled_rest + q * (-self.pull) if first and self.pull > 0.0 else None
        q_new = q + _step(jt, e, z, lam2, self.region2, self.singular2)
        over = (q_new < self.low) | (q_new > self.high)
        if over.any():
            hit = np.flatnonzero(over.any(axis=1))
            q_new[hit] = self._saturate(q[hit], q_new[hit], jt[hit], e[hit],
                                        None if z is None else z[hit], lam2[hit])
        x_new, jt_new, quat_new = self.chain.evaluate(q_new, self.weight)
        e_new = self.error(goal, x_new, quat_new)
        ee_new = _dot(e_new)
        bound = np.maximum(ee * _WORSE, self.tolerance2)
        worse = ee_new > bound
        if worse.any():
            self._backtrack(np.flatnonzero(worse), goal, bound, (q, x, jt, quat, e, ee),
                            (q_new, x_new, jt_new, quat_new, e_new, ee_new))
        return q_new, x_new, jt_new, quat_new, e_new, ee_new

    def _saturate(self, q, q_new, jt, e, z, lam2) -> np.ndarray:
        """The rows' steps q -> q_new kept within the bounds: the joints a step would carry
        across a bound are moved onto it, the step is solved again for the others with the
        locked joints' motion taken off the error (one pass), the result clipped."""
        clipped = np.clip(q_new, self.low, self.high)
        over = clipped != q_new
        free = ~over
        locked = (clipped - q) * over
        e_free = e - (jt.swapaxes(1, 2) @ locked[..., None])[..., 0]
        dq = _step(jt * free[..., None], e_free, None if z is None else z * free, lam2,
                   self.region2, self.singular2)
        return np.clip(q + locked + dq, self.low, self.high)

    def _backtrack(self, worse, goal, bound, old, new) -> None:
        """The rows ``worse`` of ``new`` (q, x, jt, quat, e, ee after the step, updated in
        place) halved back toward ``old`` until ee <= bound, at most _HALVINGS times, then
        set back to ``old``. All halvings of a row, q_old + (q - q_old) / 2^h for
        h = 1.._HALVINGS (the points of halving one at a time up to rounding), are evaluated
        in one batch (the kinematics cost per call, hardly per row) and the first that passes
        is taken."""
        chain, count = self.chain, len(worse)
        q_old = old[0][worse]
        halved = q_old + (new[0][worse] - q_old) * _HALF_POWERS          # (H, W, n)
        halved = halved.reshape(_HALVINGS * count, -1)    # halving h of row i: h count + i
        readout = chain.readout(chain.frames(halved))
        x = chain.site(readout)
        quat = None if self.weight is None else chain.site_quaternion(readout)
        target, rotation = goal
        tiled = (np.tile(target[worse], (_HALVINGS, 1)),
                 None if rotation is None else np.tile(rotation[worse], (_HALVINGS, 1, 1)))
        e = self.error(tiled, x, quat)
        ee = _dot(e)
        passed = ee.reshape(_HALVINGS, count) <= bound[worse]
        found = passed.any(axis=0)
        pick = np.argmax(passed, axis=0) * count + np.arange(count)
        if not found.all():
            rows = worse[~found]
            for array, before in zip(new, old):
                if array is not None:
                    array[rows] = before[rows]
            worse, pick = worse[found], pick[found]
        if len(worse):
            for array, part in zip(new, (halved, x, None, quat, e, ee)):
                if part is not None:
                    array[worse] = part[pick]
            new[2][worse] = chain.jacobian(readout[pick], self.weight)
