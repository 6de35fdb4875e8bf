"""A task file from a robot description as published (``psl init``): nothing tuned by hand.

`generate` reads an MJCF or URDF (a path or ``package://``), an end-effector link and
optionally a base link, a start posture and the kind (point or pose), and writes a reaching
task in the form of examples/xarm7_point_reach.yaml (end-effector DMP with a learned goal point
and a learned feed-forward torque, under gravity), every value taken from the model:

- **the driven joints**: the hinge and slide joints on the chain from the base (default: the
  world) down to the end-effector link, base outward; every other joint is locked
  (``robot.locked_joints``) at 0, or the nearest end of its range;
- **the end-effector offset**: the link's frame when neither it nor the links welded to it
  have geometry (a tool frame); otherwise the far end of their geometry (collision geoms, else
  visual ones) along the direction from the last joint's axis through the geometry's centre
  (`tool_point`);
- **start and goal postures**: drawn (seeded) inside every joint range with a margin
  (`range_margin`), the gravity torque of each joint within `GRAVITY_SHARE` of its limit, the
  hand in front of the base at mid reach (start) and moved by a share of the reach (goal),
  the straight joint-space path between them kept away from singular postures: the largest
  least singular value of the hand's position Jacobian along it (`sigma_min`; Yoshikawa's
  manipulability is stated beside it in the file);
- **the target box**: centred on the hand at the goal posture, sized by the reach, shrunk
  until the default movement toward each corner ends within `REACH_MARGIN` of it by the
  policy's own inverse kinematics (`psl_optimizer.robot_check.corner_reach`, what ``psl
  check`` runs);
- **the gains**: `psl_task.gain_rule.model_gains` at the start posture for its default
  damping ratio and bandwidth, a joint's bandwidth raised where PD alone would let gravity sag
  it more than `SAG_BOUND` (`sag_bandwidth`), all lowered while the demonstration's rollout
  saturates a torque;
- control rate, duration, policy, reward weights and threshold as point_reach_3d.yaml (the
  effort weight lowered where the arm's gravity torques would use up the threshold); an
  MJCF's control rate a whole divisor of its physics rate (`_control_rate`), a slow arm's
  movement longer (`movement_duration`) and a slow closed loop given time to settle
  (`settle_time`);
- with ``kind='pose'`` (6 driven joints or more) a pose target as pose_reach_3d.yaml: the
  hand's orientation at the goal, a ``target_yaw`` range of `YAW_HALF` about it, a pose DMP and
  ``orientation_error``; box and yaw shrink together until every corner is reached within
  `REACH_MARGIN` and `ORIENTATION_MARGIN` (`psl_optimizer.robot_check.corner_reach`).

The draft is then checked as ``psl check`` checks it (`check_robot`): a file with warnings is
not written. Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import itertools
import os
from pathlib import Path
from xml.etree import ElementTree

import mujoco
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from psl_task.arm_model import ArmModel
from psl_task.gain_rule import (DEFAULT_BANDWIDTH_HZ, DEFAULT_DAMPING_RATIO, Gains,
                                joint_inertia, model_gains)
from psl_task.inverse_kinematics import SINGULAR_REGION
from psl_task.model_spec import urdf_text, visual_only
from psl_task.package_paths import PREFIX, resolve
from psl_task.schema import RobotSection
from psl_task.task import TaskDefinition, TaskError, task_from_data

RANGE_MARGIN = 0.15       # rad (m): postures keep this far inside each range ...
RANGE_MARGIN_SHARE = 0.1  # ... at most this share of the range
VELOCITY_SHARE = 0.5      # the demonstration's peak joint speed: at most this share of the limit
GRAVITY_SHARE = 0.4       # the gravity torque at a posture: at most this share of the limit
REACH_MARGIN = 0.002      # m: each corner of the box is reached this closely (psl check: 10 mm)
BOX_HALF = (0.06, 0.09, 0.11)   # the box's half-sizes as shares of the reach (x, y, z)
BOX_SHRINK = 0.8          # the box shrinks by this while a corner is out of reach
BOX_TRIES = 8
SAMPLES = 3000            # postures drawn to choose the start and the goal from
SEED = 0
SAG_BOUND = 0.05          # rad: a joint's gravity sag under PD alone the gains keep within
BANDWIDTH_STEP = 0.7      # the bandwidth shrinks by this while a torque saturates
GAIN_TRIES = 5
CONTROL_RATE = 500.0      # Hz, as point_reach_3d.yaml (an MJCF: the nearest whole divisor)
DURATION = 1.0            # s, as point_reach_3d.yaml (longer for a slow arm: movement_duration)
SLOW_STEP = 0.4           # rad the slowest joint may move within the duration
SETTLE_TIME = 0.5         # s (longer for slow closed loops: settle_time)
SUCCESS_THRESHOLD = -0.2  # as point_reach_3d.yaml
WEIGHTS = {'goal_error': 10.0, 'smoothness': 1.0e-5, 'effort': 1.0e-4, 'tracking_error': 1.0}
ORIENTATION_WEIGHT = 1.0  # a pose's orientation_error weight, as pose_reach_3d.yaml
EFFORT_SHARE = 0.1        # the effort of holding the goal posture: at most this share of the
                          # threshold (the weight is lowered where the arm is heavy)
KINDS = ('point', 'pose')  # what the hand reaches: a point, or a point and a turn about the vertical
YAW_HALF = 0.3            # rad: a pose target's yaw range about the hand's at the goal (pose_reach_3d)
ORIENTATION_MARGIN = 0.02   # rad: each pose corner is reached this closely in orientation
ONE_DOF = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


class InitError(ValueError):
    """A description psl init cannot make a task of; the message is one line."""


@dataclasses.dataclass(frozen=True)
class Chain:
    """The joints of a description as psl init splits them."""

    driven: list[str]                 # hinge and slide joints base -> end effector
    locked: dict[str, float]          # every other joint -> its value
    base: str                         # the base body ('world' by default)
    offset: np.ndarray                # (3,) the end-effector point in the link's frame [m]
    offset_from: str                  # how the offset was found, for the file's comment


@dataclasses.dataclass(frozen=True)
class Posture:
    q: np.ndarray                     # (n,) rad (m)
    hand: np.ndarray                  # (3,) m, world frame
    sigma_min: float                  # m/rad, least singular value of the position Jacobian
    manipulability: float             # sqrt(det(J J^T)) (Yoshikawa 1985)
    gravity_share: float              # max |gravity torque| / torque limit


@dataclasses.dataclass(frozen=True)
class Generated:
    """The task file's text and the task it loads as."""

    text: str
    task: TaskDefinition
    reach: list[tuple[np.ndarray, float]]   # (tau, miss [m]) at each corner of the box
    warnings: list[str]                     # psl check's (empty for a file that is written)


