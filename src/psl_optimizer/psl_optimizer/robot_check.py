"""What psl made of a task's robot, and what in it will hurt learning (``psl check``).

Loading a task already refuses what cannot work, with the cause and the fix (`psl_task.task`,
`psl_task.arm_model`: lengths, joint ranges, demonstration times, motors). `check_robot` reports
the rest, which runs but costs: per driven joint its range, torque limit and the mass it carries;
the end effector, the scene objects and the geoms the reward measures; and warnings with their
fix for

- **gravity sag** under PD alone: at rest the controller must supply the bias force
  ``qfrc_bias`` (gravity) with its position error, ``sag = qfrc_bias / kp`` [rad] per joint,
  and the hand moves by ``|J sag|`` [m] (`mj_jacSite`), at the start and the goal posture;
  without feed-forward a task whose hand sags more than `SAG_WARNING` is told to set
  ``policy.feedforward``;
- **torque saturation**: the share of control periods of the demonstration's rollout (batch
  mode, the default instance) in which some joint's torque sits at its limit
  (`SATURATION_WARNING`); the warning names the part of the law that saturates (its torque
  in those periods split into ``kp e``, ``kd e'`` and the feed-forward, ``e'`` from the
  measured angles' differences: exact for one physics step per period) and gives the gains
  of the gain rule (`psl_task.gain_rule`) for the task, to paste;
- **a singular posture**: the closest approach of the demonstration's reference to a
  singular posture, by the manipulability ``w = prod(sigma_1..sigma_r)`` of the hand's
  position Jacobian (``sqrt(det(J J^T))`` for r = 3; r the largest rank it has along the
  reference: 2 for a planar arm; Yoshikawa 1985), relative to ``L^r`` with L the arm's
  length (the chain of its joints' anchors to the hand); below `SINGULAR_WARNING` the hand
  cannot move along some direction there without large joint speeds;
- **targets out of reach**: a task whose policy learns a hand goal point for a target the task
  parameters move (``policy.space: end_effector``, ``learn_goal``): the default movement with
  its goal at each corner of the target range (the box of the target_position parameters,
  the others at their defaults), its joint reference by the policy's inverse kinematics; where
  the reference ends farther from the corner than `REACH_WARNING` of the success threshold
  allows (goal_error's weight times the miss), those instances cannot be fulfilled: move or
  shrink the range;
- **passive joints that move under gravity** (`passive_motion`): the arm held at its start
  posture by the task's PD law for `PASSIVE_HOLD` s; when the passive joints of the robot
  move the hand by more than `PASSIVE_HAND_WARNING` (a humanoid's waist under an arm taken
  from its full-body description) or one swings farther than `PASSIVE_SWING_WARNING` (a
  hanging leg), those that moved (`passive_warning`) are named with how far, and the fix,
  a ``robot.locked_joints: {...}`` to paste, with their angles at the start;
- **the reward's geometry**: what each measured (arm geom, obstacle geom) pair costs per
  physics step (``mj_geomDistance``, timed here at the start posture) beside the physics step
  itself; a task whose pairs cost more than `GEOMETRY_WARNING` physics steps is told which
  pairs dominate (a visual mesh measured against an obstacle costs milliseconds).

It also says where the hand is (the end-effector site) at the start and the goal posture.

References:
    Yoshikawa, T. (1985). Manipulability of robotic mechanisms. The International Journal
    of Robotics Research, 4(2), 3-9. doi:10.1177/027836498500400201
Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import itertools
import time
from collections.abc import Callable

import mujoco
import numpy as np

from psl_optimizer.batch_rollout import BatchRollouts
from psl_task.arm_model import ArmModel
from psl_task.gain_rule import Gains, arm_gains
from psl_task.model_spec import ONE_DOF_TYPES, RestingContact, robot_contacts_at_rest
from psl_task.reward_geometry import CUTOFF
from psl_task.task import TaskDefinition

SAG_WARNING = 0.005          # m of hand sag under PD alone worth a warning
SATURATION_WARNING = 0.01    # share of saturated control periods worth a warning
LIMIT_WARNING = 0.02         # rad (m): a posture this close to a joint limit is warned about
GEOMETRY_WARNING = 5.0       # the reward's distances costing more physics steps than this
TIMING_REPEATS = 20          # calls timed per pair (and physics steps per timing)
STUCK_ERROR = 0.1            # rad: a joint this far off its reference and off half its way
REACH_WARNING = 0.5          # share of |success_threshold| a corner's goal_error may use up
# manipulability / L^r below this along the reference is warned: the examples' demonstrations
# stay above 0.03; TALOS's left arm (talos_arm_point_reach) starts at 0.005 and passes 0.0009,
# where the inverse kinematics asks its wrist for 2.5 rad/s; the UR5 with a straight elbow 0.004
SINGULAR_WARNING = 1e-3


PASSIVE_HOLD = 1.0           # s the arm is held at its start posture to see passive joints move
PASSIVE_HAND_WARNING = 0.001  # m the passive joints may move the hand by in that time
PASSIVE_SWING_WARNING = 0.05  # rad (m) a passive joint of the robot may swing
PASSIVE_MOVED = 0.01         # rad (m): a passive joint moving more is named in the warning


@dataclasses.dataclass(frozen=True)
class Joint:
    name: str
    low: float | None            # rad (m for a slide); None: unlimited
    high: float | None
    torque_limit: float          # N m, the larger magnitude of the torque range
    mass_carried: float          # kg, of the bodies this joint moves


@dataclasses.dataclass(frozen=True)
class RobotReport:
    task: str
    model: str
    joints: list[Joint]
    end_effector: str
    passive_joints: list[str]
    control: str                        # control rate, physics rate and substeps
    scene: list[str]
    arm_geoms: list[str]
    obstacle_geoms: list[str]
    sag_rad: dict[str, np.ndarray]      # posture name -> (n,) rad
    sag_hand: dict[str, float]          # posture name -> m
    saturated_share: float
    contacts_at_rest: list[RestingContact]   # the robot's parts in contact at rest
    contacts_excluded: bool             # ... excluded from the simulation (the default)
    step_seconds: float                 # one physics step of the model (no reward sensors)
    pair_seconds: dict[str, float]      # 'arm geom / obstacle geom' -> one distance [s]
    warnings: list[str]
    # the target range's corners and how far the default movement toward each ends [m]
    # (a task with a learned hand goal for a moving target; else empty)
    reach: list[tuple[np.ndarray, float]] = dataclasses.field(default_factory=list)
    # where the hand (the end-effector site) is at each posture: name -> (3,) m
    hand: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    manipulability: 'Manipulability | None' = None    # along the demonstration's reference
    # of the law's torque in the saturated periods, the shares of kp e, kd e' and u_ffwd
    saturation_parts: dict[str, float] = dataclasses.field(default_factory=dict)
    rule_gains: Gains | None = None     # the gain rule's gains for the task


@dataclasses.dataclass(frozen=True)
class Manipulability:
    """The hand's position manipulability along a reference, relative to L^rank."""

    start: float                  # at the reference's first sample
    minimum: float                # its least value ...
    t: float                      # s, ... at this time of the reference ...
    q: np.ndarray                 # (n,) ... at these joint angles
    rank: int                     # r: the Jacobian's largest rank along the reference
    length: float                 # m, L: the arm's length (joint anchors to the hand)


