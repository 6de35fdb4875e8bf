"""Joint gains from the model: kp and kd for a stated closed-loop bandwidth and damping ratio.

**The rule** (independent joint control: each driven joint a decoupled second-order system,
the others held still). Joint i sees the inertia ``m_i = M(q)_ii``, the diagonal of MuJoCo's
joint-space inertia matrix at the posture (`mujoco.mj_fullM`), which includes the joint's
rotor inertia ``dof_armature``. Under the PD law ``u = kp e + kd e'`` (`psl_controller.pd_law`)
its error obeys ``m_i e'' + kd_i e' + kp_i e = 0``: natural frequency ``omega = sqrt(kp_i /
m_i)``, damping ratio ``zeta = kd_i / (2 sqrt(kp_i m_i))``. For the asked ``omega = 2 pi
bandwidth_hz`` and ``zeta``:

    kp_i = m_i omega^2,    kd_i = 2 zeta omega m_i

**Bounds** (each lowers the joint's omega and keeps zeta; the bandwidth that results and the
reason are in `Gains`):

1. *Torque*: the PD torque at a position error `MAX_POSITION_ERROR` together with a velocity
   error `MAX_VELOCITY_ERROR` stays within the joint's torque limit tau_i:
   ``kp_i e_max + kd_i v_max = m_i (omega^2 e_max + 2 zeta omega v_max) <= tau_i``, so
   ``omega <= (-zeta v_max + sqrt((zeta v_max)^2 + e_max tau_i / m_i)) / e_max``.
2. *Sampling*: the law runs once per control period T, its torque held over the period, and
   MuJoCo's semi-implicit Euler integrates the joint. That loop, with ``a = (omega T)^2 =
   kp T^2 / m`` and ``b = kd T / m``, has the characteristic polynomial ``z^2 - (2 - a - b) z
   + (1 - b)``: stable iff ``0 < b < 2`` and ``a + 2 b < 4`` (Jury); for ``b > 1`` one pole
   is negative and the torque alternates sign from period to period (chatter at the torque
   limits). The rule keeps ``omega T <= MAX_OMEGA_PERIOD`` (0.1: over 60 periods per natural
   period) and ``b = 2 zeta omega T <= MAX_DAMPING_PERIOD`` (0.5); the sampled loop's natural
   frequency is then the asked one within 0.1 % and its damping ratio within about
   ``zeta omega T`` relative (7 % at zeta 0.7 and the bound; 1 % at 3 Hz and 500 Hz, zeta 0.3).

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
MAX_DAMPING_PERIOD = 0.5         # kd T / m at most (2 is unstable, 1 chatters)


@dataclasses.dataclass(frozen=True, eq=False)
class Gains:
    """The rule's gains per driven joint (the order of ``dof_ids``)."""

    kp: np.ndarray               # (n,) N m / rad
    kd: np.ndarray               # (n,) N m s / rad
    inertia: np.ndarray          # (n,) kg m^2: M(q)_ii at the posture, armature included
    bandwidth_hz: np.ndarray     # (n,) Hz: each joint's natural frequency after the bounds
    damping_ratio: float         # as asked (the bounds keep it)
    reason: tuple[str, ...]      # (n,) why a joint's bandwidth was lowered; '' if it was not

    def controller_yaml(self, digits: int = 3) -> str:
        """The task file's ``controller:`` section with these gains, one line."""
        def numbers(v: np.ndarray) -> str:
            return ', '.join(f'{x:.{digits}g}' for x in v)
        return f'controller: {{kp: [{numbers(self.kp)}], kd: [{numbers(self.kd)}]}}'


def joint_inertia(model: mujoco.MjModel, dof_ids: np.ndarray,
                  posture_qpos: np.ndarray) -> np.ndarray:
    """m_i = M(q)_ii of the dofs at the posture (n,): `mujoco.mj_fullM` after `mj_forward`,
    armature included. ``posture_qpos``: the model's qpos (nq,), or the dofs' joint positions
    (n,) in ``dof_ids`` order, the rest of qpos at ``qpos0`` (nq wins when both fit)."""
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
    return dense[dof_ids, dof_ids].copy()


