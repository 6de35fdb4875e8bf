"""Differential inverse kinematics of a site's position on a MuJoCo model.

`DifferentialIK.solve` turns a Cartesian reference of the end-effector position, x_ref (T, 3)
on a control grid of step dt, into a joint reference q (T, n), qd (T, n) for the arm's n
hinge (or slide) joints, before a rollout. Each sample k starts from the solution of k - 1
(q0 for k = 0) and takes damped least-squares steps on the site's position Jacobian J (3, n)
of ``mujoco.mj_jacSite``:

    e    = x_ref_k - fk(q)                                  position error (3,) [m]
    z    = min(1, nullspace_gain dt) (q_rest - q)           pull toward the rest posture (n,),
                                                            in the first step of a sample
    lam2 = damping^2 + e.e / 2                              damping [m^2] (Sugihara 2011)
    dq   = z + J^T (J J^T + lam2 I)^-1 (e - J z)            (Nakamura 1986)

that is dq = J^# e + (I - J^# J) z with the damped pseudo-inverse J^# = J^T (J J^T + lam2 I)^-1
and the null-space projection of Liegeois (1977). The first step of a sample is always taken,
further ones (up to ``iterations``) while |e| > ``tolerance``; along a smooth path at dt 1-2 ms
one step per sample leaves a few 1e-6 m. No feed-forward term: e contains the whole increment
x_ref_k - x_ref_{k-1} (plus what k - 1 left), of which xd_ref dt would only be a first-order
approximation, so the reference velocity is not an input.

The error-scaled part of the damping keeps steps bounded (<~ 0.7 rad along a singular
direction) when the target is out of reach or the arm near-singular, and vanishes while
tracking; ``damping`` is the floor that keeps J J^T + lam2 I invertible where rows of J are
zero (the z row of a planar arm). A step that makes the error worse (the linear model fails
near a singular posture, e.g. at the edge of the reach) is halved back until it does not:
no chatter across the stretched posture.

Joint limits (``jnt_range`` of limited joints, narrowed by ``limit_margin``) are hard: a step
that would cross a bound moves that joint onto the bound and is solved again without it, so
the other joints take over its share within the same step (one pass of the saturation in the
null space of Flacco 2015); the result is clipped to the bounds.

qd is the finite difference of q (``numpy.gradient``: central inside, one-sided at the two
ends), i.e. the velocity of the very q the PD controller tracks, null-space motion and stops
at limits included; it is finite and as smooth as q.

Reported, never raised: a target out of reach or a singular posture leaves a residual in
``IKResult.error`` (T,) = |fk(q_k) - x_ref_k| [m], with q finite and within the limits; near
the edge of the reach the exact solution itself needs joint speeds without bound (q ~ square
root of the distance to the edge), so qd peaks there. One case stays stuck: an arm exactly
straight (e.g. q = 0) asked to move exactly along itself has no first-order direction to bend
in; its error grows and says so (any other direction, or a bent rest posture, bends it).

Speed (``solve`` of a 1000-sample circle of radius 0.1 m at dt 1 ms, default settings, CPU
time, best of 40, on the development machine): 7-joint 3-D arm 11.7 us per sample, 10-joint
planar arm 11.1 us per sample; about 22 us per sample while a joint sits on its limit (two
solves a step). Nearly all of it is Python call overhead: about 20 calls per step
(mj_kinematics, mj_comPos, mj_jacSite, and mju_* vector routines on preallocated buffers,
which cost less per call than numpy's on 3 x n arrays).

Not thread-safe: a `DifferentialIK` owns one MjData (never the caller's), and writes only the
qpos at ``qpos_adr``; every other qpos (free bodies, passive joints) stays at the model's
qpos0. Deterministic: the same input gives bit-identical output. Imports no ROS.

References
----------
Liegeois, A. (1977). Automatic supervisory control of the configuration and behavior of
multibody mechanisms. IEEE Transactions on Systems, Man, and Cybernetics, 7(12), 868-871.

Nakamura, Y., Hanafusa, H. (1986). Inverse kinematic solutions with singularity robustness
for robot manipulator control. Journal of Dynamic Systems, Measurement, and Control, 108(3),
163-171.

Sugihara, T. (2011). Solvability-unconcerned inverse kinematics by the Levenberg-Marquardt
method. IEEE Transactions on Robotics, 27(5), 984-991.

Flacco, F., De Luca, A., Khatib, O. (2015). Control of redundant robots under hard joint
constraints: saturation in the null space. IEEE Transactions on Robotics, 31(3), 637-654.
"""
from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