def hand_sag(arm: ArmModel, q: np.ndarray, kp: np.ndarray) -> tuple[np.ndarray, float]:
    """Joint sag [rad] (n,) and hand displacement [m] under PD alone at rest at posture q
    (on the arm's model as it is: its task instance applied)."""
    model, data = arm.model, mujoco.MjData(arm.model)
    data.qpos[arm.qpos_adr] = q
    mujoco.mj_forward(model, data)
    sag = (data.qfrc_bias - data.qfrc_gravcomp)[arm.dof_adr] / kp    # gravcomp: cancelled
    jac = np.zeros((3, model.nv))
    mujoco.mj_jacSite(model, data, jac, None, arm.ee_site)
    return sag, float(np.linalg.norm(jac[:, arm.dof_adr] @ sag))


def corner_reach(task: TaskDefinition) -> list[tuple[np.ndarray, float, float | None]]:
    """(tau, miss [m], turn [rad] or None) at each corner of the target range: how far the
    default movement with its hand goal at that instance's target ends from it (its joint
    reference by the policy's inverse kinematics). The corners span the ``target_position``
    parameters and, where the policy learns a goal orientation (a pose DMP), the
    ``target_orientation`` ones too, the goal rotation then turned to each target's (relative
    to the demonstration's last orientation, as `psl_optimizer.ilc` composes it) and the turn
    the angle left between the hand and the target; None without. [] for a task without a
    learned hand goal or a target the task parameters move. One reference per corner."""
    from psl_controller.policy import policy_for
    from psl_task import quaternion
    from psl_task.quaternion import quaternion_of
    policy = policy_for(task)
    turns = policy.ik is not None and policy.controls_orientation
    kinds = ('target_position', 'target_orientation') if turns else ('target_position',)
    moving = [k for k, p in enumerate(task.parameters) if p.binds.kind in kinds]
    if policy.ik is None or not task.policy.learn_goal or task.target is None or not moving:
        return []
    default = policy.default_theta.copy()
    if turns:
        # the hand's final orientation is exp(goal) (x) its demonstration's: this factor maps a
        # wanted final orientation to the goal rotation that gives it
        _, last = policy.ik.pose(policy.reference(default, task.tau_default).q[-1])
        last = quaternion.product(quaternion.conjugate(last),
                                  quaternion.exp_map(default[policy.orientation_goal]))
    out = []
    for corner in itertools.product(*((task.tau_low[k], task.tau_high[k]) for k in moving)):
        tau = np.array(task.tau_default, dtype=float)
        tau[moving] = corner
        theta = default.copy()
        target, rotation = task.target_of(tau)
        theta[policy.goal] = target
        if turns:
            want = quaternion_of(rotation)
            theta[policy.orientation_goal] = quaternion.log_map(quaternion.product(want, last))
        hand, hand_quat = policy.ik.pose(policy.reference(theta, tau).q[-1])
        turn = None
        if turns:
            turn = float(np.linalg.norm(quaternion.log_map(
                quaternion.product(want, quaternion.conjugate(hand_quat)))))
        out.append((tau, float(np.linalg.norm(hand - target)), turn))
    return out