def generate(model: str, end_effector: str, out: Path, base: str | None = None,
             posture: np.ndarray | None = None, kind: str = 'point') -> Generated:
    """The task of the module docstring for `model` (a path or package://...), written as if
    to `out` (relative model paths in the file are relative to its folder; nothing is
    written here). Raises InitError (one line) for what cannot be made a task."""
    if kind not in KINDS:
        raise InitError(f'--kind must be one of {", ".join(KINDS)}, got {kind!r}')
    out = Path(out).resolve()
    model_ref = _model_reference(model, out)
    chain = split_joints(model_ref, end_effector, out, base)
    if kind == 'pose' and len(chain.driven) < 6:
        raise InitError(f'--kind pose needs at least 6 driven joints (a position and an '
                        f'orientation); the chain to {end_effector} has {len(chain.driven)}')
    arm = _arm(model_ref, end_effector, chain, out)
    margin_low, margin_high = _ranges(arm)
    if posture is not None:
        posture = np.asarray(posture, dtype=float)
        if posture.shape != (len(chain.driven),):
            raise InitError(f'--posture needs {len(chain.driven)} values, one per driven joint '
                            f'({", ".join(chain.driven)}), got {posture.size}')
        outside = (posture < margin_low) | (posture > margin_high)
        if np.any(outside):
            j = int(np.flatnonzero(outside)[0])
            raise InitError(f'--posture puts {chain.driven[j]} at {posture[j]:g}, outside '
                            f'[{margin_low[j]:.3g}, {margin_high[j]:.3g}] (its range with a '
                            'margin)')
    start, goals, reach = choose_postures(arm, chain, posture)
    for goal in goals:
        draft = _fit(model_ref, end_effector, chain, out, start, goal, reach, arm, kind)
        if draft is not None:
            return draft
    raise InitError(f'no goal posture of {end_effector} found whose target box psl check '
                    'passes; give a start posture (--posture)')


# -- the chain ------------------------------------------------------------------------------
def _model_reference(model: str, out: Path) -> str:
    """The model as the task file names it: package://... as given, a file relative to the
    file's folder (absolute where it is on another drive)."""
    if model.startswith(PREFIX):
        return model
    path = Path(model).expanduser().resolve()
    if not path.is_file():
        raise InitError(f'model {model}: no such file')
    if path.suffix.lower() not in ('.urdf', '.xml'):
        raise InitError(f'model {model}: a URDF (.urdf) or an MJCF (.xml)')
    relative = os.path.relpath(path, out.parent)
    return str(path) if relative.startswith('..') else relative


def _probe(model_ref: str, end_effector: str, out: Path, joints: list[str] | None = None,
           locked: dict[str, float] | None = None, offset=(0.0, 0.0, 0.0),
           start: np.ndarray | None = None, goal: np.ndarray | None = None,
           kp: np.ndarray | None = None, kd: np.ndarray | None = None) -> TaskDefinition:
    """A task of the model with the given joints, for reading the model as psl loads it."""
    n = len(joints) if joints else 1
    start = np.zeros(n) if start is None else start
    goal = start if goal is None else goal
    robot = {'model': model_ref, 'end_effector': {'body': end_effector,
                                                  'offset': [float(v) for v in offset]}}
    if joints:
        robot['joints'] = list(joints)
    if locked and 'locked_joints' in RobotSection.model_fields:
        robot['locked_joints'] = dict(locked)
    data = {'robot': robot, 'control_rate': _probe_rate(model_ref, out), 'duration': DURATION,
            'start_posture': start.tolist(), 'goal_posture': goal.tolist(),
            'task_parameters': [],
            'controller': {'kp': (np.ones(n) if kp is None else kp).tolist(),
                           'kd': (np.ones(n) if kd is None else kd).tolist()},
            'policy': {'n_basis': 5},
            'demonstration': {'times': [0.0, DURATION],
                              'positions': [start.tolist(), goal.tolist()]},
            'reward': {'weights': {}, 'success_threshold': SUCCESS_THRESHOLD}}
    return task_from_data(out, data)


