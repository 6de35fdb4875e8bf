"""Tests of PopulationIK against independent references: its kinematics against MuJoCo's
(mj_kinematics, mj_jacSite) on the tasks' models and on a model with every kind of chain
element; its solution against DifferentialIK candidate by candidate; row independence
(one candidate alone = the same candidate in a population, bit for bit, under every OpenBLAS
kernel this CPU runs); refused input; the optional orientation term.

PopulationIK, the second implementation the serial solver is tested against, lives here with
its tests (no session uses it: this learner's populations are one or two candidates, where
the serial solver is faster; docs/benchmarks.md). What it is:

Differential inverse kinematics of a population of Cartesian paths, side by side.

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

Speed: docs/benchmarks.md ("The inverse kinematics on point_reach_3d: knots": 3.5 ms per
candidate at P = 10 against 5.8 ms serially; per-call numpy overhead, so it pays only for
populations of ten or more).

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

import os
from pathlib import Path

import mujoco
import numpy as np
import pytest

from psl_task.arm_model import ArmModel
from psl_task.inverse_kinematics import (ORIENTATION_WEIGHT, QUATERNION_NORM_TOLERANCE,
                                         DifferentialIK, IKError, IKResult)
from psl_task.quaternion import (_left_conjugate, orientation_error, quaternion_of,
                                  rotation_vector)
from psl_task.site_chain import _HINGE, _SLIDE, SiteChain
from psl_task.task import load_task


# -- the second implementation ------------------------------------------------------------
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
        if np.isfinite(ik.max_velocity).any():     # not implemented here: refused, not ignored
            raise IKError('PopulationIK does not keep joint velocity bounds; give it a '
                          'DifferentialIK without max_velocity')
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


# -- its tests ----------------------------------------------------------------------
EXAMPLES = Path(__file__).resolve().parents[3] / 'examples'

# MuJoCo's kinematics (quaternions, com-based Jacobian) and the chain's (Rodrigues, cross
# products) are two roundings of the same products of ~10 transforms: ~1e-15 apart
TOL_KINEMATICS = 1e-12      # m, m/rad, rad/rad, rotation matrix entries
# PopulationIK vs DifferentialIK: the same step in another floating-point order (LU instead
# of Cholesky, other summation orders, other kinematics), so the two drift apart by roundoff
# only; the step contracts the task-space error and the null-space pull (1 % per sample)
# contracts the rest, so the drift stays near the roundoff of one step amplified by the damped
# pseudo-inverse (|J^#| <= 1 / (2 damping) = 500 rad/m): measured <= 3e-14 rad on paths in
# reach, <= 2e-10 rad on the paths that leave it or pin joints on limits. 1e-9 rad keeps a
# margin of 5 over the worst of these and is 4 orders below the IK's own tolerance (1e-5 m
# over a ~0.5 m arm, 2e-5 rad).
TOL_PATH = 1e-9             # rad, whole paths where the reference is reproducible
TOL_BEYOND = 1e-8           # rad, a whole path out of the reach and back (measured 9e-10)
TOL_STEP = 1e-10            # rad, one sample from the reference's previous q (measured <= 6e-12)
TOL_POSE_POSITION = 1e-4    # m, a reachable pose path tracked with the orientation term
TOL_POSE_ANGLE = 1e-3       # rad

PATH_SAMPLES = 600          # 1.2 s at the task's 500 Hz


# -- models ---------------------------------------------------------------------------------------
def task_arm(name):
    arm = ArmModel(load_task(name))     # the examples' robots are installed (requirements.txt)
    return arm, arm.task.end_effector_site


TASK_MODELS = ['point_reach_3d', 'reach_4dof', 'planar_10dof_reach',
               str(EXAMPLES / 'ur5_reach_over_obstacle.yaml'),
               str(EXAMPLES / 'pusher_reach_over_obstacle.yaml')]     # passive slides


def mixed_chain(rail='type="slide" axis="1 0 0" ref="0.15"'):
    """Every chain element the population IK handles: a passive slide with ref (rail) and a
    passive hinge with ref (idle) on the chain, arm slides with non-unit axes, hinges with
    ref and off-centre anchors, several joints in a body, rotated bodies and site, a free body,
    a mocap body and a hinge off the chain elsewhere."""
    return mujoco.MjModel.from_xml_string(f"""