def target_reach(task: TaskDefinition) -> list[tuple[np.ndarray, float]]:
    """(tau, miss [m]) at each corner of the target range (`corner_reach`)."""
    return [(tau, miss) for tau, miss, _ in corner_reach(task)]


def orientation_reach(task: TaskDefinition) -> list[tuple[np.ndarray, float]]:
    """(tau, angle [rad]) at each corner of the target range, orientation parameters included
    (`corner_reach`); [] for a task whose policy learns no goal orientation or whose task
    parameters turn no target."""
    if not turns_target(task):
        return []
    return [(tau, turn) for tau, _, turn in corner_reach(task) if turn is not None]


def turns_target(task: TaskDefinition) -> bool:
    """Whether a task parameter turns the target (``target_orientation``)."""
    return any(p.binds.kind == 'target_orientation' for p in task.parameters)


def _far_corners(task: TaskDefinition, corners: list[tuple[np.ndarray, float]], component: str,
                 what: str, distance: Callable[[float], str], fix: str) -> str | None:
    """The warning for the corners whose miss, weighted by the reward's `component`, uses up
    more than `REACH_WARNING` of the success threshold (None: none does); `distance` words
    the largest miss."""
    weight = task.reward.weights.get(component, 0.0)
    threshold = abs(task.reward.success_threshold)
    far = [(tau, miss) for tau, miss in corners if weight * miss > REACH_WARNING * threshold]
    if not far:
        return None
    tau, miss = max(far, key=lambda c: c[1])
    return (f'{what} out of reach: at {len(far)} of the {len(corners)} corners of the target '
            f'range the hand ends up to {distance(miss)} (tau '
            f'{np.array2string(tau, precision=3)}), {component} alone {weight * miss:.3f} of '
            f"the success threshold's {threshold:g}: {fix}")


def stuck_joints(arm: ArmModel, result, reference) -> list[str]:
    """The driven joints that the model's own friction or damping keeps from following the
    demonstration's reference (rollout `result`), each named with its error, the way the
    reference moves it and the cause: a tracking error over `STUCK_ERROR` rad and over half
    that way, where the joint's frictionloss f holds it at least half that error off under kp
    (a static error up to f / kp), or its damping c slows it beyond the movement (the closed
    loop's slow pole kp / (c + kd) under 1 / duration; Ogata, Modern Control Engineering,
    sec. 5-3, an overdamped second-order system). A joint that lags for other reasons (low
    gains under gravity, which a learned feed-forward takes up) is not named. [] when the
    rollout was refused."""
    if result.refused or result.q is None:
        return []
    m, task = arm.model, arm.task
    q_ref = reference.q[:len(result.q)]
    error = np.max(np.abs(result.q - q_ref), axis=0)
    way = np.max(reference.q, axis=0) - np.min(reference.q, axis=0)
    out = []
    for j in np.flatnonzero((error > STUCK_ERROR) & (error > 0.5 * way)):
        dof = arm.dof_adr[j]
        kp, kd = task.controller.kp[j], task.controller.kd[j]
        friction, damping = m.dof_frictionloss[dof], m.dof_damping[dof]
        why = []
        if friction / max(kp, 1e-12) >= 0.5 * error[j]:
            why.append(f'frictionloss {friction:.3g} N m holds it up to '
                       f'{friction / max(kp, 1e-12):.3g} rad off under kp {kp:.3g}')
        if (damping + kd) / max(kp, 1e-12) > task.duration:
            why.append(f'damping {damping:.3g} N m s/rad slows it to a time constant of '
                       f'{(damping + kd) / max(kp, 1e-12):.3g} s under kp {kp:.3g}')
        if why:
            out.append(f'{arm.joint_names[j]} up to {error[j]:.3f} rad off (the reference moves '
                       f'it {way[j]:.3f} rad): its {" and ".join(why)}')
    return out


def hand_at(arm: ArmModel, q: np.ndarray) -> np.ndarray:
    """The end-effector site's position [m] (3,) at joint angles q (forward kinematics)."""
    data = mujoco.MjData(arm.model)
    data.qpos[arm.qpos_adr] = q
    mujoco.mj_kinematics(arm.model, data)
    return data.site_xpos[arm.ee_site].copy()