def _probe_rate(model_ref: str, out: Path) -> float:
    """A control rate the model's physics rate allows, for the probe: `CONTROL_RATE` for a URDF
    (psl sets its timestep), an MJCF's own physics rate otherwise (gymnasium's pusher steps
    at 100 Hz); `_control_rate` picks the task's."""
    path = resolve(model_ref) if model_ref.startswith(PREFIX) else out.parent / model_ref
    if path.suffix.lower() != '.xml':
        return CONTROL_RATE
    try:
        return 1.0 / mujoco.MjSpec.from_file(str(path)).option.timestep
    except (ValueError, OSError):
        return CONTROL_RATE                     # the probe's load names what is wrong


def description_model(task: TaskDefinition) -> mujoco.MjModel:
    """The description as its author drew it: every link a body (a URDF's fixed links not
    fused), visual geoms kept; for the chain and the links' geometry, never simulated."""
    if task.model_path.suffix.lower() == '.urdf':
        root = ElementTree.fromstring(urdf_text(task))
        extension = root.find('mujoco')
        if extension is None:
            extension = ElementTree.SubElement(root, 'mujoco')
        compiler = extension.find('compiler')
        if compiler is None:
            compiler = ElementTree.SubElement(extension, 'compiler')
        compiler.set('discardvisual', 'false')
        compiler.set('fusestatic', 'false')
        spec = mujoco.MjSpec.from_string(ElementTree.tostring(root, encoding='unicode'))
    else:
        spec = mujoco.MjSpec.from_file(str(task.model_path))
    return spec.compile()


def split_joints(model_ref: str, end_effector: str, out: Path,
                 base: str | None = None) -> Chain:
    """The driven chain from `base` (default: the world) to the end-effector link, the joints
    locked, and the end-effector point. InitError for an unreadable model, an unknown link, a
    link not below the base, a chain without a hinge or slide joint."""
    try:
        probe = _probe(model_ref, end_effector, out)
        m = description_model(probe)
    except (TaskError, ValueError) as exc:
        raise InitError(f'cannot read the model: {_one_line(exc)}') from None
    bodies = [m.body(b).name for b in range(m.nbody)]
    for what, name in (('--end-effector', end_effector), ('--base', base)):
        if name is not None and name not in bodies:
            raise InitError(f'{what} {name!r}: the model has no such link (its links: '
                            f'{", ".join(b for b in bodies[1:] if b)})')
    tip = bodies.index(end_effector)
    root = 0 if base is None else bodies.index(base)
    path = []
    b = tip
    while b != root:
        if b == 0:
            raise InitError(f'--end-effector {end_effector!r} is not below --base {base!r}')
        path.append(b)
        b = int(m.body_parentid[b])
    path.reverse()                              # base outward
    on_chain = [j for b in path for j in range(m.njnt) if m.jnt_bodyid[j] == b]
    driven = [m.joint(j).name for j in on_chain if m.jnt_type[j] in ONE_DOF]
    if not driven:
        raise InitError(f'no hinge or slide joint between {base or "the world"} and '
                        f'{end_effector!r}: nothing to drive')
    locked = {}
    for j in range(m.njnt):
        name = m.joint(j).name
        if name in driven or not name:
            continue
        value = 0.0
        if m.jnt_type[j] in ONE_DOF and m.jnt_limited[j]:
            value = float(np.clip(0.0, *m.jnt_range[j]))
        locked[name] = value
    offset, offset_from = tool_point(m, tip, int(on_chain[-1]) if on_chain else -1)
    return Chain(driven=driven, locked=locked, base=base or 'world', offset=offset,
                 offset_from=offset_from)


def _one_line(exc: Exception) -> str:
    return ' '.join(str(exc).split())


