"""The task file's schema: every section typed, every default here and only here.

One pydantic model (or a dataclass pydantic validates) per section of a task YAML: the top
level (`TaskFile`), ``robot`` (`RobotSection`, its ``end_effector``), ``controller``
(`ControllerSpec`), ``policy`` (`PolicySpec`), ``demonstration`` (`Demonstration`),
``task_parameters`` (`TaskParameterEntry`, its ``binds`` by kind: `psl_task.bindings`),
``target`` (`TargetSpec`), ``scene`` (`SceneObject`), ``homing`` (`HomingSpec`), ``safety``
(`SafetySpec`) and ``reward`` (`RewardSpec`). A key no section knows is refused anywhere,
with the section and the nearest valid key ("did you mean settle_time?"); a value of the
wrong type or out of its range is refused naming the key (`parse_task_file`).

What the sections hold together (a posture's length against the joints, the demonstration
against the duration, ...) is checked where the task is built (`psl_task.task`). The section
dataclasses are what the rest of psl reads (`TaskDefinition.policy`, ...). Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (BaseModel, BeforeValidator, ConfigDict, Field, StrictBool, TypeAdapter,
                      ValidationError, model_validator, with_config)

from psl_task.bindings import Binding, BINDINGS, binding_kind

SCENE_TYPES = {'box': 3, 'sphere': 1, 'capsule': 2, 'cylinder': 2}   # type -> size entries
Space = Literal['joint', 'end_effector']       # where the DMP runs (policy.space)
Reset = Literal['teleport', 'drive']           # how an episode begins (homing.reset)
SPACES = typing.get_args(Space)
RESETS = typing.get_args(Reset)
SECTION = ConfigDict(extra='forbid', arbitrary_types_allowed=True)


def _vector(value: Any) -> np.ndarray:
    array = np.asarray(value, dtype=float) if isinstance(value, (list, tuple, np.ndarray)) \
        else None
    if array is None or array.ndim != 1 or not np.all(np.isfinite(array)):
        raise ValueError(f'must be a list of finite numbers, got {value!r}')
    return array


def _vector3(value: Any) -> np.ndarray:
    array = _vector(value)
    if array.size != 3:
        raise ValueError(f'must be 3 finite numbers, got {value!r}')
    return array


def _matrix(value: Any) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f'must be rows of numbers, got {value!r}') from None
    if not np.all(np.isfinite(array)):
        raise ValueError('must be finite numbers')
    return array


Vector = Annotated[np.ndarray, BeforeValidator(_vector)]
Vector3 = Annotated[np.ndarray, BeforeValidator(_vector3)]
Matrix = Annotated[np.ndarray, BeforeValidator(_matrix)]
Positive = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0.0)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


def _zeros3() -> np.ndarray:
    return np.zeros(3)


# -- the sections psl reads -------------------------------------------------------------------
@with_config(SECTION)
@dataclasses.dataclass(frozen=True, eq=False)
class TargetSpec:
    """The ``target`` section: the point (and orientation) the end effector must reach, at
    the end of the movement, by default; ``target_position`` / ``target_orientation`` task
    parameters replace single coordinates of it per instance."""

    position: Vector3               # (3,) m, world frame
    orientation: Vector3 = dataclasses.field(default_factory=_zeros3)   # (3,) rad, x-y-z
    body: str = ''                  # a mocap body moved to the instance's target (display)


@with_config(SECTION)
@dataclasses.dataclass(frozen=True, eq=False)
class SceneObject:
    """One entry of the ``scene`` section: a body psl adds to the model (a mocap body with
    one geom of the same name), e.g. an obstacle, a table or a target marker."""

    name: str
    size: Vector                    # MuJoCo's geom size for the type (half-sizes, radius, ...)
    position: Vector3               # (3,) m, world frame
    type: Literal['box', 'sphere', 'capsule', 'cylinder'] = 'box'   # SCENE_TYPES
    orientation: Vector3 = dataclasses.field(default_factory=_zeros3)   # (3,) rad, x-y-z
    contacts: StrictBool = False    # collide with the robot (default: scored geometrically)
    rgba: tuple[float, float, float, float] = (0.8, 0.2, 0.2, 0.6)

    def __post_init__(self):
        if self.size.size != SCENE_TYPES[self.type]:
            raise ValueError(f'size must be {SCENE_TYPES[self.type]} finite numbers for a '
                             f'{self.type}, got {self.size.tolist()}')
        if not np.all(self.size > 0.0):
            raise ValueError(f'sizes must be > 0, got {self.size.tolist()}')


@with_config(SECTION)
@dataclasses.dataclass(frozen=True, eq=False)
class ControllerSpec:
    """The ``controller`` section: gains of the PD + feed-forward law, per joint (actuator
    order). Torque limits come from the model."""

    kp: Vector                      # (n_joints,) N m / rad
    kd: Vector                      # (n_joints,) N m s / rad


@with_config(SECTION)
@dataclasses.dataclass(frozen=True)
class PolicySpec:
    """The ``policy`` section: how theta encodes the commanded trajectory
    (`psl_controller.policy`)."""

    n_basis: Annotated[int, Field(ge=1)]   # Gaussians per joint of the DMP (and feed-forward)
    kind: str = 'dmp'               # dmp | gmr (psl_controller.policy.KINDS)
    k_s: float = 400.0              # DMP spring constant of eq. 2.23 (k_d = 2 sqrt(k_s))
    canonical: str = 'linear'       # canonical system of the phase: linear | exponential
    feedforward: StrictBool = False  # theta = [theta_K, theta_D]: feed-forward torque
    n_components: int = 6           # gmr: Gaussians of the mixture
    fit_seed: int = 0               # gmr: seed of the EM fit to the demonstration
    learn_goal: StrictBool = False  # theta_K = [weights, goal]: the DMP goal is learned too
    space: Space = 'joint'          # joint | end_effector: the DMP's output (SPACES)
    orientation: StrictBool = False  # end_effector: a second DMP moves the hand's orientation


@with_config(SECTION)
@dataclasses.dataclass(frozen=True)
class RewardSpec:
    """The ``reward`` section: weights of the named components (`psl_optimizer.reward`), the
    success threshold and what the geometric components measure."""

    weights: dict[str, Finite]      # component name -> weight; missing components count zero;
                                    # a name registered as a reward component (a plugin's too:
                                    # psl_task.reward_components)
    success_threshold: float        # fulfilled when reward >= this
    clearance_margin: NonNegative = 0.0   # m; closer than this to an obstacle costs
    obstacle_geoms: tuple[str, ...] = ()  # geoms the arm must keep clear of
    arm_geoms: tuple[str, ...] = ()       # the arm's geoms measured against them
    # what the smoothness component differentiates twice: the measured joint angles, or the
    # commanded reference (a noisy robot: 1 mrad of noise at 2 ms adds about 6 sigma^2/dt^4 =
    # 4e5 rad^2/s^4 to the measured one, more than any motion, docs/benchmarks.md)
    smoothness_of: Literal['measured', 'reference'] = 'measured'
    # bodies of the world the arm does not drive (a ball, a puck) whose poses the reward's
    # components read (RolloutData.world): in simulation MuJoCo's, on a robot the poses
    # published on world/<body>/pose (geometry_msgs/PoseStamped; remap it to a motion capture)
    observe: tuple[str, ...] = ()


@with_config(SECTION)
@dataclasses.dataclass(frozen=True)
class SafetySpec:
    """The ``safety`` section: what a candidate's commanded trajectory must keep before it is
    executed (`psl_task.safety_check`), in either rollout mode. By default the reference must be
    finite and inside the joint ranges; every other limit is off until the task sets it."""

    joint_margin: NonNegative = 0.0           # rad (m) kept inside each limited joint's range
    max_velocity: NonNegative = float('inf')  # rad/s (m/s), |qd_ref| of every driven joint
    max_acceleration: NonNegative = float('inf')  # rad/s^2, |qdd_ref|
    torque_share: NonNegative = float('inf')  # inverse-dynamics torque along the reference, as
                                              # a share of each joint's torque limit
    collisions: StrictBool = False      # no penetration of reward.obstacle_geoms in a
                                        # kinematic replay of the reference
    self_collision: StrictBool = False  # no contact between the robot's own geoms in it
    replay_period: Positive = 0.01      # s between the replayed states of the collision check
    penalty: Finite = -100.0            # reward of a refused candidate, minus its violation
    max_tracking_error: NonNegative = float('inf')  # rad (m), |q - q_ref| of any driven joint
                                        # while the controller runs a trajectory: beyond it
                                        # the controller aborts the episode (graph mode)


@with_config(SECTION)
@dataclasses.dataclass(frozen=True)
class HomingSpec:
    """The ``homing`` section: how an episode begins. ``teleport`` (simulation only) puts the
    arm at the start posture at rest; ``drive`` moves it there through the controller first,
    along a quintic within the velocity and acceleration limits, and waits until it has
    settled (`psl_controller.homing`)."""

    reset: Reset = 'teleport'           # teleport | drive (RESETS); psl up --reset overrides
    max_velocity: Positive = 1.0        # rad/s (m/s) of any joint along the homing path
    max_acceleration: Positive = 4.0    # rad/s^2
    min_duration: Positive = 0.2        # s, the shortest homing motion
    settle_time: Positive = 0.3         # s held at the start posture after the motion
    tolerance: Positive = 0.01          # rad from the start posture (and rad/s of velocity)
                                        # within which the arm counts as there


# -- the sections of the file only ----------------------------------------------------------
class _Section(BaseModel):
    model_config = SECTION


class EndEffector(_Section):
    """``robot.end_effector``: a site of the model, or a body and an offset (psl adds a site
    there)."""

    site: str | None = None
    body: str | None = None
    offset: Vector3 | None = None

    @model_validator(mode='after')
    def _one_way(self) -> 'EndEffector':
        if (self.site is None) == (self.body is None) or (self.site and self.offset is not None):
            raise ValueError('is {site: NAME} or {body: NAME, offset: [x, y, z]}')
        return self


class RobotSection(_Section):
    """``robot``: the model, the end effector, the driven joints and what psl adds."""

    model: str | None = None
    end_effector: EndEffector | None = None
    package_paths: dict[str, str] = {}     # package://NAME/... -> folder (relative to the YAML)
    torque_limits: Vector | None = None    # (n,) N m for motors psl adds (else the model's)
    gravity_compensation: StrictBool = False
    joints: list[str] = []                 # the driven joints in command order
    exclude_contacts: list[tuple[str, str]] = []   # body pairs MuJoCo never collides
    # the robot's parts in contact at the start or goal posture (an overlap of coarse
    # collision meshes): exclude them (the default, psl check names them) or keep them
    contacts_at_rest: Literal['exclude', 'keep'] = 'exclude'


class Demonstration(_Section):
    """``demonstration``: the waypoints the default policy is fitted to."""

    times: Vector
    positions: Matrix


class TaskParameterEntry(_Section):
    """One entry of ``task_parameters``; its ``binds`` by kind (`psl_task.bindings`)."""

    name: str
    low: float
    high: float
    default: float | None = None           # default: the middle of the range
    unit: str = ''
    binds: dict[str, Any]


class TaskFile(_Section):
    """The top level of a task YAML."""

    name: str | None = None                # default: the file's stem
    description: str = ''
    model: str | None = None               # or robot.model
    end_effector_site: str | None = None   # or robot.end_effector
    robot: RobotSection = RobotSection()
    control_rate: Positive                 # Hz
    duration: Positive                     # s, length of the motion
    settle_time: NonNegative = 0.0         # s, the episode goes on after the motion
    start_posture: Vector
    goal_posture: Vector
    task_parameters: list[TaskParameterEntry]
    controller: ControllerSpec
    policy: PolicySpec
    demonstration: Demonstration
    reward: RewardSpec
    target: TargetSpec | None = None
    safety: SafetySpec = SafetySpec()
    homing: HomingSpec = HomingSpec()
    scene: list[SceneObject] = []


_TASK_FILE = TypeAdapter(TaskFile)


def parse_task_file(data: Any) -> tuple[TaskFile, list[Binding]]:
    """The validated file and each task parameter's binding; ValueError with one line per
    problem, each naming the key (``policy.n_basis: ...``), an unknown key with the nearest
    valid one."""
    if not isinstance(data, dict):
        raise ValueError('a task file is a mapping of keys')
    try:
        task_file = _TASK_FILE.validate_python(data)
    except ValidationError as exc:
        raise ValueError('; '.join(_describe(error, TaskFile) for error in exc.errors())) \
            from None
    from psl_task import reward_components    # its names come from the packages' metadata
    reward_components.check_names(task_file.reward.weights)
    bindings = []
    for i, entry in enumerate(task_file.task_parameters):
        where = f'task_parameters[{i}] ({entry.name}).binds'
        try:
            kind = binding_kind(entry.binds)
        except KeyError as exc:
            raise ValueError(f'{where}: kind must be one of {", ".join(BINDINGS)}, got '
                             f'{exc.args[0]!r}{_nearest(exc.args[0], BINDINGS)}') from None
        try:
            bindings.append(kind.model_validate(
                {k: v for k, v in entry.binds.items() if k != 'kind'}))
        except ValidationError as exc:
            raise ValueError('; '.join(_describe(error, kind, where + '.')
                                       for error in exc.errors())) from None
    return task_file, bindings


def _nearest(key: Any, known) -> str:
    close = difflib.get_close_matches(str(key), list(known), n=1, cutoff=0.6)
    return f' (did you mean {close[0]}?)' if close else ''


def _describe(error: dict, root: type, prefix: str = '') -> str:
    """One pydantic error as a line of psl's messages."""
    loc = tuple(part for part in error['loc'] if not str(part).startswith('function-'))
    where = prefix + _dotted(loc)
    kind = error['type']
    if kind in ('extra_forbidden', 'unexpected_keyword_argument'):
        known = _fields(root, loc[:-1])
        section = (prefix + _dotted(loc[:-1])).rstrip('.') or 'the top level'
        return (f'{section} has unknown key {loc[-1]!r}{_nearest(loc[-1], known)}; known: '
                f'{", ".join(known)}')
    if kind in ('missing', 'missing_keyword_argument'):
        section = (prefix + _dotted(loc[:-1])).rstrip('.')
        return f'missing key {loc[-1]!r}' + (f' in {section}' if section else '')
    if kind == 'bool_type':
        return f'{where} must be true or false, got {error["input"]!r}'
    if kind in ('greater_than', 'greater_than_equal', 'less_than', 'less_than_equal'):
        sign = {'greater_than': '>', 'greater_than_equal': '>=', 'less_than': '<',
                'less_than_equal': '<='}[kind]
        limit = next(iter(error['ctx'].values()))
        return f'{where} must be {sign} {limit:g}, got {error["input"]!r}'
    if kind == 'finite_number':
        return f'{where} must be finite'
    if kind == 'literal_error':
        return f'{where} must be one of {error["ctx"]["expected"]}, got {error["input"]!r}'
    if kind in ('dict_type', 'model_type', 'model_attributes_type', 'dataclass_type',
                'dataclass_args_type'):
        return f'{where} must be a mapping of keys, got {error["input"]!r}'
    message = error['msg'].removeprefix('Value error, ')
    if not where:
        return message
    joint = ' ' if message.startswith(('must ', 'is ')) else ': '
    return where + joint + message


def _dotted(loc: tuple) -> str:
    out = ''
    for part in loc:
        out += f'[{part}]' if isinstance(part, int) else (f'.{part}' if out else str(part))
    return out


def _fields(root: type, loc: tuple) -> list[str]:
    """The keys the section at `loc` under `root` knows."""
    kind: Any = root
    for part in loc:
        kind = _unwrap(kind)
        if isinstance(part, int):
            kind = typing.get_args(kind)[0] if typing.get_args(kind) else kind
            continue
        kind = typing.get_type_hints(kind, include_extras=True).get(part, kind)
    return _keys(_unwrap(kind))


def _unwrap(kind: Any) -> Any:
    """X for Annotated[X, ...] and X | None."""
    while True:
        if typing.get_origin(kind) is Annotated:
            kind = typing.get_args(kind)[0]
            continue
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        if typing.get_origin(kind) in (typing.Union, types.UnionType) and len(args) == 1:
            kind = args[0]
            continue
        return kind


def _keys(kind: Any) -> list[str]:
    if isinstance(kind, type) and issubclass(kind, BaseModel):
        return list(kind.model_fields)
    if dataclasses.is_dataclass(kind):
        return [f.name for f in dataclasses.fields(kind)]
    return []