def arm_length(arm: ArmModel, q: np.ndarray) -> float:
    """L [m]: the chain of the driven joints' anchors (dof order) to the hand at posture q;
    for a serial arm the same at every posture."""
    data = mujoco.MjData(arm.model)
    data.qpos[arm.qpos_adr] = q
    mujoco.mj_kinematics(arm.model, data)
    points = np.vstack([data.xanchor[arm.joint_ids], data.site_xpos[arm.ee_site]])
    return float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))


def manipulability_along(arm: ArmModel, q: np.ndarray, dt: float) -> Manipulability:
    """The module docstring's manipulability at every sample of q (T, n): the singular values
    of the hand's position Jacobian over the driven joints (3, n), the product of the r
    largest (r: their largest numerical rank along q), over L^r."""
    model, data = arm.model, mujoco.MjData(arm.model)
    jac = np.zeros((3, model.nv))
    sigma = np.empty((len(q), min(3, len(arm.dof_adr))))
    for k, qk in enumerate(q):
        data.qpos[arm.qpos_adr] = qk
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        mujoco.mj_jacSite(model, data, jac, None, arm.ee_site)
        sigma[k] = np.linalg.svd(jac[:, arm.dof_adr], compute_uv=False)[:sigma.shape[1]]
    length = arm_length(arm, q[0])
    rank = max(1, int(np.max(np.sum(sigma > 1e-9 * max(length, 1e-9), axis=1))))
    w = np.prod(sigma[:, :rank], axis=1) / max(length, 1e-9) ** rank
    k = int(np.argmin(w))
    return Manipulability(start=float(w[0]), minimum=float(w[k]), t=k * dt, q=q[k].copy(),
                          rank=rank, length=length)


def saturation_parts(arm: ArmModel, result, at_limit: np.ndarray) -> dict[str, float]:
    """Of the law's torque in the saturated (period, joint) entries of a rollout (`at_limit`
    (N, n), the rows of torque[1:]), the shares of |kp e|, |kd e'| and |u_ffwd| ({} if none):
    torque[k] is the law on state k - 1; the measured velocity from the angles' differences
    (semi-implicit Euler: q_k = q_(k-1) + T qd_k exactly for one physics step per period)."""
    if not np.any(at_limit):
        return {}
    task, ref = arm.task, result.reference
    q = result.q
    qd = np.vstack([np.zeros((1, q.shape[1])), np.diff(q, axis=0) / task.control_period])
    parts = {'kp': task.controller.kp * (ref.q - q), 'kd': task.controller.kd * (ref.qd - qd),
             'feed-forward': ref.u_ffwd}
    sums = {name: float(np.sum(np.abs(v[:-1])[at_limit])) for name, v in parts.items()}
    total = sum(sums.values())
    return {name: value / total for name, value in sums.items()} if total > 0 else {}


@dataclasses.dataclass(frozen=True)
class PassiveMotion:
    """What the robot's passive joints do while the arm is held at rest (`passive_motion`)."""

    moved: dict[str, float]     # passive joint -> its largest excursion from the start [rad
                                # (hinge, ball: the angle), m (slide, free: the body's origin)]
    start: dict[str, float]     # passive joint -> where it starts: the value to lock it at
                                # (a free or ball joint: 0, the model's reference pose)
    hand: float                 # m, the hand's largest distance from where it started
    hand_by_passive: float      # m, ... with the driven joints put back at the start: what
                                # the passive joints alone did to it
    seconds: float              # how long the arm was held
    units: dict[str, str] = dataclasses.field(default_factory=dict)   # joint -> 'rad' | 'm'
    carry_hand: tuple[str, ...] = ()    # the passive joints between the world and the hand