def tool_point(m: mujoco.MjModel, tip: int, joint: int) -> tuple[np.ndarray, str]:
    """The end-effector point in link `tip`'s frame, and where it came from: the link's origin
    when it and the links welded below it have no geometry (a tool frame); otherwise the far
    end of that geometry (collision geoms, else visual ones: vertices of meshes, corners of
    the bounding boxes of primitives) along the direction from `joint`'s anchor (the last
    joint before the link) through the geometry's bounding-box centre."""
    welded = [tip]
    for b in range(tip + 1, m.nbody):           # parents come before their children
        if m.body_parentid[b] in welded and not np.any(m.jnt_bodyid == b):
            welded.append(b)
    geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] in welded]
    seen_only = visual_only(m)
    solid = [g for g in geoms if not seen_only[g]]
    kind = 'collision' if solid else 'visual'
    geoms = solid or geoms
    if not geoms:
        return np.zeros(3), 'the link\'s frame: it has no geometry (a tool frame)'
    data = mujoco.MjData(m)
    mujoco.mj_kinematics(m, data)
    points = []
    for g in geoms:
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and m.geom_dataid[g] >= 0:
            mesh = m.geom_dataid[g]
            adr, num = m.mesh_vertadr[mesh], m.mesh_vertnum[mesh]
            local = m.mesh_vert[adr:adr + num]
        else:
            centre, half = m.geom_aabb[g, :3], m.geom_aabb[g, 3:]
            local = centre + half * np.array(list(itertools.product((-1, 1), repeat=3)))
        points.append(data.geom_xpos[g] + local @ data.geom_xmat[g].reshape(3, 3).T)
    rotation = data.xmat[tip].reshape(3, 3)
    points = (np.vstack(points) - data.xpos[tip]) @ rotation    # in the link's frame
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
    anchor = (np.zeros(3) if joint < 0 else
              (data.xanchor[joint] - data.xpos[tip]) @ rotation)
    direction = centre - anchor
    if np.linalg.norm(direction) < 1e-6:
        direction = np.array([0.0, 0.0, 1.0])
    direction /= np.linalg.norm(direction)
    offset = centre + np.max((points - centre) @ direction) * direction
    return offset, (f'the far end of the {kind} geometry of {m.body(tip).name}'
                    + (f' and the links welded to it' if len(welded) > 1 else '')
                    + ', away from its joint')


# -- the model as psl loads it ----------------------------------------------------------------
def _arm(model_ref: str, end_effector: str, chain: Chain, out: Path) -> ArmModel:
    try:
        return ArmModel(_probe(model_ref, end_effector, out, chain.driven, chain.locked,
                               chain.offset,
                               start=_inside(model_ref, end_effector, chain, out)))
    except (TaskError, ValueError) as exc:
        raise InitError(_one_line(exc)) from None


def _inside(model_ref, end_effector, chain: Chain, out: Path) -> np.ndarray:
    """A posture inside every range (0 where it may be), to load the model with."""
    probe = _probe(model_ref, end_effector, out, chain.driven, chain.locked, chain.offset)
    m = description_model(probe)
    q = []
    for name in chain.driven:
        j = m.joint(name).id
        q.append(float(np.clip(0.0, *m.jnt_range[j])) if m.jnt_limited[j] else 0.0)
    return np.array(q)


