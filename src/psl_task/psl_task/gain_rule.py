"""Joint gains from the model: kp and kd for a stated closed-loop bandwidth and damping ratio.

**The rule** (independent joint control: each driven joint a decoupled second-order system,
the others held still). Joint i sees the inertia ``m_i = M(q)_ii``, the diagonal of MuJoCo's
joint-space inertia matrix at the (design) posture (`mujoco.mj_fullM`), which includes the joint's
rotor inertia ``dof_armature``. Under the PD law ``u = kp e + kd e'`` (`psl_controller.pd_law`)
its error obeys ``m_i e'' + kd_i e' + kp_i e = 0``: natural frequency ``omega = sqrt(kp_i /
m_i)``, damping ratio ``zeta = kd_i / (2 sqrt(kp_i m_i))``. For the asked ``omega = 2 pi
bandwidth_hz`` and ``zeta``:

    kp_i = m_i omega^2,    kd_i = 2 zeta omega m_i

**Bounds** (the bandwidth each joint gets, its damping ratio and the reason are in `Gains`):

1. *Torque* (lowers omega, keeps zeta): the PD torque at a position error
   `MAX_POSITION_ERROR` together with a velocity error `MAX_VELOCITY_ERROR` stays within the
   joint's torque limit tau_i: ``kp_i e_max + kd_i v_max = m_i (omega^2 e_max + 2 zeta omega
   v_max) <= tau_i``, so ``omega <= (-zeta v_max + sqrt((zeta v_max)^2 + e_max tau_i / m_i)) /
   e_max``.
2. *Sampling*: the law runs once per control period T, its torque held over the period, and
   MuJoCo's semi-implicit Euler integrates the joint. For one joint of inertia m, with ``a =
   kp T^2 / m`` and ``b = kd T / m``, that loop has the characteristic polynomial ``z^2 - (2 -
   a - b) z + (1 - b)``: stable iff ``0 < b < 2`` and ``a + 2 b < 4`` (Jury); for ``b > 1`` a
   pole is negative and the torque alternates sign from period to period (chatter at the
   torque limits). The rule keeps ``omega T <= MAX_OMEGA_PERIOD`` (0.1, lowering omega: over 60
   periods per natural period, the sampled loop's frequency the asked one within 0.1 %, its
   damping ratio within about ``zeta omega T`` relative).
3. *Coupling* (the sampling condition in every mode of the arm, not only the joint's own):
   joints are coupled through M's off-diagonal terms, and a mode of two joints with nearly
   coaxial axes (a 7-joint arm's first and third joints with the upper arm upright) moves
   only the light links between them. The least inertia joint i sees is ``mf_i = 1 /
   (M^-1)_ii``, what it moves when every other joint yields, the least over the postures
   given (the arm moves through them: `arm_gains` gives the demonstration's). The rule keeps
   ``kp_i T^2 / mf_i <= MAX_STIFFNESS_PERIOD`` (0.25, lowering omega) and ``kd_i T / mf_i <=
   MAX_DAMPING_PERIOD`` (0.5, lowering kd alone: the damping ratio that results is stated).
   Without it a Franka Panda moving its upper arm through upright (joints 1 and 3 coaxial,
   mf / m 0.024) has a pole of the sampled loop at -3.5 under gains from M's diagonal: it
   chatters between its torque limits (`psl check`: 69 % of the periods saturated, kd e' 95 %
   of the torque there); with the bound, none.

The defaults (`DEFAULT_BANDWIDTH_HZ` 3 Hz, `DEFAULT_DAMPING_RATIO` 0.7) are psl's compliant
control with a learned feed-forward: the embedded tasks' hand-set gains give 1.3 to 9 Hz
(most 3 to 5 Hz) at damping ratios 0.3 to 1.3; arms as published that learned after gains
were found by hand (Franka Panda: 2.0 to 2.8 Hz on its four big joints, SO-ARM100: 4.3 to 5.2
Hz) lie around them. Low enough that loads visibly spoil tracking (DESIGN.md section 4), which
the feed-forward then learns.

References:
    Craig, J. J. (2005). Introduction to Robotics: Mechanics and Control, 3rd ed., ch. 9
    ("Linear control of manipulators": control of second-order systems, control-law
    partitioning). Pearson.
    Siciliano, B., Sciavicco, L., Villani, L., Oriolo, G. (2009). Robotics: Modelling,
    Planning and Control, sec. 8.3 ("Independent joint control"). Springer.
    doi:10.1007/978-1-84628-642-1

Imports no ROS.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import mujoco
import numpy as np

if TYPE_CHECKING:
    from psl_task.arm_model import ArmModel

DEFAULT_BANDWIDTH_HZ = 3.0       # Hz, each joint's closed-loop natural frequency
DEFAULT_DAMPING_RATIO = 0.7      # each joint's closed-loop damping ratio
MAX_POSITION_ERROR = 0.1         # rad (m): e_max, answered without saturating ...
MAX_VELOCITY_ERROR = 1.0         # rad/s (m/s): ... together with v_max
MAX_OMEGA_PERIOD = 0.1           # omega T at most (the sampled loop is the continuous one)
MAX_STIFFNESS_PERIOD = 0.25      # kp T^2 / mf at most (in any mode of the coupled arm)
MAX_DAMPING_PERIOD = 0.5         # kd T / mf at most (2 is unstable, 1 chatters)
DEMO_SAMPLES = 20                # postures per demonstration segment (`arm_gains`)


@dataclasses.dataclass(frozen=True, eq=False)
class Gains:
    """The rule's gains per driven joint (the order of ``dof_ids``)."""

    kp: np.ndarray               # (n,) N m / rad
    kd: np.ndarray               # (n,) N m s / rad
    inertia: np.ndarray          # (n,) kg m^2: M(q)_ii at the posture, armature included
    free_inertia: np.ndarray     # (n,) kg m^2: 1 / (M^-1)_ii, the other joints yielding
    bandwidth_hz: np.ndarray     # (n,) Hz: each joint's natural frequency after the bounds
    damping_ratio: np.ndarray    # (n,) each joint's damping ratio after the bounds
    reason: tuple[str, ...]      # (n,) why a joint's bandwidth or damping was lowered, or ''

    def controller_yaml(self, digits: int = 3) -> str:
        """The task file's ``controller:`` section with these gains, one line."""
        def numbers(v: np.ndarray) -> str:
            return ', '.join(f'{x:.{digits}g}' for x in v)
        return f'controller: {{kp: [{numbers(self.kp)}], kd: [{numbers(self.kd)}]}}'


