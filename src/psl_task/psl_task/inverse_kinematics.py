"""Differential inverse kinematics of a site's position (and orientation) on a MuJoCo model.

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

Near a singular posture the error-scaled part is not enough: while the arm tracks, |e| is a
few 1e-6 m, and a direction of the task space in which the arm can hardly move (a singular
value sigma of J far below the arm's size: an elbow nearly straight, two wrist axes nearly
aligned) gets the gain sigma / (sigma^2 + lam2), hundreds of rad per m. Each sample's step
then overshoots in that direction and the next one takes it back: the joint path zig-zags
from sample to sample (seen on TALOS's arm as published, whose start posture lies near the
straight elbow: joint accelerations of 10^3-10^4 rad/s^2 along a hand path of 2 m/s^2, a
measured motion whose smoothness and tracking costs jumped between neighbouring instances).
So the damping is also selective (numerical filtering, Maciejewski and Klein 1988; per
singular direction as in Buss and Kim 2005): in the eigenbasis J J^T = U diag(sigma_i^2) U^T,
a direction with sigma_i below ``singular_region`` (eps) gets the extra damping

    lam_i^2 = singular_damping^2 (1 - sigma_i^2 / eps^2)
    dq      = z + J^T U diag(1 / (sigma_i^2 + lam2 + lam_i^2)) U^T (e - J z)

which rises continuously from 0 at eps to singular_damping^2 at a singular posture. A step
whose smallest sigma is at least eps is the Cholesky solve above, unchanged (an arm far from
its singular postures follows the very same path).

Joint limits (``jnt_range`` of limited joints, narrowed by ``limit_margin``) are hard: a step
that would cross a bound moves that joint onto the bound and is solved again without it, so
the other joints take over its share within the same step (one pass of the saturation in the
null space of Flacco 2015); the result is clipped to the bounds.

Joint velocity bounds (``max_velocity``, e.g. ``ArmModel.limits.velocity``: a URDF's
``<limit velocity>``; the safety check refuses a reference past them, as every controller psl
serves does: `psl_task.joint_limits`): the steps toward a sample, all of them together, move
each joint at most (1 - ``velocity_margin``) v_max h from where the sample began (h the time
the sample covers: dt, or a knot's stride times dt); a step that would carry a joint further
is scaled down uniformly, its direction kept (the task scaling of Flacco 2015, which shrinks
the task velocity until the joint velocity bounds hold), the null-space pull and the joints
moved onto a limit included. The hand lags the path where the path asks more than the joints
give, and catches up once it asks less (the lag is reported in ``IKResult.error``). Sample 0
(from q0 to x_ref[0]: no time passes) is not bounded. A reference is sent ending at rest
(its last velocity 0: a JointTrajectoryController refuses one ending in motion), so the last
chord is held to a quarter of it: where the hand still lags at the end, the cubic of the last
segment, which then starts at the chord's speed and ends at 0, stays within its control
points' hull (its middle one 2.5 c_last - c_prev / 2 <= 0.9 of the bound). So every chord (q_{k+1} - q_k) / dt is
within (1 - margin) v_max by construction (an interpolated sample between knots on a chord past
it is solved one by one), and so is qd. The cubic a controller interpolates between the points
(q, qd) passes its chord c only where the chord changes from sample to sample: by
1.25 c - (c_- + c_+) / 8 at a segment's middle, up to 1.5 c for a reversal, 1.125 c for a start
from rest; measured along TALOS's references (default and perturbed theta) it stays below 1.17
times the bound kept, so the default margin 0.2 keeps it below the bound itself (0.93 v_max),
within `psl_task.joint_limits.VELOCITY_SLACK`. Without a finite bound (None, inf: the default)
the path is the one without bounds, bit for bit. Not chosen: a weighted least-norm step with
weights from the bounds (Chan and Dubey 1995), which moves slow joints less everywhere (every
path changes, also far from any bound) and keeps no bound by itself.

qd is the finite difference of q (``numpy.gradient``: central inside, one-sided at the two
ends), i.e. the velocity of the very q the PD controller tracks, null-space motion and stops
at limits included; it is finite and as smooth as q.

Reported, never raised: a target out of reach or a singular posture leaves a residual in
``IKResult.error`` (T,) = |fk(q_k) - x_ref_k| [m], with q finite and within the limits; near
the edge of the reach the exact solution itself needs joint speeds without bound (q ~ square
root of the distance to the edge), so qd peaks there. One case stays stuck: an arm exactly
straight (e.g. q = 0) asked to move exactly along itself has no first-order direction to bend
in; its error grows and says so (any other direction, or a bent rest posture, bends it).

Orientation (issue 26): with ``orientation_ref`` (T, 4), unit quaternions [w, x, y, z] of
the site's orientation, the error and the Jacobian are six-dimensional,

    e = [x_ref_k - fk(q) ; w_o log(q_ref_k (x) conj(q_site(q)))]     (6,) [m]
    J = [J_p ; w_o J_r]                                               (6, n)

(log: the rotation vector of the shortest rotation, ``mju_quat2Vel``; J_r the site's
rotational Jacobian of ``mj_jacSite``; w_o = ``orientation_weight`` [m/rad]); the damping,
the tolerance and the "worse" test measure the stacked error, the step is the same formula.
This is the Cartesian-space orientation of Ude, Nemec, Petric, Morimoto (2014): the pose DMP
(`psl_controller.quaternion_dmp`) produces q_ref, this follows it. `IKResult.rotation_error`
holds the angle between the site's orientation and q_ref at each sample [rad].

Knots: a DMP's path is smooth on the scale of its basis functions (tens of ms), the control
grid is 1-2 ms. ``solve`` marches along the path in strides of s = knot_step / dt samples
(``knot_step`` 8 ms: s = 4 at 500 Hz, 8 at 1 kHz): from a solved sample a it takes the steps
above toward sample a + s directly (the null-space pull at the rate of s dt) and keeps that
knot if it ends within ``tolerance``. Where it does not (the edge of the reach, a singular
passage: where the linear model errs over a large step), the samples from the knot before a
on are solved one by one, and the knots resume once s samples in a row ended within the
tolerance. Between knots q is a cubic spline in time through each run of consecutive knots
(scipy.interpolate.CubicSpline, not-a-knot; a sample solved one by one ends a run), clipped
into the limits. The result is checked with the vectorised kinematics of
`psl_task.site_chain.SiteChain` (the whole path in a few numpy calls): an interpolated
sample more than twice the tolerance (stacked error) from its reference is solved one by one
in another pass (from the last solved sample before it; after 3 passes every sample is).
Along a reachable path the result differs from the solve of every sample (``knot_step`` 0)
only in the null space (the pull integrated over steps of s dt): <= 1e-3 rad, the hand within
twice the tolerance of the reference (test_inverse_kinematics.py,
test_knots_track_like_every_sample). A chain SiteChain refuses (ball or free joints on it) is
solved at every sample.

Speed (``solve`` of a 1000-sample circle of radius 0.1 m at dt 1 ms, default settings, CPU
time, best of 40, on the development machine): 7-joint 3-D arm 11.7 us per sample, 10-joint
planar arm 11.1 us per sample; about 22 us per sample while a joint sits on its limit (two
solves a step). Nearly all of it is Python call overhead: about 20 calls per step
(mj_kinematics, mj_comPos, mj_jacSite, and mju_* vector routines on preallocated buffers,
which cost less per call than numpy's on 3 x n arrays). These are the costs per solved sample:
with knots (above) a quarter to an eighth of the samples are solved (psl bench learn reports
the milliseconds per path of a learning session).

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

Maciejewski, A. A., Klein, C. A. (1988). Numerical filtering for the operation of robotic
manipulators through kinematically singular configurations. Journal of Robotic Systems, 5(6),
527-552.

Buss, S. R., Kim, J.-S. (2005). Selectively damped least squares for inverse kinematics.
Journal of Graphics Tools, 10(3), 37-49.

Flacco, F., De Luca, A., Khatib, O. (2015). Control of redundant robots under hard joint
constraints: saturation in the null space. IEEE Transactions on Robotics, 31(3), 637-654.

Chan, T. F., Dubey, R. V. (1995). A weighted least-norm solution based scheme for avoiding
joint limits for redundant joint manipulators. IEEE Transactions on Robotics and Automation,
11(2), 286-292.

Ude, A., Nemec, B., Petric, T., Morimoto, J. (2014). Orientation in Cartesian space dynamic
movement primitives. IEEE International Conference on Robotics and Automation (ICRA),
2997-3004.
"""
from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from psl_task.quaternion import orientation_error
from psl_task.site_chain import IKError, SiteChain