def passive_motion(arm: ArmModel, seconds: float = PASSIVE_HOLD) -> PassiveMotion:
    """The arm (its task instance applied) held at the task's start posture by the task's PD
    law (`psl_controller.pd_law.law_for`: the torque limits included), each torque held over
    the control period's physics steps as the simulator holds it, for `seconds`, the passive
    joints starting at the model's reference pose at rest (as a rollout starts them): how far
    each passive joint of the robot and the hand move. Loose objects (a body hanging from the
    world by a free joint, with no driven joint below it: a ball, a puck) are not the robot's
    and are left out. The start value of a hinge or slide is kept inside its range."""
    from psl_controller.pd_law import law_for

    task, model = arm.task, arm.model
    data = mujoco.MjData(model)
    data.qpos[:] = arm.data.qpos            # the instance's placement (mocap bodies, ...)
    data.qvel[:] = 0.0
    data.mocap_pos[:], data.mocap_quat[:] = arm.data.mocap_pos, arm.data.mocap_quat
    data.qpos[arm.qpos_adr] = task.start_posture
    mujoco.mj_forward(model, data)
    joints = _robot_passive_joints(arm)
    start_qpos = data.qpos.copy()
    hand_start = data.site_xpos[arm.ee_site].copy()
    moved = dict.fromkeys((model.joint(j).name or f'#{j}' for j in joints), 0.0)
    hand = by_passive = 0.0
    probe = mujoco.MjData(model)
    law, zero = law_for(task), np.zeros(len(arm.joint_ids))
    for _ in range(int(round(seconds * task.control_rate))):
        data.ctrl[arm.actuator_ids] = law.torque(data.qpos[arm.qpos_adr],
                                                 data.qvel[arm.dof_adr], task.start_posture,
                                                 zero, zero)
        mujoco.mj_step(model, data, nstep=arm.n_substeps)
        mujoco.mj_kinematics(model, data)
        hand = max(hand, float(np.linalg.norm(data.site_xpos[arm.ee_site] - hand_start)))
        probe.qpos[:] = data.qpos
        probe.qpos[arm.qpos_adr] = task.start_posture
        mujoco.mj_kinematics(model, probe)
        by_passive = max(by_passive, float(np.linalg.norm(probe.site_xpos[arm.ee_site]
                                                          - hand_start)))
        for j, name in zip(joints, moved):
            moved[name] = max(moved[name], _excursion(model, j, data.qpos, start_qpos))
    start = {}
    for j, name in zip(joints, moved):
        value = 0.0
        if int(model.jnt_type[j]) in ONE_DOF_TYPES:
            value = float(start_qpos[model.jnt_qposadr[j]])
            if model.jnt_limited[j]:
                value = float(np.clip(value, *model.jnt_range[j]))
        start[name] = value
    units = {name: 'm' if int(model.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_SLIDE),
                                                      int(mujoco.mjtJoint.mjJNT_FREE)) else 'rad'
             for j, name in zip(joints, moved)}
    hand_body = int(model.site_bodyid[arm.ee_site])
    carry = tuple(name for j, name in zip(joints, moved)
                  if _descends(model, hand_body, int(model.jnt_bodyid[j])))
    return PassiveMotion(moved=moved, start=start, hand=hand, hand_by_passive=by_passive,
                         seconds=seconds, units=units, carry_hand=carry)


def passive_warning(motion: PassiveMotion) -> str:
    """A warning when the passive joints moved the hand by more than `PASSIVE_HAND_WARNING`
    or one swung farther than `PASSIVE_SWING_WARNING` ('' otherwise), naming those that
    moved more than `PASSIVE_MOVED` (and, when the hand moved, every one between it and the
    world that moved at all), how far, the hand's motion and the lock to paste."""
    swing = max(motion.moved.values(), default=0.0)
    if motion.hand_by_passive <= PASSIVE_HAND_WARNING and swing <= PASSIVE_SWING_WARNING:
        return ''
    moves_hand = motion.hand_by_passive > PASSIVE_HAND_WARNING
    far = {name: value for name, value in motion.moved.items()
           if value > PASSIVE_MOVED or (moves_hand and name in motion.carry_hand and value > 0)}
    # those that carry the hand first, each group the farthest first
    worst = sorted(far, key=lambda n: (n not in motion.carry_hand, -far[n]))
    lock = ', '.join(f'{name}: {motion.start[name]:.4g}' for name in far)
    return (f'passive joints move under gravity at rest: held at the start posture for '
            f'{motion.seconds:g} s, {len(far)} passive joint{"s" if len(far) > 1 else ""} of '
            'the robot moved (' + ', '.join(f'{n} {far[n]:.3f} {motion.units.get(n, "rad")}'
                                            for n in worst[:5])
            + (f', ... {len(far) - 5} more' if len(far) > 5 else '')
            + f'), which moved the hand {1000 * motion.hand_by_passive:.1f} mm: lock them at '
            'their start: '
            f'robot.locked_joints: {{{lock}}}')


def _robot_passive_joints(arm: ArmModel) -> list[int]:
    """The passive joints of the robot: every joint not driven, but those of loose objects
    (a body hanging from the world by a free joint with no driven joint in its subtree)."""
    model = arm.model
    driven = set(arm.joint_ids.tolist())
    roots = [_root(model, int(model.jnt_bodyid[j])) for j in range(model.njnt)]
    with_driven = {roots[j] for j in driven}
    loose = {roots[j] for j in range(model.njnt)
             if int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)
             and model.jnt_bodyid[j] == roots[j] and roots[j] not in with_driven}
    return [j for j in range(model.njnt) if j not in driven and roots[j] not in loose]


def _root(model: mujoco.MjModel, body: int) -> int:
    """The ancestor of `body` that hangs from the world (the body itself if it does)."""
    while model.body_parentid[body] > 0:
        body = int(model.body_parentid[body])
    return body


def _excursion(model: mujoco.MjModel, joint: int, qpos: np.ndarray,
               start: np.ndarray) -> float:
    """How far joint `joint` is from its start: |q - q0| of a hinge [rad] or slide [m], the
    rotation angle of a ball [rad], the distance of a free joint's body origin [m]."""
    adr, kind = model.jnt_qposadr[joint], int(model.jnt_type[joint])
    if kind == int(mujoco.mjtJoint.mjJNT_FREE):
        return float(np.linalg.norm(qpos[adr:adr + 3] - start[adr:adr + 3]))
    if kind == int(mujoco.mjtJoint.mjJNT_BALL):
        dot = abs(float(np.dot(qpos[adr:adr + 4], start[adr:adr + 4])))
        return 2.0 * float(np.arccos(min(1.0, dot)))
    return abs(float(qpos[adr] - start[adr]))