def range_margin(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The margin kept inside each range: `RANGE_MARGIN`, at most `RANGE_MARGIN_SHARE` of
    the range."""
    return np.minimum(RANGE_MARGIN, RANGE_MARGIN_SHARE * (high - low))


def _ranges(arm: ArmModel) -> tuple[np.ndarray, np.ndarray]:
    """Each driven joint's range narrowed by `range_margin`: the range the postures are drawn
    from, a hinge's within [-pi, pi] (a turn more is the same posture, wound up)."""
    return _drawn_ranges(arm)[:2]


def _drawn_ranges(arm: ArmModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_ranges` and the margin of each."""
    low, high = arm.limits.position_low, arm.limits.position_high
    hinge = arm.model.jnt_type[arm.joint_ids] == int(mujoco.mjtJoint.mjJNT_HINGE)
    low = np.where(hinge, np.maximum(low, -np.pi), np.where(np.isfinite(low), low, -1.0))
    high = np.where(hinge, np.minimum(high, np.pi), np.where(np.isfinite(high), high, 1.0))
    margin = range_margin(low, high)
    return low + margin, high - margin, margin


class _Kinematics:
    """Hand, Jacobian and gravity torque of the arm at a posture (locked joints at their
    values)."""

    def __init__(self, arm: ArmModel, chain: Chain):
        self.arm, self.m = arm, arm.model
        self.data = mujoco.MjData(self.m)
        for name, value in chain.locked.items():
            j = mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_JOINT, name)
            if j >= 0 and self.m.jnt_type[j] in ONE_DOF:
                self.data.qpos[self.m.jnt_qposadr[j]] = value
        self.limit = np.maximum(np.abs(arm.torque_low), np.abs(arm.torque_high))
        self.jac = np.zeros((3, self.m.nv))

    def qpos(self, q: np.ndarray) -> np.ndarray:
        self.data.qpos[self.arm.qpos_adr] = q
        return self.data.qpos.copy()

    def at(self, q: np.ndarray) -> Posture:
        self.data.qpos[self.arm.qpos_adr] = q
        self.data.qvel[:] = 0.0
        mujoco.mj_forward(self.m, self.data)
        mujoco.mj_jacSite(self.m, self.data, self.jac, None, self.arm.ee_site)
        jac = self.jac[:, self.arm.dof_adr]
        sigma = np.linalg.svd(jac, compute_uv=False)
        gravity = (self.data.qfrc_bias - self.data.qfrc_gravcomp)[self.arm.dof_adr]
        return Posture(q=np.array(q, dtype=float), hand=self.data.site_xpos[self.arm.ee_site].copy(),
                       sigma_min=float(sigma[-1]) if len(sigma) >= 3 else 0.0,
                       manipulability=float(np.prod(sigma)),
                       gravity_share=float(np.max(np.abs(gravity) / self.limit)))


def choose_postures(arm: ArmModel, chain: Chain, start_q: np.ndarray | None = None
                    ) -> tuple[Posture, list[Posture], float]:
    """The start posture (`start_q`, or the best of `SAMPLES` drawn), the goal candidates,
    best first, and the arm's reach [m] (the farthest hand of the draws from the first
    joint).

    A start: its gravity torques within `GRAVITY_SHARE` of the limits, the hand at 35-70 % of
    the reach from the first joint, and where such postures exist, in front of it (+x) and
    above the lowest point of what does not move (the base's geometry: the floor it stands
    on); of those whose sigma_min is within 70 % of the best, the one nearest the middle of
    the ranges (the least wound-up). A goal: drawn within 0.8 rad of the start, the hand
    moved by 25-45 % of the reach and placed likewise, ranked by the least sigma_min along
    the straight joint path from the start."""
    kin = _Kinematics(arm, chain)
    low, high = _ranges(arm)
    rng = np.random.default_rng(SEED)
    draws = [kin.at(q) for q in rng.uniform(low, high, (SAMPLES, len(low)))]
    base = _base_origin(arm)
    floor = _floor(arm, base)
    reach = max(float(np.linalg.norm(p.hand - base)) for p in draws)

    def placed(p: Posture, near: float, far: float) -> bool:
        return near * reach <= np.linalg.norm(p.hand - base) <= far * reach

    def tiers(postures: list[Posture]) -> list[Posture]:
        """Those in front, above the floor and at a height between 0.6 reach below the first
        joint and 0.3 above it; else those above the floor; else all."""
        above = [p for p in postures if p.hand[2] >= floor]
        front = [p for p in above if p.hand[0] - base[0] >= 0.2 * reach
                 and -0.6 * reach <= p.hand[2] - base[2] <= 0.3 * reach]
        return front or above or postures

    if start_q is not None:
        start = kin.at(start_q)
    else:
        fit = tiers([p for p in draws
                     if p.gravity_share <= GRAVITY_SHARE and placed(p, 0.35, 0.7)])
        if not fit:
            raise InitError('no posture holds its weight within '
                            f'{100 * GRAVITY_SHARE:.0f} % of the torque limits')
        best = max(p.sigma_min for p in fit)
        middle, spread = 0.5 * (low + high), np.maximum(high - low, 1e-9)
        start = min((p for p in fit if p.sigma_min >= 0.7 * best),
                    key=lambda p: float(np.linalg.norm((p.q - middle) / spread)))
    # the demonstration's peak joint speed is about 1.9 |q_goal - q_start| / duration (a
    # minimum-jerk-like path): keep it within VELOCITY_SHARE of each joint's velocity limit
    step = np.minimum(0.8, VELOCITY_SHARE * arm.limits.velocity * movement_duration(arm) / 1.9)
    near = np.clip(rng.uniform(-step, step, (SAMPLES, len(low))) + start.q, low, high)
    ranked = []
    for q in near:
        p = kin.at(q)
        moved = float(np.linalg.norm(p.hand - start.hand))
        if not (0.25 * reach <= moved <= 0.45 * reach and p.gravity_share <= GRAVITY_SHARE
                and placed(p, 0.3, 0.8)):
            continue
        path = min(kin.at(start.q + s * (q - start.q)).sigma_min for s in (0.25, 0.5, 0.75))
        ranked.append((min(path, p.sigma_min), p))
    if not ranked:
        raise InitError('no goal posture away from the start within the ranges found')
    ranked.sort(key=lambda c: -c[0])
    goals = tiers([p for _, p in ranked])
    return start, goals[:5], reach


def movement_duration(arm: ArmModel) -> float:
    """The movement's duration [s]: `DURATION`, or longer for a slow arm, in half seconds, so
    that its slowest joint may move `SLOW_STEP` rad at a peak speed within `VELOCITY_SHARE` of
    its velocity limit (a minimum-jerk-like path peaks at about 1.9 times its mean speed):
    Kinova JACO2's 0.63 rad/s gives 2.5 s."""
    slowest = float(np.min(arm.limits.velocity))
    need = 1.9 * SLOW_STEP / (VELOCITY_SHARE * slowest)
    return float(max(DURATION, np.ceil(need / 0.5 - 1e-9) * 0.5))


def settle_time(gains: Gains) -> float:
    """The time [s] the hand is given after the movement: `SETTLE_TIME`, or, in half seconds,
    the time ln(100) / (zeta omega_n) in which the envelope exp(-zeta omega_n t) of the slowest
    joint's step response under PD falls to 1 % (Ogata, Modern Control Engineering, 5th ed.,
    sec. 5-3: its 2 % settling time 4 / (zeta omega_n) is the envelope's, the response itself
    may stay out a little longer), zeta the damping ratio asked of
    the gain rule, where the torque limits bound the gains low: gymnasium's pusher (+-2 N m
    on a shoulder moving 13.7 kg) gets 0.3 Hz, 3.5 s; at 0.5 s its hand was still 2-3 cm short
    at the end on a quarter of the held-out targets. (The joints whose damping the rule's
    sampling bound lowers are light distal ones, a wrist, whose ringing moves the hand
    little: their ratio is not the one used.)"""
    slowest = float(np.min(gains.bandwidth_hz))
    settling = np.log(100.0) / (DEFAULT_DAMPING_RATIO * 2.0 * np.pi * slowest)
    return float(max(SETTLE_TIME, np.ceil(settling / 0.5 - 1e-9) * 0.5))


def _floor(arm: ArmModel, base: np.ndarray) -> float:
    """The lowest point [m] of the geometry that no joint moves (the base the arm stands
    on), or the first joint's height less the arm's size where there is none."""
    m, data = arm.model, mujoco.MjData(arm.model)
    mujoco.mj_forward(m, data)
    moved = np.zeros(m.nbody, dtype=bool)
    for b in range(1, m.nbody):
        moved[b] = m.body_jntnum[b] > 0 or moved[m.body_parentid[b]] or m.body_mocapid[b] >= 0
    static = [g for g in range(m.ngeom) if not moved[m.geom_bodyid[g]]]
    if not static:
        return -np.inf
    corners = np.array(list(itertools.product((-1, 1), repeat=3)))
    return min(float(np.min(data.geom_xpos[g, 2] + (m.geom_aabb[g, :3] + corners
                                                   * m.geom_aabb[g, 3:])
                            @ data.geom_xmat[g].reshape(3, 3).T[:, 2])) for g in static)


def _base_origin(arm: ArmModel) -> np.ndarray:
    """Where the arm's reach is measured from: the first driven joint's anchor."""
    data = mujoco.MjData(arm.model)
    mujoco.mj_forward(arm.model, data)
    return data.xanchor[arm.joint_ids[0]].copy()


# -- the draft, fitted until psl check passes it --------------------------------------------
def _fit(model_ref, end_effector, chain, out, start, goal, reach, arm,
         kind: str = 'point') -> Generated | None:
    """The task with `start` and `goal`: the box shrunk until every corner is reached, the
    bandwidth lowered while a torque saturates; None when the box cannot be reached."""
    from psl_optimizer.robot_check import check_robot, corner_reach

    kin = _Kinematics(arm, chain)
    half = reach * np.array(BOX_HALF)
    yaw = YAW_HALF if kind == 'pose' else 0.0
    control_rate = _control_rate(arm)

    asked = sag_bandwidth(arm, kin, (start, goal))

    def draft(scale: float) -> tuple[str, TaskDefinition]:
        gains = joint_gains(arm, np.stack([kin.qpos(start.q), kin.qpos(goal.q)]),
                            asked * scale, control_rate)
        text = render(model_ref, end_effector, chain, start, goal, half, gains, arm,
                      control_rate, reach, kin, yaw)
        return text, task_from_data(out, yaml.safe_load(text))

    for _ in range(BOX_TRIES):
        text, task = draft(1.0)
        corners = corner_reach(task)
        if (max(miss for _, miss, _ in corners) > REACH_MARGIN
                or max((turn for _, _, turn in corners if turn is not None), default=0.0)
                > ORIENTATION_MARGIN):
            half, yaw = half * BOX_SHRINK, yaw * BOX_SHRINK
            continue
        scale = 1.0
        for _ in range(GAIN_TRIES):
            report = check_robot(task)
            if not any(w.startswith('torque saturation') for w in report.warnings):
                break
            scale *= BANDWIDTH_STEP
            text, task = draft(scale)
        return Generated(text=text, task=task, reach=report.reach, warnings=report.warnings)
    return None


def sag_bandwidth(arm: ArmModel, kin: '_Kinematics', postures) -> np.ndarray:
    """Each joint's bandwidth [Hz] to ask of the gain rule: its default, raised where PD alone
    would let the joint sag more than `SAG_BOUND` under gravity at one of the postures
    (kp >= |g| / SAG_BOUND, kp = m omega^2): a light arm's short links (the SO-ARM100's
    wrist) weigh much for their inertia."""
    need = np.zeros(len(arm.joint_ids))
    for posture in postures:
        kin.at(posture.q)
        gravity = np.abs((kin.data.qfrc_bias - kin.data.qfrc_gravcomp)[arm.dof_adr])
        inertia = joint_inertia(arm.model, arm.dof_adr, kin.qpos(posture.q))
        need = np.maximum(need, np.sqrt(gravity / (SAG_BOUND * inertia)) / (2 * np.pi))
    return np.maximum(DEFAULT_BANDWIDTH_HZ, need)


def joint_gains(arm: ArmModel, qpos: np.ndarray, bandwidth: np.ndarray,
                control_rate: float) -> Gains:
    """`model_gains` with each joint's own bandwidth, at the postures `qpos` (the first the
    design posture; all of them bound the coupled modes)."""
    return model_gains(arm.model, arm.dof_adr, qpos, _torque_limits(arm), 1.0 / control_rate,
                       bandwidth_hz=bandwidth, damping_ratio=DEFAULT_DAMPING_RATIO)


def _torque_limits(arm: ArmModel) -> np.ndarray:
    """Each driven joint's torque limit (the smaller magnitude of an asymmetric range)."""
    return np.minimum(np.abs(arm.torque_low), np.abs(arm.torque_high))


def _control_rate(arm: ArmModel) -> float:
    """`CONTROL_RATE` for a URDF (psl sets its timestep); for an MJCF the largest whole
    divisor of its physics rate that is at most that."""
    if arm.task.model_path.suffix.lower() == '.urdf':
        return CONTROL_RATE
    physics = 1.0 / arm.model.opt.timestep
    return physics / int(np.ceil(physics / CONTROL_RATE - 1e-9))


def _vec(values, digits: int = 4) -> str:
    return '[' + ', '.join(f'{float(v):.{digits}f}' for v in values) + ']'


def _gain_vec(values) -> str:
    return '[' + ', '.join(f'{float(v):.4g}' for v in values) + ']'


def render(model_ref, end_effector, chain: Chain, start: Posture, goal: Posture,
           half: np.ndarray, gains, arm: ArmModel, control_rate: float,
           reach: float, kin: _Kinematics, yaw: float = 0.0) -> str:
    """The commented task YAML: a point reach, or with `yaw` > 0 a pose reach (the hand's
    orientation at the goal, turned by up to `yaw` rad about the vertical)."""
    pose = yaw > 0.0
    kind = 'pose' if pose else 'point'
    centre = goal.hand
    low, high = centre - half, centre + half
    duration = movement_duration(arm)
    settle = settle_time(gains)
    limits = _torque_limits(arm)
    kin.at(goal.q)
    angles = Rotation.from_matrix(kin.data.site_xmat[arm.ee_site].reshape(3, 3)).as_euler('xyz')
    gravity = (kin.data.qfrc_bias - kin.data.qfrc_gravcomp)[arm.dof_adr]
    effort, held = WEIGHTS['effort'], float(np.mean(gravity**2))
    if held * effort > EFFORT_SHARE * abs(SUCCESS_THRESHOLD):
        effort = float(f'{EFFORT_SHARE * abs(SUCCESS_THRESHOLD) / held:.1e}')
    file = Path(arm.task.model_path).name
    marker = _free_name(arm.model, 'target')
    margin = _drawn_ranges(arm)[2]
    command = (f'psl init {model_ref} --end-effector {end_effector}'
               + (f' --base {chain.base}' if chain.base != 'world' else ''))
    urdf = arm.task.model_path.suffix.lower() == '.urdf'
    lines = [
        f'# {kind.capitalize()} reach with {file} as published, written by',
        f'#   {command}' + (' --kind pose' if pose else ''),
        f'# The hand moves from the start posture to a target {kind} that changes from instance',
        "# to instance (tau = the target's x, y, z" + (', yaw' if pose else '')
        + '), under gravity, with gains from the model',
        '# and a learned feed-forward torque. Each value says where it came from. Edit the',
        '# target box (task_parameters) to your task, then run psl check again.',
        f'name: {Path(arm.task.model_path).stem}_{end_effector}_{kind}_reach',
        f'description: {end_effector} of {file} reaches a target '
        + ('pose (point and yaw)' if pose else 'point') + ' under gravity.',
        'robot:',
        f'  model: {model_ref}',
        f'  # the end effector: {chain.offset_from}',
        f'  end_effector: {{body: {end_effector}, offset: {_vec(chain.offset)}}}',
        f'  # the chain from {chain.base} to {end_effector}, base outward:',
        f'  joints: [{", ".join(chain.driven)}]',
    ]
    if chain.locked:
        lines.append('  # every other joint, held at 0 (or the nearest end of its range):')
        lines.append('  locked_joints:')
        lines += [f'    {name}: {float(value)!r}' for name, value in chain.locked.items()]
    lines += [
        '  # torque limits ' + ' / '.join(f'{v:.3g}' for v in limits)
        + " N m and the joint ranges: the model's",
        f'control_rate: {float(control_rate)!r}   # Hz, as point_reach_3d.yaml'
        + ('' if urdf else " (a whole divisor of the model's physics rate)"),
        f'duration: {duration:.1f}        # s, '
        + ('as point_reach_3d.yaml' if duration == DURATION else
           f'for joints as slow as {np.min(arm.limits.velocity):.2g} rad/s'),
        f'settle_time: {settle:.1f}     # s, '
        + ('as point_reach_3d.yaml' if settle == SETTLE_TIME else
           f'the settling time of its slowest joint ({np.min(gains.bandwidth_hz):.2g} Hz)'),
        '',
        '# Postures drawn inside every joint range with a margin of '
        + ' / '.join(f'{v:.2g}' for v in margin) + ' rad',
        f'# (m), each joint\'s gravity torque within {100 * GRAVITY_SHARE:.0f} % of its limit. '
        'sigma_min: the least',
        "# singular value of the hand's position Jacobian [m/rad] (the inverse kinematics damps",
        f"# below {SINGULAR_REGION:g}); w: Yoshikawa's manipulability, the product of the "
        'singular values.',
        f'start_posture: {_vec(start.q)}',
        f'#   hand at {_vec(start.hand, 3)} m, sigma_min {start.sigma_min:.3f}, w '
        f'{start.manipulability:.2e}, gravity {100 * start.gravity_share:.0f} % of a limit',
        f'goal_posture: {_vec(goal.q)}',
        f'#   hand at {_vec(goal.hand, 3)} m, sigma_min {goal.sigma_min:.3f}, w '
        f'{goal.manipulability:.2e}, gravity {100 * goal.gravity_share:.0f} % of a limit',
        '',
        'target:',
        f"  position: {_vec(centre, 3)}   # the hand at goal_posture: the box's centre",
        *([f'  orientation: {_vec(angles)}   # rad, extrinsic x-y-z: the hand at goal_posture']
          if pose else []),
        f'  body: {marker}',
        '',
        f'# The target box, sized by the reach ({reach:.3f} m from the first joint): the default',
        f'# movement toward each corner ends within {1000 * REACH_MARGIN:g} mm of it (what psl '
        'check tests). Edit it;',
        '# psl check names the corners the arm does not reach.',
        'task_parameters:',
    ]
    for axis, label in enumerate('xyz'):
        lines.append(f'  - {{name: target_{label}, unit: m, low: {low[axis]:.3f}, high: '
                     f'{high[axis]:.3f}, binds: {{kind: target_position, axis: {axis}}}}}')
    if pose:
        lines.append(f'  - {{name: target_yaw, unit: rad, low: {angles[2] - yaw:.4f}, high: '
                     f'{angles[2] + yaw:.4f}, binds: {{kind: target_orientation, axis: 2}}}}'
                     f"   # the hand's turn about the vertical, +-{yaw:.2g} rad")
    lines += [
        '',
        "scene:   # a marker at the target (moved to each instance's)",
        f'  - {{name: {marker}, type: sphere, size: [0.02], position: {_vec(centre, 3)}, '
        'rgba: [0.2, 0.8, 0.2, 0.6]}',
        '',
        '# psl_task.gain_rule.model_gains at the start posture (its coupled modes bounded at '
        'the goal too),',
        '# damping ratio ' + ' / '.join(f'{v:.2g}' for v in gains.damping_ratio)
        + '; each joint\'s',
        f'# bandwidth [Hz] (the rule\'s {DEFAULT_BANDWIDTH_HZ:g}, raised where gravity would '
        f'sag the joint more than {SAG_BOUND:g} rad',
        '# under PD alone) ' + ' / '.join(f'{v:.2g}' for v in gains.bandwidth_hz)
        + ', from the joint-space inertia [kg m^2]',
        '# ' + ' / '.join(f'{v:.3g}' for v in gains.inertia)
        + ' (the rule\'s bounds: the torque limits, the control period)',
        'controller:',
        f'  kp: {_gain_vec(gains.kp)}   # N m / rad',
        f'  kd: {_gain_vec(gains.kd)}   # N m s / rad',
        '',
        f'policy:   # as {kind}_reach_3d.yaml',
        '  kind: dmp',
        '  n_basis: 5',
        '  space: end_effector   # the DMP over the hand point, joints by differential IK',
        *(['  orientation: true     # and a quaternion DMP over its orientation',
           '  learn_goal: true      # theta_K = [weights (3 x 5), goal point (3), '
           'orientation weights (3 x 5), goal rotation (3)]'] if pose else
          ['  learn_goal: true      # theta_K = [weights (3 x 5), goal point (3)]']),
        f'  feedforward: true     # theta = [theta_K, theta_D ({len(chain.driven)} x 5)]',
        '  k_s: 400.0',
        '  canonical: linear',
        '',
        'demonstration:   # from the start to the goal, straight in joint space',
        f'  times: [0.0, {duration:.1f}]',
        '  positions:',
        f'    - {_vec(start.q)}',
        f'    - {_vec(goal.q)}',
        '',
        f'reward:   # as {kind}_reach_3d.yaml',
        '  weights:',
        f'    goal_error: {WEIGHTS["goal_error"]:.1f}   # m, the hand\'s distance to the target '
        'at the end',
        *([f'    orientation_error: {ORIENTATION_WEIGHT:.1f}   # rad, the hand\'s angle to the '
           'target orientation at the end'] if pose else []),
        f'    smoothness: {WEIGHTS["smoothness"]:.1e}',
        f'    effort: {effort:.1e}'
        + ('' if effort == WEIGHTS['effort'] else
           f'   # lowered from {WEIGHTS["effort"]:g}: holding the goal posture costs '
           f'{held:.3g} N^2 m^2'),
        f'    tracking_error: {WEIGHTS["tracking_error"]:.1f}',
        f'  success_threshold: {SUCCESS_THRESHOLD:g}',
    ]
    return '\n'.join(lines) + '\n'


def _free_name(model: mujoco.MjModel, name: str) -> str:
    """`name`, or psl_`name` where the model has a body or geom of that name already."""
    taken = any(mujoco.mj_name2id(model, kind, name) >= 0
                for kind in (mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_GEOM))
    return f'psl_{name}' if taken else name