ORIENTATION_WEIGHT = 0.1   # m/rad: 1 rad of orientation error weighs as 0.1 m of position error
QUATERNION_NORM_TOLERANCE = 1e-6   # |q| of an orientation reference may be off 1 by this much
KNOT_STEP = 0.008    # s between the samples solved step by step (module docstring, "Knots")
SINGULAR_REGION = 0.05   # m/rad: a singular value of J below this gets the selective damping
SINGULAR_DAMPING = 0.02  # m: that damping at a singular posture (module docstring)
VELOCITY_MARGIN = 0.2    # share of a joint's velocity bound the steps keep below it (module
                         # docstring, "Joint velocity bounds")
_CHORD_ROUNDING = 1.0 + 1e-12   # a chord may pass the bound kept by this factor (rounding)
_LAST_CHORD = 0.25   # the last chord's share of the bound kept (module docstring, "Joint
                     # velocity bounds": a reference is sent ending at rest)
_KNOT_PASSES = 3     # passes over a path with knots before every sample is solved
_ONE_DOF_JOINTS = (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
_HALVINGS = 8        # a step that makes the error worse is halved back at most this often
_TINY = np.finfo(float).tiny   # a Cholesky pivot below this counts as not positive
_WORSE = 1.0 + 1e-9  # "worse": a squared error above this factor times the one before; the
                     # factor lets the tiny steps that leave an exactly singular posture pass
                     # (their gain is below the roundoff of |e|^2)


@dataclasses.dataclass(frozen=True)
class IKResult:
    """A joint reference that realises a Cartesian reference (the arrays are made read-only)."""

    q: np.ndarray           # (T, n) joint angles [rad] (slide joints: m)
    qd: np.ndarray          # (T, n) joint velocities, finite difference of q [rad/s]
    error: np.ndarray       # (T,) |fk(q_k) - x_ref_k| [m]
    # (T,) the angle [rad] between the site's orientation and orientation_ref (None without)
    rotation_error: np.ndarray | None = None

    def __post_init__(self):
        for array in (self.q, self.qd, self.error, self.rotation_error):
            if array is not None:
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
        orientation_weight: w_o [m/rad], the weight of the orientation error against the
            position error (only for a solve with an orientation reference).
        knot_step: time [s] between the samples solved step by step, the others
            interpolated (module docstring, "Knots"); 0 solves every sample.
        singular_region: eps [m/rad] (of the stacked Jacobian with an orientation): a
            direction whose singular value of J lies below it is damped selectively (module
            docstring); 0 switches it off.
        singular_damping: the selective damping [m] at a singular posture.
        max_velocity: the joints' velocity bounds (n,) or one for all [rad/s (m/s)], e.g.
            ``ArmModel.limits.velocity``; None or inf: unbounded (module docstring, "Joint
            velocity bounds").
        velocity_margin: the share of each bound the steps keep below it, in [0, 1).

    Raises:
        IKError: an unknown site, addresses that are not one-dof joints of the model, shapes
            or settings out of range.
    """

    def __init__(self, model: mujoco.MjModel, site: str | int, qpos_adr: np.ndarray,
                 dof_adr: np.ndarray, q_rest: np.ndarray, damping: float = 1e-3,
                 nullspace_gain: float = 5.0, limit_margin: float = 0.01,
                 iterations: int = 3, tolerance: float = 1e-5,
                 orientation_weight: float = ORIENTATION_WEIGHT, knot_step: float = KNOT_STEP,
                 singular_region: float = SINGULAR_REGION,
                 singular_damping: float = SINGULAR_DAMPING,
                 max_velocity: np.ndarray | float | None = None,
                 velocity_margin: float = VELOCITY_MARGIN):
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
                                      ('tolerance', tolerance, False),
                                      ('orientation_weight', orientation_weight, True),
                                      ('knot_step', knot_step, False),
                                      ('singular_region', singular_region, False),
                                      ('singular_damping', singular_damping, False)):
            if not (np.isfinite(value) and (value > 0 if positive else value >= 0)):
                raise IKError(f'{name} must be finite and {">" if positive else ">="} 0, '
                              f'got {value!r}')
        if int(iterations) != iterations or iterations < 1:
            raise IKError(f'iterations must be an integer >= 1, got {iterations!r}')
        if not (np.isfinite(velocity_margin) and 0.0 <= velocity_margin < 1.0):
            raise IKError(f'velocity_margin must lie in [0, 1), got {velocity_margin!r}')
        try:
            velocity = np.broadcast_to(np.inf if max_velocity is None else
                                       np.asarray(max_velocity, dtype=float), (self.n,)).copy()
        except ValueError:
            raise IKError(f'max_velocity must be one number or {self.n}, got '
                          f'{np.shape(max_velocity)}') from None
        if np.isnan(velocity).any() or not np.all(velocity > 0.0):
            raise IKError(f'max_velocity must be > 0 (inf: unbounded), got {velocity.tolist()}')
        self.max_velocity, self.velocity_margin = velocity, float(velocity_margin)
        # the joint move [rad (m)] a step may take per second of the path, (n,); None: any
        self._speed = (None if np.isinf(velocity).all()
                       else (1.0 - self.velocity_margin) * velocity)
        self.damping, self.nullspace_gain = float(damping), float(nullspace_gain)
        self.limit_margin, self.tolerance = float(limit_margin), float(tolerance)
        self.iterations = int(iterations)
        self.orientation_weight, self.knot_step = float(orientation_weight), float(knot_step)
        self.singular_region = float(singular_region)
        self.singular_damping = float(singular_damping)
        # bounds (n,): limited joints' range narrowed by the margin, others unbounded
        limited = model.jnt_limited[joints].astype(bool)
        self.low = np.where(limited, model.jnt_range[joints, 0] + limit_margin, -np.inf)
        self.high = np.where(limited, model.jnt_range[joints, 1] - limit_margin, np.inf)
        if np.any(self.low > self.high):
            names = [model.joint(j).name or f'#{j}' for j in joints[self.low > self.high]]
            raise IKError(f'limit_margin {limit_margin:g} leaves no range for joints {names}')
        self._data = mujoco.MjData(model)
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))
        # contiguous addresses (the usual chain) index by slices: views, no copies
        self._qpos_index = self._index(self.qpos_adr)
        # the Jacobian's columns: all of jacp (None) when the arm has every dof
        self._dof_index = (None if np.array_equal(self.dof_adr, np.arange(model.nv))
                           else self._index(self.dof_adr))
        self._chain = self._site_chain(joints)

    def _site_chain(self, joints: np.ndarray):
        """The vectorised kinematics of the chain (`psl_task.site_chain.SiteChain`) that
        checks interpolated samples, or None for a chain it does not follow (ball or free
        joints on it): then every sample is solved."""
        try:
            return SiteChain(self.model, self.site, joints)
        except IKError:
            return None

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

    def pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The site position (3,) [m] and orientation (4,) (unit quaternion [w, x, y, z],
        MuJoCo's ``mju_mat2Quat``) at joint angles q (n,) (no limits applied)."""
        self._set(self._vector(q, 'q'))
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, self._data.site_xmat[self.site])
        return self._data.site_xpos[self.site].copy(), quat

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """The site's position Jacobian (3, n) [m/rad] at joint angles q (n,)."""
        self._set(self._vector(q, 'q'))
        jac = np.empty((3, self.n))
        self._jacobian(jac)
        return jac

    def _backtrack(self, q: np.ndarray, q_old: np.ndarray, error, e_new: np.ndarray,
                   bound: float) -> float:
        """A step q_old -> q that made the squared error worse than bound is halved back
        toward q_old until it does not (a backtracking line search without the slope term),
        at most _HALVINGS times, then dropped; this keeps the linear model's large steps
        near a singular posture from jumping across it. q and e_new (m,) are updated in
        place (error(e_new) writes the error at the posture last set); returns the squared
        error at the new q."""
        for _ in range(_HALVINGS):
            mujoco.mju_addTo(q, q_old)
            mujoco.mju_scl(q, q, 0.5)
            self._set(q)
            error(e_new)
            ee = mujoco.mju_dot(e_new, e_new)
            if ee <= bound:
                return ee
        mujoco.mju_copy(q, q_old)
        self._set(q)
        error(e_new)
        return mujoco.mju_dot(e_new, e_new)

    # -- the path -------------------------------------------------------------------------
    def solve(self, x_ref: np.ndarray, q0: np.ndarray, dt: float,
              orientation_ref: np.ndarray | None = None) -> IKResult:
        """The joint reference of a Cartesian position (and orientation) reference.

        Args:
            x_ref: (T, 3) site positions [m] on the control grid; x_ref[0] should be (near)
                fk(q0), otherwise the first samples converge toward it and report the error.
            q0: (n,) joint angles at the start (clipped into the limits).
            dt: grid step [s] (scales the null-space pull and qd).
            orientation_ref: None (the position only), or (T, 4) unit quaternions
                [w, x, y, z] of the site's orientation on the same grid: the error is then
                six-dimensional (module docstring, "Orientation").

        Returns:
            IKResult with q, qd (T, n), the position error (T,) and, with orientation_ref,
            the orientation error (T,).

        Raises:
            IKError: x_ref not (T, 3) with T >= 1, q0 not (n,), orientation_ref not (T, 4)
                unit quaternions, non-finite input, dt <= 0.
        """
        x_ref = np.ascontiguousarray(x_ref, dtype=float)
        if x_ref.ndim != 2 or x_ref.shape[1] != 3 or len(x_ref) == 0:
            raise IKError(f'x_ref must have shape (T, 3) with T >= 1, got {x_ref.shape}')
        _check_finite(x_ref, 'x_ref')
        quat_ref = None if orientation_ref is None else _unit_quaternions(orientation_ref,
                                                                          len(x_ref))
        q = np.clip(self._vector(q0, 'q0'), self.low, self.high)
        if not (np.isfinite(dt) and dt > 0):
            raise IKError(f'dt must be finite and > 0, got {dt!r}')
        stride = max(1, int(self.knot_step / dt + 1e-9)) if self._chain is not None else 1
        path = _Path(len(x_ref), self.n)
        path.q[0] = q
        for _ in range(_KNOT_PASSES):
            self._follow(x_ref, quat_ref, dt, stride, path)
            if path.solved.all():
                break
            result, missed = self._interpolated(path.q, path.solved, x_ref, quat_ref, dt)
            if result is not None:
                return result
            path.redo(missed)
        else:
            path.redo(~path.solved)                  # every sample
            self._follow(x_ref, quat_ref, dt, stride, path)
        return self._result(path.q, self._errors(path.q, x_ref, quat_ref), dt)

    def _follow(self, x_ref: np.ndarray, quat_ref: np.ndarray | None, dt: float, stride: int,
                path: _Path) -> None:
        """The damped least-squares path (module docstring) through the samples x_ref
        (T, 3) (and quat_ref (T, 4)), continued from path.start (path.q[0] the start
        posture), into path. From a solved sample a it tries the sample b = a + stride
        (the pull at the rate of the time between) unless a sample up to it is marked
        one by one or a ended outside ``tolerance``; if b ends within it b is taken,
        otherwise the samples up to b are solved one by one from a (stride 1: every
        sample, one by one)."""
        T, n = len(x_ref), self.n
        a = path.start
        q = path.q[a].copy()                          # updated in place below
        damping2, tolerance2, iterations = self.damping ** 2, self.tolerance ** 2, self.iterations
        low, high, q_rest, gain = self.low, self.high, self.q_rest, self.nullspace_gain
        m = 3 if quat_ref is None else 6
        step_solve = _Step(m, self.singular_region, self.singular_damping)
        jac = self._jacp if (self._dof_index is None and m == 3) else np.empty((m, n))
        e, e_new = np.empty(m), np.empty(m)           # errors before / after a step
        z, dq, q_old, q_knot = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
        error = _Error(self, x_ref, quat_ref)
        jacobian = self._jacobian if m == 3 else self._pose_jacobian
        slack = _slack(q, low, high)
        self._set(q)

        speed = self._speed
        q_sample = np.empty(n)                        # q where a sample's steps began

        def reach(k: int, pull: float, pulled_rest: np.ndarray,
                  budget: np.ndarray | None = None) -> float:
            """Take the steps toward sample k from q (in place), all of them together moving
            each joint at most budget (n,) [rad] (None: any move); the squared error left."""
            nonlocal q, slack, e, e_new
            error.sample = k
            error(e)
            if budget is not None:
                mujoco.mju_copy(q_sample, q)
            ee = mujoco.mju_dot(e, e)
            for i in range(iterations):
                if i > 0 and ee <= tolerance2:
                    break
                jacobian(jac)
                lam2 = damping2 + 0.5 * ee
                if i == 0 and pull > 0.0:
                    mujoco.mju_addScl(z, pulled_rest, q, -pull)     # z = pull (q_rest - q)
                    pulled = z
                else:
                    pulled = None
                step_solve(dq, jac, e, pulled, lam2)
                mujoco.mju_copy(q_old, q)
                # the L1 norm bounds every joint's move: the bounds need a look only once
                # the moves since the last look add up to the distance left to the nearest
                slack -= mujoco.mju_L1(dq)
                if slack >= 0.0:
                    mujoco.mju_addTo(q, dq)
                else:
                    q, slack = _respect_limits(step_solve, q, dq, jac, e, pulled, lam2, low,
                                               high)
                if budget is not None and _within_budget(q, q_old, q_sample, budget):
                    slack = _slack(q, low, high)
                self._set(q)
                error(e_new)
                ee_new = mujoco.mju_dot(e_new, e_new)
                bound = max(ee * _WORSE, tolerance2)
                if ee_new > bound:
                    ee_new = self._backtrack(q, q_old, error, e_new, bound)
                e, e_new, ee = e_new, e, ee_new
            return ee

        pull = min(1.0, gain * dt)
        pulled_rest = pull * q_rest
        one_budget = None if speed is None else speed * dt
        if a == 0:
            path.within[0] = reach(0, pull, pulled_rest) <= tolerance2
            path.q[0], path.solved[0] = q, True
        while a < T - 1:
            b = min(a + stride, T - 1)
            # knots after `stride` samples within the tolerance, or a knot within it
            steady = path.within[max(0, a - stride + 1):a + 1].all()
            if b - a > 1 and steady and not path.one_by_one[a + 1:b + 1].any():
                mujoco.mju_copy(q_knot, q)
                knot_slack = slack
                knot_pull = min(1.0, gain * (b - a) * dt)
                if reach(b, knot_pull, knot_pull * q_rest,
                         None if speed is None else speed * ((b - a) * dt)) <= tolerance2:
                    path.q[b], path.solved[b] = q, True
                    path.within[a + 1:b + 1] = True
                    a = b
                    continue
                # missed: the samples one by one, from the knot before a (the path bends
                # there already: its spline would miss too)
                before = a - stride
                if before >= 0 and path.solved[before] and not path.solved[before + 1:a].any():
                    a = before
                    q[:] = path.q[a]
                    path.solved[a + 1:] = False
                    slack = _slack(q, low, high)
                else:
                    mujoco.mju_copy(q, q_knot)
                    slack = knot_slack
                self._set(q)
            for k in range(a + 1, b + 1):
                budget = one_budget if k < T - 1 or speed is None else _LAST_CHORD * one_budget
                path.within[k] = reach(k, pull, pulled_rest, budget) <= tolerance2
                path.q[k] = q
            path.solved[a + 1:b + 1] = True
            a = b

    def _pose_jacobian(self, out: np.ndarray) -> None:
        """The site's position Jacobian over w_o times its rotational one (6, n), at the
        posture last set, into out (6, n)."""
        mujoco.mj_comPos(self.model, self._data)
        mujoco.mj_jacSite(self.model, self._data, self._jacp, self._jacr, self.site)
        index = slice(None) if self._dof_index is None else self._dof_index
        out[:3] = self._jacp[:, index]
        np.multiply(self._jacr[:, index], self.orientation_weight, out=out[3:])

    def _errors(self, q: np.ndarray, x_ref: np.ndarray, quat_ref: np.ndarray | None):
        """The position errors (T,) [m] and (None without quat_ref) orientation errors (T,)
        [rad] of the postures q (T, n)."""
        if self._chain is None:
            x = np.empty_like(x_ref)
            quat = None if quat_ref is None else np.empty((len(q), 4))
            for k, q_k in enumerate(q):
                self._set(q_k)
                x[k] = self._data.site_xpos[self.site]
                if quat is not None:
                    mujoco.mju_mat2Quat(quat[k], self._data.site_xmat[self.site])
        elif quat_ref is None:
            x, quat = self._chain.forward(q), None
        else:
            x, quat = self._chain.pose(q)
        position = np.sqrt(np.sum((x - x_ref) ** 2, axis=1))
        if quat_ref is None:
            return position, None
        return position, orientation_error(quat, quat_ref)

    def _interpolated(self, q_out: np.ndarray, solved: np.ndarray, x_ref: np.ndarray,
                      quat_ref: np.ndarray | None, dt: float
                      ) -> tuple[IKResult | None, np.ndarray]:
        """The path at the solved samples (q_out[solved]) completed between knots by a cubic
        spline in time through each run of consecutive knots (a sample solved one by one
        ends a run: the spline does not see it), clipped into the limits; None if an
        interpolated sample misses its reference by more than twice ``tolerance`` (the
        stacked error: w_o times the orientation error counted as a distance); and the
        interpolated samples that missed (T,) bool (`solve` solves them one by one in its
        next pass)."""
        t = np.arange(len(x_ref)) * dt
        q = q_out.copy()
        index = np.flatnonzero(solved)
        wide = np.diff(index) > 1               # intervals with samples to interpolate
        i = 0
        while i < len(wide):
            if not wide[i]:
                i += 1
                continue
            j = i
            while j < len(wide) and wide[j]:
                j += 1
            knots = index[i:j + 1]              # a run of knots
            inner = np.arange(knots[0] + 1, knots[-1])
            inner = inner[~solved[inner]]
            from scipy.interpolate import CubicSpline   # here: 0.4 s of every start else
            q[inner] = CubicSpline(t[knots], q_out[knots], axis=0)(t[inner])
            i = j
        between = ~solved
        q[between] = np.clip(q[between], self.low, self.high)
        position, rotation = errors = self._errors(q, x_ref, quat_ref)
        missed = between & (_stacked(position, rotation, self.orientation_weight)
                            > 2.0 * self.tolerance)
        if self._speed is not None and len(q) > 1:
            # a spline through knots the steps kept within the bound may still bulge past
            # it between them: the samples of a chord past it are solved one by one too
            chord = np.abs(np.diff(q, axis=0))
            chord[-1] /= _LAST_CHORD
            fast = np.any(chord > self._speed * (dt * _CHORD_ROUNDING), axis=1)
            missed[:-1] |= between[:-1] & fast
            missed[1:] |= between[1:] & fast
        if missed.any():
            return None, missed
        return self._result(q, errors, dt), missed

    @staticmethod
    def _result(q: np.ndarray, errors, dt: float) -> IKResult:
        qd = np.gradient(q, dt, axis=0) if len(q) > 1 else np.zeros_like(q)
        return IKResult(q=q, qd=qd, error=errors[0], rotation_error=errors[1])


class _Path:
    """A path being solved over passes (`DifferentialIK.solve`): q (T, n) at the samples
    solved, which are solved, which ended within the tolerance, which a pass must solve one
    by one, and the sample the next pass starts from (what comes before it is kept)."""

    def __init__(self, length: int, n: int):
        self.q = np.zeros((length, n))
        self.solved = np.zeros(length, dtype=bool)
        self.within = np.zeros(length, dtype=bool)
        self.one_by_one = np.zeros(length, dtype=bool)
        self.start = 0

    def redo(self, samples: np.ndarray) -> None:
        """Solve the samples (T,) bool one by one in the next pass, which starts at the last
        solved sample before the first of them (the passes before it took the same
        decisions up to there, so their result is kept)."""
        first = int(np.argmax(samples))
        self.one_by_one |= samples
        self.start = int(np.flatnonzero(self.solved[:first])[-1])
        self.solved[self.start + 1:] = False


class _Error:
    """The error (3,) x_ref_k - x or (6,) [x_ref_k - x; w_o log(q_ref_k (x) conj(q_site))]
    of the posture last set, for the sample ``sample``: called with the output array."""

    def __init__(self, ik: DifferentialIK, x_ref: np.ndarray, quat_ref: np.ndarray | None):
        self.x_ref, self.quat_ref, self.sample = x_ref, quat_ref, 0
        self.x = ik._data.site_xpos[ik.site]             # views: follow every _set
        self.xmat = ik._data.site_xmat[ik.site]
        self.weight = ik.orientation_weight
        self.quat, self.conj, self.relative = np.empty(4), np.empty(4), np.empty(4)
        self.rotation = np.empty(3)

    def __call__(self, out: np.ndarray) -> None:
        k = self.sample
        if self.quat_ref is None:
            mujoco.mju_sub(out, self.x_ref[k], self.x)
            return
        mujoco.mju_sub(out[:3], self.x_ref[k], self.x)
        mujoco.mju_mat2Quat(self.quat, self.xmat)
        mujoco.mju_negQuat(self.conj, self.quat)
        mujoco.mju_mulQuat(self.relative, self.quat_ref[k], self.conj)
        mujoco.mju_quat2Vel(self.rotation, self.relative, 1.0)      # the shortest rotation
        mujoco.mju_scl(out[3:], self.rotation, self.weight)


def _stacked(position: np.ndarray, rotation: np.ndarray | None, weight: float) -> np.ndarray:
    """|e| of the stacked error [position; w_o rotation] (T,) [m]."""
    return position if rotation is None else np.sqrt(position ** 2 + (weight * rotation) ** 2)


def _check_finite(array: np.ndarray, name: str) -> None:
    if not np.all(np.isfinite(array)):
        bad = np.flatnonzero(~np.all(np.isfinite(array), axis=1))
        raise IKError(f'{name} must be finite; {len(bad)} samples are not, the first at '
                      f'index {bad[0]}')


def _unit_quaternions(orientation_ref, length: int) -> np.ndarray:
    """orientation_ref as (T, 4) unit quaternions (normalised), or IKError."""
    quat = np.array(orientation_ref, dtype=float)
    if quat.shape != (length, 4):
        raise IKError(f'orientation_ref must have shape ({length}, 4) like x_ref, got '
                      f'{quat.shape}')
    _check_finite(quat, 'orientation_ref')
    norm = np.sqrt(np.sum(quat * quat, axis=1))
    off = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE)
    if len(off):
        raise IKError(f'orientation_ref must hold unit quaternions [w, x, y, z]; sample '
                      f'{off[0]} has norm {float(norm[off[0]])!r}')
    return quat / norm[:, None]