def mass_matrix(model: mujoco.MjModel, dof_ids: np.ndarray,
                posture_qpos: np.ndarray) -> np.ndarray:
    """MuJoCo's joint-space inertia matrix M(q) (nv, nv) at the posture (see `joint_inertia`
    for ``posture_qpos``)."""
    dof_ids = np.asarray(dof_ids, dtype=int)
    posture = np.asarray(posture_qpos, dtype=float)
    data = mujoco.MjData(model)
    if posture.shape == (model.nq,):
        data.qpos[:] = posture
    elif posture.shape == dof_ids.shape:
        data.qpos[:] = model.qpos0
        data.qpos[model.jnt_qposadr[model.dof_jntid[dof_ids]]] = posture
    else:
        raise ValueError(f'posture_qpos has {posture.size} entries: give the model\'s qpos '
                         f'({model.nq}) or one per dof ({dof_ids.size})')
    if not np.all(np.isfinite(posture)):
        raise ValueError(f'posture_qpos must be finite, got {posture}')
    mujoco.mj_forward(model, data)
    dense = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, dense)
    return dense


def joint_inertia(model: mujoco.MjModel, dof_ids: np.ndarray,
                  posture_qpos: np.ndarray) -> np.ndarray:
    """m_i = M(q)_ii of the dofs at the posture (n,): `mujoco.mj_fullM` after `mj_forward`,
    armature included. ``posture_qpos``: the model's qpos (nq,), or the dofs' joint positions
    (n,) in ``dof_ids`` order, the rest of qpos at ``qpos0`` (nq wins when both fit)."""
    dof_ids = np.asarray(dof_ids, dtype=int)
    return np.diag(mass_matrix(model, dof_ids, posture_qpos))[dof_ids].copy()