<mujoco>
  <compiler angle="radian" autolimits="true"/>
  <default><geom type="capsule" size="0.02" mass="0.3"/></default>
  <worldbody>
    <body name="ball" pos="1 1 1"><freejoint/><geom type="sphere" size="0.05"/></body>
    <body name="target" mocap="true" pos="0.3 0.2 0.1"><geom type="sphere" size="0.02"/></body>
    <body name="base" pos="0.1 -0.2 0.5" quat="0.9 0.1 0.3 -0.2">
      <joint name="rail" {rail}/>
      <geom type="box" size="0.05 0.05 0.05"/>
      <body name="carriage" pos="0 0.1 0">
        <joint name="lift" type="slide" axis="0.2 0.1 1" range="-0.3 0.3"/>
        <geom type="box" size="0.03 0.03 0.03"/>
        <body name="upper" pos="0.05 0 0.1" euler="0.3 -0.2 0.5">
          <joint name="yaw" axis="0 0 1" pos="0.02 0.01 0" range="-2 2"/>
          <joint name="pitch" axis="0 1 0" ref="0.4" range="-1 2"/>
          <joint name="spin" axis="1 0 0"/>
          <geom fromto="0 0 0 0.3 0 0"/>
          <body name="fore" pos="0.3 0 0" quat="0.8 0.2 -0.1 0.3">
            <joint name="elbow" axis="0.3 1 0.2" pos="0 0 0.03" ref="-0.2" range="-0.5 2.5"/>
            <joint name="idle" axis="0 0 1" ref="0.7"/>
            <geom fromto="0 0 0 0.25 0 0"/>
            <body name="hand" pos="0.25 0.02 -0.01">
              <joint name="wrist" type="slide" axis="1 0 0" range="-0.05 0.05"/>
              <geom fromto="0 0 0 0.08 0 0"/>
              <site name="tip" pos="0.08 0.01 0.02" quat="0.7 0.1 0.7 0.1"/>
            </body>
          </body>
        </body>
      </body>
    </body>
    <body name="other" pos="-1 0 0"><joint name="other" axis="0 0 1"/>
      <geom fromto="0 0 0 0.1 0 0"/></body>
  </worldbody>