def geometry_cost(arm: ArmModel) -> tuple[float, dict[str, float]]:
    """Seconds of one physics step of the arm's model at the start posture, and of one signed
    distance of each (arm geom, obstacle geom) pair the reward measures there (the least of
    `TIMING_REPEATS` timings each: the cost, not the machine's noise)."""
    model, data = arm.model, mujoco.MjData(arm.model)
    data.qpos[arm.qpos_adr] = arm.task.start_posture
    mujoco.mj_forward(model, data)
    step = []
    for _ in range(TIMING_REPEATS):
        start = time.perf_counter()
        mujoco.mj_step(model, data)
        step.append(time.perf_counter() - start)
    data.qpos[arm.qpos_adr] = arm.task.start_posture
    mujoco.mj_forward(model, data)
    fromto = np.zeros(6)
    pairs = {}
    for g1 in arm.arm_geoms:
        for g2 in arm.task.reward.obstacle_geoms:
            a, b = arm.geom(g1), arm.geom(g2)
            times = []
            for _ in range(TIMING_REPEATS):
                start = time.perf_counter()
                mujoco.mj_geomDistance(model, data, a, b, CUTOFF, fromto)
                times.append(time.perf_counter() - start)
            pairs[f'{g1} / {g2}'] = min(times)
    return min(step), pairs


def geometry_warning(step_seconds: float, pair_seconds: dict[str, float]) -> str:
    """A warning when the reward's distances cost more than `GEOMETRY_WARNING` physics steps
    ('' otherwise), naming the costliest pairs."""
    total = sum(pair_seconds.values())
    if not pair_seconds or total <= GEOMETRY_WARNING * step_seconds:
        return ''
    worst = sorted(pair_seconds, key=pair_seconds.get, reverse=True)[:3]
    return (f"the reward's geometry: {len(pair_seconds)} distances cost "
            f'{1e6 * total:.0f} us per physics step, {total / step_seconds:.0f} times the step '
            f'itself ({1e6 * step_seconds:.0f} us); the costliest: '
            + ', '.join(f'{p} {1e6 * pair_seconds[p]:.0f} us' for p in worst)
            + ': list the colliding geoms (primitives, convex collision meshes) in '
            'reward.arm_geoms, not visual meshes')