def model_gains(model: mujoco.MjModel, dof_ids: np.ndarray, posture_qpos: np.ndarray,
                torque_limits: np.ndarray, control_period: float,
                bandwidth_hz: float | np.ndarray = DEFAULT_BANDWIDTH_HZ,
                damping_ratio: float = DEFAULT_DAMPING_RATIO,
                max_position_error: float = MAX_POSITION_ERROR,
                max_velocity_error: float = MAX_VELOCITY_ERROR) -> Gains:
    """The module docstring's rule at a posture.

    Args:
        model: the compiled model (its armature, masses, geometry).
        dof_ids: (n,) the driven joints' dof indices (``ArmModel.dof_adr``).
        posture_qpos: the posture (see `joint_inertia`), or several (k, nq) or (k, n): the
            first is the design posture (its M's diagonal), all of them bound the coupled
            modes (the least free inertia over them: give the postures the arm moves through,
            e.g. the demonstration's).
        torque_limits: (n,) N m > 0, each joint's torque limit (the smaller magnitude of an
            asymmetric range).
        control_period: s > 0, the law's period T.
        bandwidth_hz, damping_ratio: the closed loop asked, > 0 (the bandwidth one for all
            joints or (n,), one per joint).
        max_position_error, max_velocity_error: e_max, v_max of the torque bound, > 0.

    Returns:
        `Gains`; a joint whose bound binds has its lower bandwidth and a reason.

    Raises:
        ValueError: sizes that differ, a value out of its range.
    """
    dof_ids = np.asarray(dof_ids, dtype=int).reshape(-1)
    limits = np.asarray(torque_limits, dtype=float).reshape(-1)
    if limits.shape != dof_ids.shape:
        raise ValueError(f'torque_limits has {limits.size} entries for {dof_ids.size} dofs')
    if not np.all(np.isfinite(limits)) or np.any(limits <= 0.0):
        raise ValueError(f'torque_limits must be finite and > 0, got {limits}')
    asked_hz = np.broadcast_to(np.asarray(bandwidth_hz, dtype=float), dof_ids.shape)
    if not np.all(np.isfinite(asked_hz)) or np.any(asked_hz <= 0.0):
        raise ValueError(f'bandwidth_hz must be finite and > 0, got {bandwidth_hz}')
    for name, value in (('control_period', control_period),
                        ('damping_ratio', damping_ratio),
                        ('max_position_error', max_position_error),
                        ('max_velocity_error', max_velocity_error)):
        if not np.isfinite(value) or value <= 0.0:
            raise ValueError(f'{name} must be finite and > 0, got {value}')
    if np.any((dof_ids < 0) | (dof_ids >= model.nv)):
        raise ValueError(f'dof_ids {dof_ids} outside the model\'s {model.nv} dofs')
    postures = np.asarray(posture_qpos, dtype=float)
    if postures.ndim == 1:
        postures = postures[None]
    elif postures.ndim != 2 or len(postures) == 0:
        raise ValueError(f'posture_qpos must be one posture or a (k, nq) / (k, n) array of them, '
                         f'got shape {postures.shape}')
    dense = [mass_matrix(model, dof_ids, q) for q in postures]
    m = np.diag(dense[0])[dof_ids].copy()      # > 0: MuJoCo compiles no massless dof
    # each joint with the other dofs yielding (passive ones too): 1 / (M^-1)_ii, the least
    # over the postures
    free = np.min([1.0 / np.diag(np.linalg.inv(d))[dof_ids] for d in dense], axis=0)
    zeta, period = float(damping_ratio), float(control_period)
    e_max, v_max = float(max_position_error), float(max_velocity_error)
    asked = 2.0 * np.pi * asked_hz
    # 1: m (omega^2 e_max + 2 zeta omega v_max) <= tau (the positive root)
    torque_omega = (-zeta * v_max + np.sqrt((zeta * v_max) ** 2 + e_max * limits / m)) / e_max
    # 2 and 3: omega T on the joint's own inertia; kp T^2 / mf
    period_omega = np.full(m.shape, MAX_OMEGA_PERIOD / period)
    coupled_omega = np.sqrt(MAX_STIFFNESS_PERIOD * free / m) / period
    omega = np.minimum.reduce([asked, torque_omega, period_omega,
                               coupled_omega])
    kp = m * omega ** 2
    kd = np.minimum(2.0 * zeta * omega * m, MAX_DAMPING_PERIOD * free / period)     # 3
    ratio = kd / (2.0 * np.sqrt(kp * m))
    hz = omega / (2.0 * np.pi)
    reason = []
    for i in range(dof_ids.size):
        why = []
        if omega[i] < asked[i]:
            if omega[i] == torque_omega[i]:
                why.append(
                    f'torque limit {limits[i]:.3g} N m: at {e_max:g} rad and {v_max:g} rad/s of '
                    f'error {asked_hz[i]:g} Hz would ask kp e {m[i] * asked[i] ** 2 * e_max:.3g} '
                    f'+ kd e\' {2 * zeta * asked[i] * m[i] * v_max:.3g} N m; {hz[i]:.3g} Hz fits')
            elif omega[i] == period_omega[i]:
                why.append(
                    f'control period {1e3 * period:g} ms: omega T <= {MAX_OMEGA_PERIOD:g} keeps '
                    f'the sampled loop the continuous one; {hz[i]:.3g} Hz fits')
            else:
                why.append(
                    f'coupled: with the other joints yielding the joint moves {free[i]:.3g} '
                    f'kg m^2 (of {m[i]:.3g}); kp T^2 / {free[i]:.3g} <= '
                    f'{MAX_STIFFNESS_PERIOD:g} keeps every mode of the sampled loop stable; '
                    f'{hz[i]:.3g} Hz fits')
        if ratio[i] < zeta * (1 - 1e-12):
            why.append(
                f'damping: kd T / {free[i]:.3g} kg m^2 (the joint\'s inertia with the others '
                f'yielding) <= {MAX_DAMPING_PERIOD:g}, or the sampled loop chatters (> 1) and '
                f'diverges (> 2); damping ratio {ratio[i]:.2g}')
        reason.append('; '.join(why))
    return Gains(kp=kp, kd=kd, inertia=m, free_inertia=free, bandwidth_hz=hz,
                 damping_ratio=ratio, reason=tuple(reason))