_ONE_DOF_JOINTS = (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
_HALVINGS = 8        # a step that makes the error worse is halved back at most this often
_WORSE = 1.0 + 1e-9  # "worse": a squared error above this factor times the one before; the
                     # factor lets the tiny steps that leave an exactly singular posture pass
                     # (their gain is below the roundoff of |e|^2)


class IKError(ValueError):
    """Input the inverse kinematics refuses: wrong shapes, non-finite numbers, bad settings."""


@dataclasses.dataclass(frozen=True)
class IKResult:
    """A joint reference that realises a Cartesian reference (the arrays are made read-only)."""

    q: np.ndarray           # (T, n) joint angles [rad] (slide joints: m)
    qd: np.ndarray          # (T, n) joint velocities, finite difference of q [rad/s]
    error: np.ndarray       # (T,) |fk(q_k) - x_ref_k| [m]

    def __post_init__(self):
        for array in (self.q, self.qd, self.error):
            array.setflags(write=False)

    @property
    def max_error(self) -> float:
        """The largest position error along the path [m]."""
        return float(self.error.max())

    def reachable(self, tolerance: float) -> bool:
        """Whether every sample of the path was realised within ``tolerance`` [m]."""
        return self.max_error <= tolerance


class DifferentialIK:
    """Damped least-squares position IK of one site over n one-dof joints (module docstring).

    Args:
        model: the task's model (only read; this object keeps its own MjData).
        site: name or id of the site whose position is controlled.
        qpos_adr: (n,) qpos addresses of the arm's joints (hinge or slide), in q order.
        dof_adr: (n,) dof addresses of the same joints (Jacobian columns).
        q_rest: (n,) posture the null space is pulled toward (typically the start posture).
        damping: floor of the damping lambda [m]; small (1e-3 m for an arm of ~1 m):
            larger values smooth singular passages at the cost of a lag of about
            (damping / sigma_min)^2 of the step.
        nullspace_gain: rate [1/s] of the pull toward q_rest (0 switches it off).
        limit_margin: distance kept from every joint limit (rad for hinges, m for slides).
        iterations: maximal number of steps per sample (>= 1).
        tolerance: error [m] below which a sample takes no further step.

    Raises:
        IKError: an unknown site, addresses that are not one-dof joints of the model, shapes
            or settings out of range.
    """

    def __init__(self, model: mujoco.MjModel, site: str | int, qpos_adr: np.ndarray,
                 dof_adr: np.ndarray, q_rest: np.ndarray, damping: float = 1e-3,
                 nullspace_gain: float = 5.0, limit_margin: float = 0.01,
                 iterations: int = 3, tolerance: float = 1e-5):
        self.model = model
        self.site = self._site_id(model, site)
        joints = self._joints(model, qpos_adr, dof_adr)
        self.n = len(joints)
        self.qpos_adr = np.asarray(qpos_adr, dtype=int).copy()
        self.dof_adr = np.asarray(dof_adr, dtype=int).copy()
        self.q_rest = self._vector(q_rest, 'q_rest')
        for name, value, positive in (('damping', damping, True),
                                      ('nullspace_gain', nullspace_gain, False),
                                      ('limit_margin', limit_margin, False),
                                      ('tolerance', tolerance, False)):
            if not (np.isfinite(value) and (value > 0 if positive else value >= 0)):
                raise IKError(f'{name} must be finite and {">" if positive else ">="} 0, '
                              f'got {value!r}')
        if int(iterations) != iterations or iterations < 1:
            raise IKError(f'iterations must be an integer >= 1, got {iterations!r}')
        self.damping, self.nullspace_gain = float(damping), float(nullspace_gain)
        self.limit_margin, self.tolerance = float(limit_margin), float(tolerance)
        self.iterations = int(iterations)
        # bounds (n,): limited joints' range narrowed by the margin, others unbounded
        limited = model.jnt_limited[joints].astype(bool)
        self.low = np.where(limited, model.jnt_range[joints, 0] + limit_margin, -np.inf)
        self.high = np.where(limited, model.jnt_range[joints, 1] - limit_margin, np.inf)
        if np.any(self.low > self.high):
            names = [model.joint(j).name or f'#{j}' for j in joints[self.low > self.high]]
            raise IKError(f'limit_margin {limit_margin:g} leaves no range for joints {names}')
        self._data = mujoco.MjData(model)
        self._jacp = np.zeros((3, model.nv))
        # contiguous addresses (the usual chain) index by slices: views, no copies
        self._qpos_index = self._index(self.qpos_adr)
        # the Jacobian's columns: all of jacp (None) when the arm has every dof
        self._dof_index = (None if np.array_equal(self.dof_adr, np.arange(model.nv))
                           else self._index(self.dof_adr))

    # -- set-up ---------------------------------------------------------------------------
    @staticmethod
    def _site_id(model: mujoco.MjModel, site: str | int) -> int:
        if isinstance(site, str):
            site_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
            if site_id < 0:
                raise IKError(f'the model has no site {site!r}')
            return site_id
        if not 0 <= int(site) < model.nsite:
            raise IKError(f'site id {site} out of range (the model has {model.nsite} sites)')
        return int(site)

    @staticmethod
    def _joints(model: mujoco.MjModel, qpos_adr, dof_adr) -> np.ndarray:
        """The joint ids (n,) at the qpos addresses; each a hinge or slide with that dof."""
        qpos_adr, dof_adr = np.asarray(qpos_adr), np.asarray(dof_adr)
        if (qpos_adr.ndim != 1 or dof_adr.shape != qpos_adr.shape or len(qpos_adr) == 0
                or not np.issubdtype(qpos_adr.dtype, np.integer)
                or not np.issubdtype(dof_adr.dtype, np.integer)):
            raise IKError(f'qpos_adr {qpos_adr.shape} and dof_adr {dof_adr.shape} must be equal, '
                          f'non-empty 1-D integer arrays')
        if len(set(qpos_adr.tolist())) != len(qpos_adr):
            raise IKError(f'qpos_adr {qpos_adr.tolist()} names a joint twice')
        joints = []
        for adr, dof in zip(qpos_adr.tolist(), dof_adr.tolist()):
            found = np.flatnonzero((model.jnt_qposadr == adr)
                                   & np.isin(model.jnt_type, _ONE_DOF_JOINTS))
            if len(found) != 1 or model.jnt_dofadr[found[0]] != dof:
                raise IKError(f'qpos address {adr} with dof address {dof} is not a hinge or '
                              f'slide joint of the model')
            joints.append(int(found[0]))
        return np.array(joints)

    @staticmethod
    def _index(adr: np.ndarray) -> slice | np.ndarray:
        if np.all(np.diff(adr) == 1):
            return slice(int(adr[0]), int(adr[-1]) + 1)
        return adr

    def _vector(self, q, name: str) -> np.ndarray:
        q = np.array(q, dtype=float)
        if q.shape != (self.n,):
            raise IKError(f'{name} must have shape ({self.n},), got {q.shape}')
        if not np.all(np.isfinite(q)):
            raise IKError(f'{name} must be finite, got {q.tolist()}')
        return q

    # -- kinematics -----------------------------------------------------------------------
    def _set(self, q: np.ndarray) -> None:
        self._data.qpos[self._qpos_index] = q
        mujoco.mj_kinematics(self.model, self._data)

    def _jacobian(self, out: np.ndarray) -> None:
        """The site's position Jacobian (3, n) at the posture last set, into out (3, n)."""
        mujoco.mj_comPos(self.model, self._data)
        mujoco.mj_jacSite(self.model, self._data, self._jacp, None, self.site)
        if out is not self._jacp:
            np.copyto(out, self._jacp if self._dof_index is None
                      else self._jacp[:, self._dof_index])

    def forward(self, q: np.ndarray) -> np.ndarray:
        """The site position (3,) [m] at joint angles q (n,) (no limits applied)."""
        self._set(self._vector(q, 'q'))
        return self._data.site_xpos[self.site].copy()

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """The site's position Jacobian (3, n) [m/rad] at joint angles q (n,)."""
        self._set(self._vector(q, 'q'))
        jac = np.empty((3, self.n))
        self._jacobian(jac)
        return jac

    def _backtrack(self, q: np.ndarray, q_old: np.ndarray, target: np.ndarray,
                   e_new: np.ndarray, bound: float) -> float:
        """A step q_old -> q that made the squared error worse than bound is halved back
        toward q_old until it does not (a backtracking line search without the slope term),
        at most _HALVINGS times, then dropped; this keeps the linear model's large steps
        near a singular posture from jumping across it. q and e_new (3,) are updated in
        place; returns the squared error at the new q."""
        x = self._data.site_xpos[self.site]
        for _ in range(_HALVINGS):
            mujoco.mju_addTo(q, q_old)
            mujoco.mju_scl(q, q, 0.5)
            self._set(q)
            mujoco.mju_sub(e_new, target, x)
            ee = mujoco.mju_dot(e_new, e_new)
            if ee <= bound:
                return ee
        mujoco.mju_copy(q, q_old)
        self._set(q)
        mujoco.mju_sub(e_new, target, x)
        return mujoco.mju_dot(e_new, e_new)

    # -- the path -------------------------------------------------------------------------
    def solve(self, x_ref: np.ndarray, q0: np.ndarray, dt: float) -> IKResult:
        """The joint reference of a Cartesian position reference.

        Args:
            x_ref: (T, 3) site positions [m] on the control grid; x_ref[0] should be (near)
                fk(q0), otherwise the first samples converge toward it and report the error.
            q0: (n,) joint angles at the start (clipped into the limits).
            dt: grid step [s] (scales the null-space pull and qd).

        Returns:
            IKResult with q, qd (T, n) and the position error (T,).

        Raises:
            IKError: x_ref not (T, 3) with T >= 1, q0 not (n,), non-finite input, dt <= 0.
        """
        x_ref = np.ascontiguousarray(x_ref, dtype=float)
        if x_ref.ndim != 2 or x_ref.shape[1] != 3 or len(x_ref) == 0:
            raise IKError(f'x_ref must have shape (T, 3) with T >= 1, got {x_ref.shape}')
        if not np.all(np.isfinite(x_ref)):
            bad = np.flatnonzero(~np.all(np.isfinite(x_ref), axis=1))
            raise IKError(f'x_ref must be finite; {len(bad)} samples are not, the first at '
                          f'index {bad[0]}')
        q = np.clip(self._vector(q0, 'q0'), self.low, self.high)
        if not (np.isfinite(dt) and dt > 0):
            raise IKError(f'dt must be finite and > 0, got {dt!r}')

        T, n = len(x_ref), self.n
        q_out = np.empty((T, n))
        x_out = np.empty((T, 3))
        pull = min(1.0, self.nullspace_gain * dt)
        damping2, tolerance2, iterations = self.damping ** 2, self.tolerance ** 2, self.iterations
        pulled_rest, low, high = pull * self.q_rest, self.low, self.high
        step = _Step()
        jac = self._jacp if self._dof_index is None else np.empty((3, n))   # (3, n)
        e, e_new = np.empty(3), np.empty(3)           # position errors before / after a step
        z, dq, q_old = np.empty(n), np.empty(n), np.empty(n)
        x = self._data.site_xpos[self.site]         # (3,) a view: follows every _set
        slack = _slack(q, low, high)
        self._set(q)
        for k in range(T):
            target = x_ref[k]
            mujoco.mju_sub(e, target, x)
            ee = mujoco.mju_dot(e, e)
            for i in range(iterations):
                if i > 0 and ee <= tolerance2:
                    break
                self._jacobian(jac)
                lam2 = damping2 + 0.5 * ee
                if i == 0 and pull > 0.0:
                    mujoco.mju_addScl(z, pulled_rest, q, -pull)     # z = pull (q_rest - q)
                    pulled = z
                else:
                    pulled = None
                step(dq, jac, e, pulled, lam2)
                mujoco.mju_copy(q_old, q)
                # the L1 norm bounds every joint's move: the bounds need a look only once
                # the moves since the last look add up to the distance left to the nearest
                slack -= mujoco.mju_L1(dq)
                if slack >= 0.0:
                    mujoco.mju_addTo(q, dq)
                else:
                    q, slack = _respect_limits(step, q, dq, jac, e, pulled, lam2, low, high)
                self._set(q)
                mujoco.mju_sub(e_new, target, x)
                ee_new = mujoco.mju_dot(e_new, e_new)
                bound = max(ee * _WORSE, tolerance2)
                if ee_new > bound:
                    ee_new = self._backtrack(q, q_old, target, e_new, bound)
                e, e_new, ee = e_new, e, ee_new
            q_out[k] = q
            x_out[k] = x
        error = np.sqrt(np.sum((x_out - x_ref) ** 2, axis=1))
        qd = np.gradient(q_out, dt, axis=0) if T > 1 else np.zeros((1, n))
        return IKResult(q=q_out, qd=qd, error=error)


class _Step:
    """The damped least-squares step (module docstring) on preallocated buffers:
    dq (n,) = z + J^T (J J^T + lam2 I)^-1 (e - J z) toward the error e (3,), with the joint
    displacement z (n,) projected onto J's damped null space (z None: no null-space term).
    MuJoCo's mju_* routines instead of numpy: a fraction of the call overhead on 3 x n."""

    def __init__(self):
        self.a = np.empty((3, 3))
        self.a_flat = self.a.reshape(9)         # a view
        self.eye_flat = np.eye(3).reshape(9)
        self.r = np.empty(3)
        self.y = np.empty(3)

    def __call__(self, dq: np.ndarray, jac: np.ndarray, e: np.ndarray, z: np.ndarray | None,
                 lam2: float) -> None:
        a, r, y = self.a, self.r, self.y
        mujoco.mju_mulMatMatT(a, jac, jac)
        mujoco.mju_addToScl(self.a_flat, self.eye_flat, lam2)
        if z is None:
            r = e
        else:
            mujoco.mju_mulMatVec(r, jac, z)
            mujoco.mju_sub(r, e, r)
        mujoco.mju_cholFactor(a, 0.0)
        mujoco.mju_cholSolve(y, a, r)
        mujoco.mju_mulMatTVec(dq, jac, y)
        if z is not None:
            mujoco.mju_addTo(dq, z)


def _slack(q: np.ndarray, low: np.ndarray, high: np.ndarray) -> float:
    """The distance from q (n,) to the nearest joint bound (inf without bounds)."""
    return float(np.minimum(q - low, high - q).min())


def _respect_limits(step: _Step, q: np.ndarray, dq: np.ndarray, jac: np.ndarray,
                    e: np.ndarray, z: np.ndarray | None, lam2: float, low: np.ndarray,
                    high: np.ndarray) -> tuple[np.ndarray, float]:
    """The step dq (n,) from q (n,) kept within [low, high]: the joints it would carry across
    a bound are moved onto it and the step is solved again for the others, with the locked
    joints' motion taken off the error (Flacco 2015, one pass); the result is clipped.
    Returns the new q and its slack (0 when a joint is on a bound: look again next step)."""
    q_new = q + dq
    clipped = np.clip(q_new, low, high)
    over = clipped != q_new
    if not over.any():
        return q_new, _slack(q_new, low, high)
    free = ~over
    locked = (clipped - q) * over                                   # (n,) onto the bound
    jac_free = jac * free                                           # locked columns zeroed
    step(dq, jac_free, e - jac @ locked, None if z is None else z * free, lam2)
    return np.clip(q + locked + dq, low, high), 0.0