</mujoco>""")


MIXED_ARM = ['elbow', 'lift', 'wrist', 'yaw', 'spin', 'pitch']   # q order != chain order


def mixed_ik(model, joints=MIXED_ARM, site='tip'):
    ids = [model.joint(name).id for name in joints]
    return DifferentialIK(model, site, model.jnt_qposadr[ids], model.jnt_dofadr[ids],
                          q_rest=np.zeros(len(ids)), knot_step=0.0)


def mujoco_kinematics(model, ik, q):
    """Site position (3,), rotation (3, 3), jacp and jacr (3, n) at q on a fresh MjData."""
    data = mujoco.MjData(model)
    data.qpos[ik.qpos_adr] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    mujoco.mj_jacSite(model, data, jacp, jacr, ik.site)
    return (data.site_xpos[ik.site].copy(), data.site_xmat[ik.site].reshape(3, 3).copy(),
            jacp[:, ik.dof_adr], jacr[:, ik.dof_adr])


def matrix_of(quat):
    out = np.empty(9)
    mujoco.mju_quat2Mat(out, quat)
    return out.reshape(3, 3)


def check_kinematics(model, ik, postures):
    population = PopulationIK(ik)
    x, quat = population.pose(postures)
    jacp, jacr = population.chain.jacobians(postures)
    np.testing.assert_array_equal(population.forward(postures), x)
    for k, q in enumerate(postures):
        x_ref, rot_ref, jacp_ref, jacr_ref = mujoco_kinematics(model, ik, q)
        np.testing.assert_allclose(x[k], x_ref, rtol=0, atol=TOL_KINEMATICS)
        np.testing.assert_allclose(matrix_of(quat[k]), rot_ref, rtol=0, atol=TOL_KINEMATICS)
        np.testing.assert_allclose(jacp[k], jacp_ref, rtol=0, atol=TOL_KINEMATICS)
        np.testing.assert_allclose(jacr[k], jacr_ref, rtol=0, atol=TOL_KINEMATICS)


# -- (1) kinematics against MuJoCo ----------------------------------------------------------------
@pytest.mark.parametrize('name', TASK_MODELS)
def test_kinematics_match_mujoco_on_the_task_models(name):
    arm, site = task_arm(name)
    ik = DifferentialIK(arm.model, site, arm.qpos_adr, arm.dof_adr, arm.task.start_posture)
    rng = np.random.default_rng(0)
    # random postures over the joints' ranges and beyond (the kinematics have no limits)
    postures = rng.uniform(-np.pi, np.pi, size=(40, ik.n))
    check_kinematics(arm.model, ik, postures)


def test_kinematics_match_mujoco_on_every_kind_of_chain_element():
    model = mixed_chain()
    ik = mixed_ik(model)
    rng = np.random.default_rng(1)
    postures = rng.uniform(-2.0, 2.0, size=(40, ik.n))
    check_kinematics(model, ik, postures)
    # the batch shape is kept: (2, 20, n) -> (2, 20, 3)
    assert PopulationIK(ik).forward(postures.reshape(2, 20, -1)).shape == (2, 20, 3)


@pytest.mark.parametrize('rail, kind', [('type="ball"', 'ball'), ('type="free"', 'free')])
def test_ball_and_free_joints_on_the_chain_are_refused(rail, kind):
    model = (mixed_chain(rail) if kind == 'ball' else mujoco.MjModel.from_xml_string("""