def arm_gains(arm: 'ArmModel', postures: np.ndarray | None = None,
              bandwidth_hz: float = DEFAULT_BANDWIDTH_HZ,
              damping_ratio: float = DEFAULT_DAMPING_RATIO) -> Gains:
    """The rule on a task's arm (its instance as the arm has it applied: `ArmModel.reset`),
    its torque limits (the smaller magnitude of each range) and control period, at
    ``postures`` (k, n) of the driven joints, the first the design posture; default the
    task's start posture, then its demonstration's waypoints and `DEMO_SAMPLES` points on
    each straight segment between them (joint space), the postures it moves through."""
    task = arm.task
    if postures is None:
        demo = task.demo_positions                    # from the start posture to the goal
        share = np.linspace(0.0, 1.0, DEMO_SAMPLES + 1)[:, None]
        postures = np.vstack([task.start_posture] + [a + share * (b - a)
                                                     for a, b in zip(demo[:-1], demo[1:])])
    postures = np.atleast_2d(np.asarray(postures, dtype=float))
    qpos = np.repeat(arm.data.qpos[None], len(postures), axis=0)   # passive joints as now
    qpos[:, arm.qpos_adr] = postures
    limits = np.minimum(np.abs(arm.torque_low), np.abs(arm.torque_high))
    return model_gains(arm.model, arm.dof_adr, qpos, limits, task.control_period,
                       bandwidth_hz, damping_ratio)