def check_robot(task: TaskDefinition) -> RobotReport:
    """The report of the module docstring. Raises TaskError for a task that does not load."""
    arm = ArmModel(task)
    arm.reset(task.tau_default)             # the default instance (e.g. its payload mass)
    m = arm.model
    joints = []
    for i, (name, jid) in enumerate(zip(arm.joint_names, arm.joint_ids)):
        body = m.jnt_bodyid[jid]
        moved = [b for b in range(m.nbody) if _descends(m, b, body)]
        limited = bool(m.jnt_limited[jid])
        joints.append(Joint(name=name, low=float(m.jnt_range[jid, 0]) if limited else None,
                            high=float(m.jnt_range[jid, 1]) if limited else None,
                            torque_limit=float(max(abs(arm.torque_low[i]),
                                                   abs(arm.torque_high[i]))),
                            mass_carried=float(m.body_mass[moved].sum())))
    kp = task.controller.kp
    sag_rad, sag_hand = {}, {}
    for label, q in (('start', task.start_posture), ('goal', task.goal_posture)):
        sag_rad[label], sag_hand[label] = hand_sag(arm, q, kp)
    batch = BatchRollouts(task, n_threads=1)
    result = batch.run(batch.policy.default_theta[None], task.tau_default)[0]
    limits = np.maximum(np.abs(arm.torque_low), np.abs(arm.torque_high))
    warnings = []
    if result.refused:          # nothing ran: no torque to measure
        warnings.append(f'the demonstration is refused by the safety check ({result.refused}): '
                        'the search starts from a movement that never runs: slow it '
                        '(duration) or move the postures')
        at_limit = np.zeros((task.num_steps, task.n_joints), dtype=bool)
        reference = batch.policy.reference(batch.policy.default_theta, task.tau_default)
    else:
        at_limit = np.abs(result.torque[1:]) >= limits - 1e-9 * np.maximum(1.0, limits)
        reference = result.reference
    saturated = float(np.mean(np.any(at_limit, axis=1)))
    parts = saturation_parts(arm, result, at_limit)
    rule = arm_gains(arm)          # at the start posture, bounded along the demonstration
    hand = {label: hand_at(arm, q) for label, q in (('start', task.start_posture),
                                                    ('goal', task.goal_posture))}
    manip = manipulability_along(arm, reference.q, task.control_period)
    worst = max(sag_hand, key=sag_hand.get)
    if sag_hand[worst] > SAG_WARNING and not task.policy.feedforward:
        warnings.append(
            f'gravity sag: under PD alone the hand sits {1000 * sag_hand[worst]:.1f} mm from the '
            f'commanded point at the {worst} posture (joint sag up to '
            f'{np.max(np.abs(sag_rad[worst])):.4f} rad): set policy.feedforward: true (psl '
            'learns the torque) or robot.gravity_compensation: true, or raise controller.kp')
    near = _near_limits(arm, task)
    if near:
        warnings.append(
            f'postures at a joint limit: {near}; the safety check refuses every candidate '
            'that moves past the range (about half of the search\'s steps there): move the '
            'postures and the demonstration inside the range')
    moving = passive_warning(passive_motion(arm))
    if moving:
        warnings.append(moving)
    resting = list(robot_contacts_at_rest(task))
    excluded = task.contacts_at_rest == 'exclude'
    if resting and not excluded:
        warnings.append(
            f'the robot is in contact with itself at rest ({_contacts(resting)}): MuJoCo '
            'pushes the parts apart at every step and the arm chatters under any gains: set '
            'robot.contacts_at_rest: exclude (the default), or fix the collision meshes')
    step_seconds, pair_seconds = geometry_cost(arm)
    costly = geometry_warning(step_seconds, pair_seconds)
    if costly:
        warnings.append(costly)
    corners = corner_reach(task)
    reach = [(tau, miss) for tau, miss, _ in corners]
    far = _far_corners(task, reach, 'goal_error', 'targets',
                       lambda miss: f'{1000 * miss:.1f} mm from the target',
                       'move or shrink the target_position ranges into the arm\'s reach')
    if far:
        warnings.append(far)
    if turns_target(task):
        far = _far_corners(task, [(tau, turn) for tau, _, turn in corners if turn is not None],
                           'orientation_error', 'target orientations',
                           lambda angle: f'{angle:.3f} rad from the target orientation',
                           'narrow the target_orientation ranges')
        if far:
            warnings.append(far)
    if saturated > SATURATION_WARNING:
        joints_at = [arm.joint_names[j] for j in np.flatnonzero(np.any(at_limit, axis=0))]
        gain = max(('kp', 'kd'), key=lambda name: parts.get(name, 0.0))
        words = {'kp': 'kp e', 'kd': "kd e'", 'feed-forward': 'the feed-forward'}
        order = [gain] + [name for name in words if name != gain]
        warnings.append(
            f'torque saturation: {100 * saturated:.1f} % of the demonstration\'s control periods '
            f'hit a torque limit ({", ".join(joints_at)}); of the torque there '
            + ', '.join(f'{words[name]} makes {100 * parts.get(name, 0.0):.0f} %'
                        for name in order)
            + f': lower controller.{gain}, slow the movement (duration), or raise the motors\' '
            f'ctrlrange; the gain rule ({_rule_words(rule)}, docs/your_robot.md) picks '
            f'{rule.controller_yaml()}')
    stuck = stuck_joints(arm, result, reference)
    if stuck:
        warnings.append(
            'joints that do not follow their reference in the demonstration: '
            + '; '.join(stuck) + ': raise their controller.kp (the gain rule does not count '
            "a joint's own friction and damping), or keep the movement off them")
    if manip.minimum < SINGULAR_WARNING:
        warnings.append(
            f'near a singular posture: the hand\'s manipulability falls to '
            f'{manip.minimum:.2g} of L^{manip.rank} (L = {manip.length:.3g} m; '
            f'{manip.start:.2g} at the start) at t = {manip.t:.3g} s, q '
            f'{np.array2string(manip.q, precision=3)}: the hand cannot move along some '
            'direction there without large joint speeds: keep the postures and the '
            'demonstration away from it (a stretched arm, joint axes in line)')
    return RobotReport(task=task.name, model=str(task.model_path), joints=joints,
                       end_effector=task.end_effector_site,
                       passive_joints=list(arm.passive_joints),
                       control=(f'{task.control_rate:g} Hz, physics {1 / m.opt.timestep:g} Hz: '
                                f'each command held over {arm.n_substeps} physics step'
                                f'{"s" if arm.n_substeps > 1 else ""}'),
                       scene=[o.name for o in task.scene], arm_geoms=list(arm.arm_geoms),
                       obstacle_geoms=list(task.reward.obstacle_geoms), sag_rad=sag_rad,
                       sag_hand=sag_hand, saturated_share=saturated,
                       contacts_at_rest=resting, contacts_excluded=excluded,
                       step_seconds=step_seconds, pair_seconds=pair_seconds, warnings=warnings,
                       reach=reach, hand=hand, manipulability=manip,
                       saturation_parts=parts, rule_gains=rule)