def model_gains(model: mujoco.MjModel, dof_ids: np.ndarray, posture_qpos: np.ndarray,
                torque_limits: np.ndarray, control_period: float,
                bandwidth_hz: float = DEFAULT_BANDWIDTH_HZ,
                damping_ratio: float = DEFAULT_DAMPING_RATIO,
                max_position_error: float = MAX_POSITION_ERROR,
                max_velocity_error: float = MAX_VELOCITY_ERROR) -> Gains:
    """The module docstring's rule at a posture.

    Args:
        model: the compiled model (its armature, masses, geometry).
        dof_ids: (n,) the driven joints' dof indices (``ArmModel.dof_adr``).
        posture_qpos: the posture (see `joint_inertia`).
        torque_limits: (n,) N m > 0, each joint's torque limit (the smaller magnitude of an
            asymmetric range).
        control_period: s > 0, the law's period T.
        bandwidth_hz, damping_ratio: the closed loop asked, > 0.
        max_position_error, max_velocity_error: e_max, v_max of the torque bound, > 0.

    Returns:
        `Gains`; a joint whose bound binds has its lower bandwidth and a reason.

    Raises:
        ValueError: sizes that differ, a value out of its range, a dof without inertia.
    """
    dof_ids = np.asarray(dof_ids, dtype=int).reshape(-1)
    limits = np.asarray(torque_limits, dtype=float).reshape(-1)
    if limits.shape != dof_ids.shape:
        raise ValueError(f'torque_limits has {limits.size} entries for {dof_ids.size} dofs')
    if not np.all(np.isfinite(limits)) or np.any(limits <= 0.0):
        raise ValueError(f'torque_limits must be finite and > 0, got {limits}')
    for name, value in (('control_period', control_period), ('bandwidth_hz', bandwidth_hz),
                        ('damping_ratio', damping_ratio),
                        ('max_position_error', max_position_error),
                        ('max_velocity_error', max_velocity_error)):
        if not np.isfinite(value) or value <= 0.0:
            raise ValueError(f'{name} must be finite and > 0, got {value}')
    if np.any((dof_ids < 0) | (dof_ids >= model.nv)):
        raise ValueError(f'dof_ids {dof_ids} outside the model\'s {model.nv} dofs')
    m = joint_inertia(model, dof_ids, posture_qpos)
    if np.any(m <= 0.0):
        raise ValueError(f'dofs {dof_ids[m <= 0.0]} have no inertia at the posture')
    zeta, period = float(damping_ratio), float(control_period)
    e_max, v_max = float(max_position_error), float(max_velocity_error)
    asked = 2.0 * np.pi * float(bandwidth_hz)
    # bound 1: m (omega^2 e_max + 2 zeta omega v_max) <= tau (the positive root)
    torque_omega = (-zeta * v_max + np.sqrt((zeta * v_max) ** 2 + e_max * limits / m)) / e_max
    # bound 2: omega T and kd T / m = 2 zeta omega T
    sampled_omega = min(MAX_OMEGA_PERIOD, MAX_DAMPING_PERIOD / (2.0 * zeta)) / period
    omega = np.minimum(asked, np.minimum(torque_omega, sampled_omega))
    kp, kd = m * omega ** 2, 2.0 * zeta * omega * m
    hz = omega / (2.0 * np.pi)
    reason = []
    for i in range(dof_ids.size):
        if omega[i] >= asked:
            reason.append('')
        elif torque_omega[i] <= sampled_omega:
            reason.append(
                f'torque limit {limits[i]:.3g} N m: at {e_max:g} rad and {v_max:g} rad/s of '
                f'error {bandwidth_hz:g} Hz would ask kp e {m[i] * asked ** 2 * e_max:.3g} + '
                f'kd e\' {2 * zeta * asked * m[i] * v_max:.3g} N m; {hz[i]:.3g} Hz fits')
        else:
            reason.append(
                f'control period {1e3 * period:g} ms: omega T <= {MAX_OMEGA_PERIOD:g} and '
                f'kd T / m <= {MAX_DAMPING_PERIOD:g} keep the sampled loop the continuous one '
                f'(kd T / m > 1 chatters, > 2 diverges); {hz[i]:.3g} Hz fits')
    return Gains(kp=kp, kd=kd, inertia=m, bandwidth_hz=hz, damping_ratio=zeta,
                 reason=tuple(reason))


def arm_gains(arm: 'ArmModel', posture: np.ndarray | None = None,
              bandwidth_hz: float = DEFAULT_BANDWIDTH_HZ,
              damping_ratio: float = DEFAULT_DAMPING_RATIO) -> Gains:
    """The rule on a task's arm (its instance as the arm has it applied: `ArmModel.reset`)
    at ``posture`` (the driven joints' angles; default the task's start posture), its torque
    limits (the smaller magnitude of each range) and control period."""
    task = arm.task
    q = np.asarray(task.start_posture if posture is None else posture, dtype=float)
    qpos = arm.data.qpos.copy()          # the arm's other joints (passive) as they are now
    qpos[arm.qpos_adr] = q
    limits = np.minimum(np.abs(arm.torque_low), np.abs(arm.torque_high))
    return model_gains(arm.model, arm.dof_adr, qpos, limits, task.control_period,
                       bandwidth_hz, damping_ratio)