<mujoco><worldbody><body name="base"><freejoint name="float"/>
  <geom type="sphere" size="0.05"/>
  <body name="link"><joint name="j0" axis="0 0 1"/><geom type="capsule" fromto="0 0 0 0.3 0 0"
    size="0.02"/><site name="tip" pos="0.3 0 0"/></body></body></worldbody></mujoco>"""))
    ik = mixed_ik(model) if kind == 'ball' else mixed_ik(model, ['j0'])
    with pytest.raises(IKError, match=f'{kind} joint .* lies on the chain .* site \'tip\''):
        PopulationIK(ik)


def test_an_arm_joint_off_the_chain_is_refused():
    ik = mixed_ik(mixed_chain(), MIXED_ARM + ['other'])
    with pytest.raises(IKError, match=r"\['other'\] are not on the chain"):
        PopulationIK(ik)


def test_a_solver_with_joint_velocity_bounds_is_refused():
    ik = mixed_ik(mixed_chain())
    bounded = DifferentialIK(ik.model, ik.site, ik.qpos_adr, ik.dof_adr, ik.q_rest,
                             max_velocity=2.0)
    with pytest.raises(IKError, match='does not keep joint velocity bounds'):
        PopulationIK(bounded)


def test_quaternions_and_rotation_vectors_match_mujoco():
    rng = np.random.default_rng(2)
    quats = rng.normal(size=(200, 4))
    quats[:50, 0] = 0.0                                  # rotations by pi
    quats[50:60, 1:] *= 1e-9                             # rotations by nearly 0
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    rotations = np.array([matrix_of(q) for q in quats])
    for quat, mine in zip(quats, quaternion_of(rotations)):
        expected = np.empty(4)
        mujoco.mju_mat2Quat(expected, matrix_of(quat).reshape(9))
        assert min(np.abs(mine - expected).max(), np.abs(mine + expected).max()) < 1e-14
    for quat, mine in zip(quats[50:], rotation_vector(quats[50:])):     # angles < pi
        expected = np.empty(3)
        mujoco.mju_quat2Vel(expected, quat, 1.0)
        np.testing.assert_allclose(mine, expected, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(rotation_vector(quats[:50]), axis=1), np.pi,
                               rtol=1e-14)
    np.testing.assert_array_equal(rotation_vector(-quats), rotation_vector(quats))
    np.testing.assert_allclose(orientation_error(quats, quats), 0.0, rtol=0, atol=1e-12)


# -- (2) the solution against DifferentialIK ------------------------------------------------------
def minimum_jerk(n):
    u = np.linspace(0.0, 1.0, n)
    return 10 * u ** 3 - 15 * u ** 4 + 6 * u ** 5


def line(a, b, n=PATH_SAMPLES, hold=100):
    """From a to b (3,) with minimum-jerk timing, then hold samples at b."""
    path = a + minimum_jerk(n - hold)[:, None] * (np.asarray(b) - a)
    return np.vstack([path, np.repeat(path[-1:], hold, axis=0)])


def circle(start, radius, u, w, n=PATH_SAMPLES):
    """A circle through start in the plane of the unit vectors u, w (centre start - r u)."""
    angle = 2 * np.pi * minimum_jerk(n)[:, None]
    return start + radius * ((np.cos(angle) - 1.0) * np.asarray(u) + np.sin(angle) * w)


@pytest.fixture(scope='module')
def reach():
    """point_reach_3d's DifferentialIK, start posture, grid step and hand paths from the
    start (hand at (0.31, -0.06, -0.53), shoulder at 0, reach 0.65 m): in reach; with the
    shoulder flexion on its lower limit for 260 samples (still in reach); three joints or
    more on limits toward a target they make infeasible (error 0.03 m); a circle that pins
    the elbow on its limit and leaves the reach (0.03 m); out of reach and back (0.14 m
    beyond)."""
    arm, site = task_arm('point_reach_3d')
    task = arm.task
    ik = DifferentialIK(arm.model, site, arm.qpos_adr, arm.dof_adr, task.start_posture,
                        knot_step=0.0)     # every sample, as PopulationIK
    q0 = np.array(task.start_posture)
    x0 = ik.forward(q0)
    half = PATH_SAMPLES // 2
    paths = {
        'in_reach': line(x0, [0.42, 0.0, -0.10]),
        'shoulder_on_limit': line(x0, [-0.35, -0.05, -0.45]),
        'three_on_limits': line(x0, [0.0, 0.0, -0.2]),
        'circle_beyond_reach': circle(x0, 0.1, np.array([1.0, 0, 0]), np.array([0, 0, 1.0])),
        'out_and_back': np.vstack([line(x0, [0.70, 0.1, -0.35], half, 20),
                                   line([0.70, 0.1, -0.35], x0, PATH_SAMPLES - half, 20)]),
    }
    return ik, q0, task.control_period, paths


def test_paths_exercise_limits_and_reach(reach):
    """The premises of the comparisons below: which paths pin joints, which leave the reach."""
    ik, q0, dt, paths = reach
    on_limit = {}
    for name, path in paths.items():
        q = ik.solve(path, q0, dt).q
        on_limit[name] = np.flatnonzero(np.any((q == ik.low) | (q == ik.high), axis=0))
    assert on_limit['in_reach'].size == 0
    assert list(on_limit['shoulder_on_limit']) == [0]
    assert len(on_limit['three_on_limits']) >= 3 and len(on_limit['circle_beyond_reach']) >= 1
    assert ik.solve(paths['out_and_back'], q0, dt).max_error > 0.1


def test_population_matches_differential_ik_along_whole_paths(reach):
    """Candidate by candidate, the whole path within TOL_PATH (q), TOL_PATH (error, m) and
    TOL_PATH / dt (qd); 'out_and_back' within TOL_BEYOND: as the target crosses the edge of
    the reach the arm is stretched (singular) and the steps amplify rounding, by a bounded
    factor since the selective damping of singular directions (the next test)."""
    ik, q0, dt, paths = reach
    names = list(paths)
    results = PopulationIK(ik).solve(np.array([paths[n] for n in names]), q0, dt)
    for name, result in zip(names, results):
        reference = ik.solve(paths[name], q0, dt)
        tol = TOL_BEYOND if name == 'out_and_back' else TOL_PATH
        np.testing.assert_allclose(result.q, reference.q, rtol=0, atol=tol, err_msg=name)
        np.testing.assert_allclose(result.error, reference.error, rtol=0, atol=tol,
                                   err_msg=name)
        np.testing.assert_allclose(result.qd, reference.qd, rtol=0, atol=tol / dt,
                                   err_msg=name)
        assert np.all((result.q >= ik.low) & (result.q <= ik.high)), name


def test_beyond_reach_the_reference_is_reproducible(reach):
    """x_ref changed by one part in 1e15 moves DifferentialIK's q by less than TOL_PATH in
    reach and TOL_BEYOND out of it. (Before the selective damping of singular directions,
    the stretched arm amplified any difference tenfold per sample as the target crossed the
    edge of the reach: 'out_and_back' moved by more than 0.01 rad.)"""
    ik, q0, dt, paths = reach
    for name, path in paths.items():
        q = ik.solve(path, q0, dt).q
        q_nudged = ik.solve(path * (1.0 - 1e-15), q0, dt).q
        tol = TOL_BEYOND if name == 'out_and_back' else TOL_PATH
        assert np.abs(q_nudged - q).max() < tol, name


def test_population_matches_differential_ik_sample_by_sample(reach):
    """Teacher forcing: sample k solved from DifferentialIK's q_{k-1} (a population of T - 1
    one-sample paths) gives DifferentialIK's q_k within TOL_STEP on every path, out of reach
    included: the same step, halving, limit and iteration decisions at every sample."""
    ik, q0, dt, paths = reach
    population = PopulationIK(ik)
    for name, path in paths.items():
        reference = ik.solve(path, q0, dt).q
        steps = population.solve(path[1:, None, :], reference[:-1], dt)
        q = np.array([result.q[0] for result in steps])
        np.testing.assert_allclose(q, reference[1:], rtol=0, atol=TOL_STEP, err_msg=name)


def test_a_start_per_candidate(reach):
    ik, q0, dt, paths = reach
    path = paths['in_reach'][:200]
    starts = q0 + np.array([[0.0] * 7, [0.05, -0.05, 0.1, 0.1, 0.0, 0.1, -0.1]])
    results = PopulationIK(ik).solve(np.array([path, path]), starts, dt)
    for start, result in zip(starts, results):
        np.testing.assert_allclose(result.q, ik.solve(path, start, dt).q, rtol=0, atol=TOL_PATH)
    assert not np.allclose(results[0].q[0], results[1].q[0])


def test_slides_and_a_permuted_chain_match_differential_ik():
    model = mixed_chain()
    ik = mixed_ik(model)
    q0 = np.array([0.8, 0.05, 0.0, 0.3, -0.4, 0.6])
    x0 = ik.forward(q0)
    paths = np.array([line(x0, x0 + [0.05, -0.04, 0.03], 300, 50),
                      line(x0, x0 + [-0.1, 0.1, -0.05], 300, 50)])
    for path, result in zip(paths, PopulationIK(ik).solve(paths, q0, 2e-3)):
        np.testing.assert_allclose(result.q, ik.solve(path, q0, 2e-3).q, rtol=0, atol=TOL_PATH)


def test_a_single_sample(reach):
    ik, q0, dt, paths = reach
    result = PopulationIK(ik).solve(paths['in_reach'][None, 5:6], q0, dt)[0]
    reference = ik.solve(paths['in_reach'][5:6], q0, dt)
    assert result.q.shape == result.qd.shape == (1, 7) and np.all(result.qd == 0.0)
    np.testing.assert_allclose(result.q, reference.q, rtol=0, atol=TOL_STEP)


# -- (3) rows are independent ---------------------------------------------------------------------
def test_one_candidate_alone_equals_it_in_any_population(reach):
    """Row-wise arithmetic only: a candidate's q, qd and error do not depend on the others
    (how many, which, in what order, which of them take further steps, halve or hit limits),
    bit for bit, the chaotic 'out_and_back' included."""
    ik, q0, dt, paths = reach
    population = PopulationIK(ik)
    stacked = np.array(list(paths.values()))
    together = population.solve(stacked, q0, dt)
    order = np.array([3, 0, 4, 2, 1] * 3)                 # 15 candidates, each thrice
    shuffled = population.solve(stacked[order], q0, dt)
    for i, path in enumerate(stacked):
        alone = population.solve(path[None], q0, dt)[0]
        again = [shuffled[j] for j in np.flatnonzero(order == i)]
        for result in [together[i]] + again:
            np.testing.assert_array_equal(result.q, alone.q)
            np.testing.assert_array_equal(result.qd, alone.qd)
            np.testing.assert_array_equal(result.error, alone.error)


SWEEP = 'PSL_OPENBLAS_SWEEP'     # the kernel a sweep's run was asked to take


@pytest.mark.skipif(bool(os.environ.get(SWEEP)), reason='inside the sweep')
def test_rows_are_independent_under_every_openblas_kernel_this_cpu_runs():
    """OpenBLAS blocks a matrix product by its shape, with kernels chosen by CPU
    (test_policy_population.py): the row-independence test above once per kernel
    (OPENBLAS_CORETYPE), as on other CPUs."""
    from psl_bench import openblas
    try:
        outputs = openblas.run_per_kernel(
            [__file__, '-k', 'alone_equals_it_in_any_population or orientation_term'])
    except ValueError as exc:
        pytest.skip(str(exc))
    for kernel, out in outputs.items():
        assert '2 passed' in out, f'with the {kernel} kernel:\n{out[-3000:]}'


# -- (4) refused input ----------------------------------------------------------------------------
def _nan_at(array, index):
    array = np.array(array, dtype=float)
    array[index] = np.nan
    return array


@pytest.mark.parametrize('change, message', [
    (dict(x_ref=np.zeros((5, 3))), r'x_ref must have shape \(P, T, 3\).*\(5, 3\)'),
    (dict(x_ref=np.zeros((2, 5, 2))), r'x_ref must have shape \(P, T, 3\)'),
    (dict(x_ref=np.zeros((2, 0, 3))), r'P, T >= 1, got \(2, 0, 3\)'),
    (dict(x_ref=np.zeros((0, 5, 3))), r'P, T >= 1'),
    (dict(x_ref=_nan_at(np.zeros((2, 5, 3)), (1, 3, 2))),
     'x_ref must be finite; candidate 1 is not at sample 3'),
    (dict(q0=np.zeros(6)), r'q0 must have shape \(7,\) or \(2, 7\), got \(6,\)'),
    (dict(q0=np.zeros((3, 7))), r'q0 must have shape .* got \(3, 7\)'),
    (dict(q0=_nan_at(np.zeros((2, 7)), (1, 4))), 'q0 must be finite; candidate 1'),
    (dict(dt=0.0), 'dt must be finite and > 0'),
    (dict(dt=np.nan), 'dt must be finite and > 0'),
    (dict(orientation_ref=np.ones((2, 5))), r'orientation_ref must have shape \(2, 5, 4\)'),
    (dict(orientation_ref=np.ones((2, 5, 4)) * 0.5 + [0, 0, 0, 1e-3]),
     'unit quaternions .* candidate 0 at sample 0 has norm'),
    (dict(orientation_ref=_nan_at(np.ones((2, 5, 4)) * 0.5, (0, 2, 1))),
     'orientation_ref must be finite; candidate 0 is not at sample 2'),
    (dict(orientation_ref=np.ones((2, 5, 4)) * 0.5, orientation_weight=0.0),
     'orientation_weight must be finite and > 0'),
])
def test_bad_input_is_refused(reach, change, message):
    ik = reach[0]
    arguments = dict(x_ref=np.zeros((2, 5, 3)), q0=np.zeros(7), dt=0.002)
    with pytest.raises(IKError, match=message):
        PopulationIK(ik).solve(**{**arguments, **change})


# -- orientation (issue 26) -----------------------------------------------------------------------
def test_a_reachable_pose_path_is_tracked_with_the_orientation_term(reach):
    """Poses along joint paths (forward kinematics, so reachable exactly): with the
    orientation term the hand follows position and orientation; without it the position only,
    the orientation drifts where the redundancy and the null-space pull take it."""
    ik, q0, dt, _ = reach
    population = PopulationIK(ik)
    s = minimum_jerk(PATH_SAMPLES)[:, None]
    goals = np.array([[0.411, 0.059, 0.041, 1.625, -0.007, 0.25, -0.017],
                      [0.9, 0.4, -0.6, 1.2, 0.8, -0.5, 0.3]])
    joint_paths = q0 + s * (goals[:, None, :] - q0)                 # (2, T, 7)
    x_ref, quat_ref = population.pose(joint_paths)
    posed = population.solve(x_ref, q0, dt, orientation_ref=quat_ref, orientation_weight=0.1)
    plain = population.solve(x_ref, q0, dt)
    for k, (with_term, without) in enumerate(zip(posed, plain)):
        angle = orientation_error(population.pose(with_term.q)[1], quat_ref[k])
        angle_without = orientation_error(population.pose(without.q)[1], quat_ref[k])
        assert with_term.max_error < TOL_POSE_POSITION and angle.max() < TOL_POSE_ANGLE
        assert without.max_error < TOL_POSE_POSITION
        assert angle_without.max() > 1e-2 and angle_without.max() > 100 * angle.max()
    # rows stay independent with the term too
    alone = population.solve(x_ref[1:], q0, dt, orientation_ref=quat_ref[1:],
                             orientation_weight=0.1)[0]
    np.testing.assert_array_equal(alone.q, posed[1].q)


def test_without_orientation_reference_the_weight_changes_nothing(reach):
    ik, q0, dt, paths = reach
    population = PopulationIK(ik)
    x_ref = np.array([paths['circle_beyond_reach']])
    default = population.solve(x_ref, q0, dt)[0]
    weighted = population.solve(x_ref, q0, dt, orientation_ref=None, orientation_weight=5.0)[0]
    np.testing.assert_array_equal(default.q, weighted.q)


def test_the_serial_pose_solve_matches_the_population_one(reach):
    """DifferentialIK's six-dimensional step (mju_* calls, MuJoCo's quaternions and
    Jacobians) against PopulationIK's (numpy, the chain's Rodrigues kinematics): the same
    algorithm in two floating-point orders, along a pose path in reach."""
    ik, q0, dt, paths = reach
    population = PopulationIK(ik)
    s = minimum_jerk(PATH_SAMPLES)[:, None]
    goal = np.array([0.9, 0.4, -0.6, 1.2, 0.8, -0.5, 0.3])
    x_ref, quat_ref = population.pose(q0 + s * (goal - q0))
    serial = ik.solve(x_ref, q0, dt, orientation_ref=quat_ref)
    side = population.solve(x_ref[None], q0, dt, orientation_ref=quat_ref[None],
                            orientation_weight=ik.orientation_weight)[0]
    np.testing.assert_allclose(serial.q, side.q, rtol=0, atol=TOL_PATH)
    np.testing.assert_allclose(serial.rotation_error,
                               orientation_error(population.pose(side.q)[1], quat_ref),
                               rtol=0, atol=TOL_KINEMATICS)
    assert serial.max_error < TOL_POSE_POSITION and serial.rotation_error.max() < TOL_POSE_ANGLE