class _Step:
    """The damped least-squares step (module docstring) on preallocated buffers:
    dq (n,) = z + J^T (J J^T + lam2 I)^-1 (e - J z) toward the error e (m,) (m = 3, or 6 with
    the orientation), with the joint displacement z (n,) projected onto J's damped null space
    (z None: no null-space term); where a singular value of J lies below `region` [m/rad],
    the selectively damped step of the module docstring (`damping` [m] at a singular
    posture; region 0: never). MuJoCo's mju_* routines instead of numpy: a fraction of the
    call overhead on m x n."""

    def __init__(self, m: int = 3, region: float = 0.0, damping: float = 0.0):
        self.a = np.empty((m, m))
        self.a_flat = self.a.reshape(m * m)     # a view
        self.eye_flat = np.eye(m).reshape(m * m)
        self.r = np.empty(m)
        self.y = np.empty(m)
        self.region2, self.damping2 = region * region, damping * damping
        self.clear = self.region2 * (1.0 + 1e-6)       # `_clear_of_region`'s shift
        self.shifted = np.empty((m, m))
        self.shifted_flat = self.shifted.reshape(m * m)          # a view
        self.sigma2, self.basis = np.empty(m), np.empty((m, m))   # J J^T's eigen-pairs
        self._quat = np.empty(4)                                  # mju_eig3's by-product

    def __call__(self, dq: np.ndarray, jac: np.ndarray, e: np.ndarray, z: np.ndarray | None,
                 lam2: float) -> None:
        a, r, y = self.a, self.r, self.y
        mujoco.mju_mulMatMatT(a, jac, jac)
        if z is None:
            r = e
        else:
            mujoco.mju_mulMatVec(r, jac, z)
            mujoco.mju_sub(r, e, r)
        if (self.region2 > 0.0 and not self._clear_of_region(a)
                and self._eigen(a) < self.region2):
            # in J J^T's eigenbasis (columns of basis): each direction's own damping
            extra = self.damping2 * np.maximum(0.0, 1.0 - self.sigma2 / self.region2)
            np.matmul(self.basis, (self.basis.T @ r) / (self.sigma2 + lam2 + extra), out=y)
        else:
            mujoco.mju_addToScl(self.a_flat, self.eye_flat, lam2)
            mujoco.mju_cholFactor(a, 0.0)
            mujoco.mju_cholSolve(y, a, r)
        mujoco.mju_mulMatTVec(dq, jac, y)
        if z is not None:
            mujoco.mju_addTo(dq, z)

    def _clear_of_region(self, a: np.ndarray) -> bool:
        """Whether J J^T = a (m, m) certainly has no eigenvalue below region^2, without its
        eigen-decomposition (which costs more than the rest of a step): a - c I is positive
        definite (its Cholesky factorisation has m positive pivots) exactly when every
        eigenvalue of a exceeds c; c = region^2 (1 + 1e-6), the margin far above the
        rounding of either computation. True only where `_eigen` would find the smallest
        eigenvalue >= region^2 too: the step is the one it would be."""
        np.copyto(self.shifted, a)
        mujoco.mju_addToScl(self.shifted_flat, self.eye_flat, -self.clear)
        return mujoco.mju_cholFactor(self.shifted, _TINY) == len(a)

    def _eigen(self, a: np.ndarray) -> float:
        """J J^T = a (m, m) into sigma2 (its eigenvalues, the squared singular values of J)
        and basis (its eigenvectors, columns); returns the smallest eigenvalue."""
        if len(a) == 3:
            mujoco.mju_eig3(self.sigma2, self.basis.reshape(9), self._quat, self.a_flat)
        else:
            self.sigma2[:], self.basis[:] = np.linalg.eigh(a)
        return float(self.sigma2.min())


def _within_budget(q: np.ndarray, q_old: np.ndarray, q_sample: np.ndarray,
                   budget: np.ndarray) -> bool:
    """The step q_old -> q (n,) scaled down uniformly (its direction kept) so that no joint
    moves further than budget (n,) from q_sample, where the sample's steps began (q_old is
    within it): q updated in place; whether it was scaled."""
    step = q - q_old
    room = np.where(step > 0.0, budget - (q_old - q_sample), budget + (q_old - q_sample))
    over = np.abs(step) > room
    if not over.any():
        return False
    scale = float(np.min(np.maximum(room[over], 0.0) / np.abs(step[over])))
    np.multiply(step, scale, out=step)
    np.add(q_old, step, out=q)
    return True


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