def _rule_words(rule: Gains) -> str:
    """The gain rule's settings as the warning states them."""
    def span(values: np.ndarray, unit: str = '') -> str:
        low, high = f'{values.min():.2g}', f'{values.max():.2g}'
        return (high if low == high else f'{low} to {high}') + unit
    return (f'bandwidth {span(rule.bandwidth_hz, " Hz")}, damping ratio '
            f'{span(rule.damping_ratio)}')


def _contacts(resting: list[RestingContact]) -> str:
    return ', '.join(f'{c.body1} / {c.body2} {100 * c.depth:.1f} cm deep at the '
                     f'{" and ".join(c.postures)} posture' for c in resting)


def _near_limits(arm: ArmModel, task: TaskDefinition) -> str:
    """The driven joints whose start, goal or demonstration waypoints lie within
    `LIMIT_WARNING` of a limit (the safety check's range with its margin), named."""
    m = arm.model
    limited = m.jnt_limited[arm.joint_ids].astype(bool)
    low = m.jnt_range[arm.joint_ids, 0] + task.safety.joint_margin
    high = m.jnt_range[arm.joint_ids, 1] - task.safety.joint_margin
    q = np.vstack([task.start_posture, task.goal_posture, task.demo_positions])
    close = limited & (np.any(q - low < LIMIT_WARNING, axis=0) |
                       np.any(high - q < LIMIT_WARNING, axis=0))
    return ', '.join(arm.joint_names[j] for j in np.flatnonzero(close))


def _descends(model: mujoco.MjModel, body: int, ancestor: int) -> bool:
    while body > 0:
        if body == ancestor:
            return True
        body = model.body_parentid[body]
    return body == ancestor


def format_report(report: RobotReport) -> str:
    """The report as the text ``psl check`` prints."""
    width = max(len('joint'), *(len(j.name) for j in report.joints))
    lines = [f'task {report.task}: model {report.model}',
             f'{"joint":{width}s} {"range [rad]":>16s} {"torque limit [N m]":>19s} '
             f'{"mass moved [kg]":>16s}']
    for j in report.joints:
        rng = 'unlimited' if j.low is None else f'[{j.low:.3g}, {j.high:.3g}]'
        lines.append(f'{j.name:{width}s} {rng:>16s} {j.torque_limit:19.3g} '
                     f'{j.mass_carried:16.3g}')
    lines.append(f'passive joints (no motor, move freely): '
                 f'{", ".join(report.passive_joints) or "none"}')
    lines.append(f'control: {report.control}')
    lines.append(f'end effector: site {report.end_effector}')
    if report.scene:
        lines.append(f'scene objects: {", ".join(report.scene)}')
    if report.obstacle_geoms:
        lines.append(f'reward measures {", ".join(report.arm_geoms)} against '
                     f'{", ".join(report.obstacle_geoms)}')
        total = sum(report.pair_seconds.values())
        lines.append(f"the reward's {len(report.pair_seconds)} distances per physics step: "
                     f'{1e6 * total:.1f} us beside the step\'s {1e6 * report.step_seconds:.1f} '
                     'us (' + ', '.join(f'{p} {1e6 * t:.1f}'
                                        for p, t in report.pair_seconds.items()) + ' us)')
    if report.contacts_at_rest:
        lines.append(f'robot parts in contact at rest: {_contacts(report.contacts_at_rest)}: '
                     + ('excluded from the simulation (MuJoCo contact exclusion; '
                        'robot.contacts_at_rest: keep keeps them)' if report.contacts_excluded
                        else 'kept (robot.contacts_at_rest: keep)'))
    else:
        lines.append('robot parts in contact at rest: none')
    for label in report.sag_hand:
        lines.append(f'gravity sag under PD alone at the {label} posture: hand '
                     f'{1000 * report.sag_hand[label]:.2f} mm, joints '
                     f'{np.array2string(np.round(report.sag_rad[label], 6), precision=4)} rad')
    for label, point in report.hand.items():
        lines.append(f'hand at the {label} posture: '
                     f'({", ".join(f"{x:.3f}" for x in point)}) m')
    lines.append(f'demonstration rollout: {100 * report.saturated_share:.1f} % of control '
                 'periods at a torque limit')
    if report.manipulability is not None:
        w = report.manipulability
        lines.append(f'closest to a singular posture along the demonstration: manipulability '
                     f'{w.minimum:.3g} of L^{w.rank} (L = {w.length:.3g} m) at t = {w.t:.3g} s, '
                     f'q {np.array2string(w.q, precision=3)}; {w.start:.3g} at the start')
    if report.rule_gains is not None:
        lines.append(f'the gain rule ({_rule_words(report.rule_gains)}) picks '
                     f'{report.rule_gains.controller_yaml()}')
    if report.reach:
        worst = max(miss for _, miss in report.reach)
        lines.append(f'target range: {len(report.reach)} corners, the default movement toward '
                     f'each ends within {1000 * worst:.1f} mm of it')
    lines += [f'warning: {w}' for w in report.warnings] or ['no warnings']
    return '\n'.join(lines)
