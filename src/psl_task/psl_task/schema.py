"""The task file's schema: every section typed, every default here and only here.

One pydantic model (or a dataclass pydantic validates) per section of a task YAML: the top
level (`TaskFile`), ``robot`` (`RobotSection`, its ``end_effector``), ``controller``
(`ControllerSpec`), ``policy`` (`PolicySpec`), ``demonstration`` (`Demonstration`),
``task_parameters`` (`TaskParameterEntry`, its ``binds`` by kind: `psl_task.bindings`),
``target`` (`TargetSpec`), ``scene`` (`SceneObject`), ``homing`` (`HomingSpec`), ``safety``
(`SafetySpec`) and ``reward`` (`RewardSpec`). A key no section knows is refused anywhere,
with the section and the nearest valid key ("did you mean settle_time?"); a value of the
wrong type or out of its range is refused naming the key (`parse_task_file`). Each key's
description is the docstring under it (pydantic's ``use_attribute_docstrings``), so the
reference docs/task_reference.md is generated from here (`psl_task.schema_reference`).

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
                      ValidationError, WithJsonSchema, model_validator, with_config)

from psl_task.bindings import Binding, BINDINGS, binding_kind

SCENE_TYPES = {'box': 3, 'sphere': 1, 'capsule': 2, 'cylinder': 2}   # type -> size entries
Space = Literal['joint', 'end_effector']       # where the DMP runs (policy.space)
Reset = Literal['teleport', 'drive']           # how an episode begins (homing.reset)
SPACES = typing.get_args(Space)
RESETS = typing.get_args(Reset)
SECTION = ConfigDict(extra='forbid', arbitrary_types_allowed=True,
                     use_attribute_docstrings=True)   # a key's docstring: its description


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


# what each array is in the YAML, for the JSON schema (validation is the function's alone)
_NUMBERS = {'type': 'array', 'items': {'type': 'number', 'finite': True}}
Vector = Annotated[np.ndarray, BeforeValidator(_vector), WithJsonSchema(_NUMBERS)]
Vector3 = Annotated[np.ndarray, BeforeValidator(_vector3),
                    WithJsonSchema({**_NUMBERS, 'minItems': 3, 'maxItems': 3})]
Matrix = Annotated[np.ndarray, BeforeValidator(_matrix),
                   WithJsonSchema({'type': 'array', 'items': _NUMBERS})]
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

    position: Vector3
    """The target point (3,) [m], world frame; the coordinates no task parameter binds."""
    orientation: Vector3 = dataclasses.field(default_factory=_zeros3)
    """The target frame's extrinsic x-y-z angles (3,) [rad]; the angles no task parameter
    binds."""
    body: str = ''
    """A mocap body psl moves to each instance's target, for display ('': none)."""


@with_config(SECTION)
@dataclasses.dataclass(frozen=True, eq=False)
class SceneObject:
    """One entry of the ``scene`` section: a body psl adds to the model (a mocap body with
    one geom of the same name), e.g. an obstacle, a table or a target marker."""

    name: str
    """The body's and its geom's name (``mocap_position`` bindings and
    ``reward.obstacle_geoms`` name it)."""
    size: Vector
    """MuJoCo's geom size for the type [m]: 3 half-sizes (box), a radius (sphere), a radius
    and a half-length (capsule, cylinder); each > 0."""
    position: Vector3
    """The body's position (3,) [m], world frame."""
    type: Literal['box', 'sphere', 'capsule', 'cylinder'] = 'box'
    """The geom's shape (SCENE_TYPES)."""
    orientation: Vector3 = dataclasses.field(default_factory=_zeros3)
    """The body's extrinsic x-y-z angles (3,) [rad]."""
    contacts: StrictBool = False
    """Collide with the robot; by default the reward scores the distance geometrically."""
    rgba: tuple[float, float, float, float] = (0.8, 0.2, 0.2, 0.6)
    """The geom's colour: red, green, blue, alpha in [0, 1]."""

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

    kp: Vector
    """Proportional gains (n_joints,) [N m / rad], one per driven joint."""
    kd: Vector
    """Derivative gains (n_joints,) [N m s / rad], one per driven joint."""


@with_config(SECTION)
@dataclasses.dataclass(frozen=True)
class PolicySpec:
    """The ``policy`` section: how theta encodes the commanded trajectory
    (`psl_controller.policy`)."""

    n_basis: Annotated[int, Field(ge=1)]
    """Gaussians per joint of the DMP (and of the feed-forward torque)."""
    kind: str = 'dmp'
    """The trajectory's encoding: dmp | gmr (psl_controller.policy.KINDS)."""
    k_s: float = 400.0
    """The DMP's spring constant of eq. 2.23 (k_d = 2 sqrt(k_s))."""
    canonical: str = 'linear'
    """The canonical system of the phase: linear | exponential."""
    feedforward: StrictBool = False
    """theta = [theta_K, theta_D]: a feed-forward torque is learned too."""
    n_components: int = 6
    """gmr: Gaussians of the mixture."""
    fit_seed: int = 0
    """gmr: the seed of the EM fit to the demonstration."""
    learn_goal: StrictBool = False
    """theta_K = [weights, goal]: the DMP's goal is learned too (default: the demonstration's
    end)."""
    space: Space = 'joint'
    """What the DMP moves: the joints, or the end effector's position through inverse
    kinematics (SPACES)."""
    orientation: StrictBool = False
    """end_effector space: a second DMP moves the hand's orientation."""


@with_config(SECTION)
@dataclasses.dataclass(frozen=True)
class RewardSpec:
    """The ``reward`` section: weights of the named components (`psl_optimizer.reward`), the
    success threshold and what the geometric components measure."""

    weights: dict[str, Finite]
    """Component name -> weight; reward = -sum(weight * component); a missing component
    counts zero; a name must be registered (psl_task.reward_components, a plugin's too)."""
    success_threshold: float
    """A rollout fulfils its instance when its reward >= this."""
    clearance_margin: NonNegative = 0.0
    """[m] closer than this to an obstacle costs (the clearance component)."""
    obstacle_geoms: tuple[str, ...] = ()
    """The geoms the arm must keep clear of."""
    arm_geoms: tuple[str, ...] = ()
    """The arm's geoms measured against them (default: those of the bodies the driven joints
    move, visual-only geoms left out)."""
    # the measured angles of a noisy robot: 1 mrad of noise at 2 ms adds about
    # 6 sigma^2/dt^4 = 4e5 rad^2/s^4 to the smoothness, more than any motion (docs/benchmarks.md)
    smoothness_of: Literal['measured', 'reference'] = 'measured'
    """What the smoothness component differentiates twice: the measured joint angles or the
    commanded reference."""
    observe: tuple[str, ...] = ()
    """Bodies the arm does not drive (a ball, a puck) whose poses the components read: MuJoCo's
    in simulation, world/<body>/pose (geometry_msgs/PoseStamped, remap it to a motion capture)
    on a robot."""
    component_timeout: Positive = 5.0
    """[s] each component's call on a population must return within this: a call that does
    not fails the population's rollouts with the reason, and until it returns, the
    component's further calls fail at once (psl_task.reward_components.BoundedCalls)."""


@with_config(SECTION)
@dataclasses.dataclass(frozen=True)
class SafetySpec:
    """The ``safety`` section: what a candidate's commanded trajectory must keep before it is
    executed (`psl_task.safety_check`), in either rollout mode. Always, what every controller
    psl serves holds a goal to: the reference finite, inside the joint ranges and within the
    arm's velocity limits (a URDF's, else 100 rad/s), its feed-forward within the torque
    limits, and so between its points as a controller interpolates them; every other limit is
    off until the task sets it."""

    joint_margin: NonNegative = 0.0
    """[rad (m)] kept inside each limited joint's range."""
    max_velocity: NonNegative = float('inf')
    """[rad/s (m/s)] bound on |qd_ref| of every driven joint, where lower than the arm's own
    (a URDF's ``<limit velocity>``, else 100 rad/s)."""
    max_acceleration: NonNegative = float('inf')
    """[rad/s^2] bound on |qdd_ref|."""
    torque_share: NonNegative = float('inf')
    """Bound on the inverse-dynamics torque along the reference, as a share of each joint's
    torque limit."""
    collisions: StrictBool = False
    """No penetration of reward.obstacle_geoms in a kinematic replay of the reference."""
    self_collision: StrictBool = False
    """No contact between the robot's own geoms in that replay."""
    replay_period: Positive = 0.01
    """[s] between the replayed states of the collision check."""
    penalty: Finite = -100.0
    """The reward of a refused candidate, minus its violation."""
    max_tracking_error: NonNegative = float('inf')
    """[rad (m)] bound on |q - q_ref| of any driven joint while the controller runs a
    trajectory: beyond it the controller aborts the episode (graph mode)."""


@with_config(SECTION)
@dataclasses.dataclass(frozen=True)
class HomingSpec:
    """The ``homing`` section: how an episode begins. ``teleport`` (simulation only) puts the
    arm at the start posture at rest; ``drive`` moves it there through the controller first,
    along a quintic within the velocity and acceleration limits, and waits until it has
    settled (`psl_controller.homing`)."""

    reset: Reset = 'teleport'
    """teleport (simulation only) | drive (RESETS); psl up --reset overrides it."""
    max_velocity: Positive = 1.0
    """[rad/s (m/s)] of any joint along the homing path."""
    max_acceleration: Positive = 4.0
    """[rad/s^2] of any joint along the homing path."""
    min_duration: Positive = 0.2
    """[s] the shortest homing motion."""
    settle_time: Positive = 0.3
    """[s] held at the start posture after the motion."""
    tolerance: Positive = 0.01
    """[rad] from the start posture (and rad/s of velocity) within which the arm counts as
    there."""


# -- the sections of the file only ----------------------------------------------------------
class _Section(BaseModel):
    model_config = SECTION


class EndEffector(_Section):
    """``robot.end_effector``: a site of the model, or a body and an offset (psl adds a site
    there)."""

    site: str | None = None
    """A site of the model (or give body)."""
    body: str | None = None
    """A body of the model; psl adds the site psl_end_effector to it."""
    offset: Vector3 | None = None
    """With body: the site's position (3,) [m] in the body's frame (default: its origin)."""

    @model_validator(mode='after')
    def _one_way(self) -> 'EndEffector':
        if (self.site is None) == (self.body is None) or (self.site and self.offset is not None):
            raise ValueError('is {site: NAME} or {body: NAME, offset: [x, y, z]}')
        return self


class RobotSection(_Section):
    """``robot``: the model, the end effector, the driven joints and what psl adds."""

    model: str | None = None
    """An MJCF or URDF file: a path (absolute, or relative to the YAML) or package://NAME/...
    (or the top-level model)."""
    end_effector: EndEffector | None = None
    """{site: NAME} or {body: NAME, offset: [x, y, z]} (or the top-level end_effector_site)."""
    package_paths: dict[str, str] = {}
    """package://NAME/... -> folder (relative to the YAML), searched before the
    environment's."""
    torque_limits: Vector | None = None
    """(n_joints,) [N m] for the motors psl adds (default: the joints' actuatorfrcrange)."""
    gravity_compensation: StrictBool = False
    """Set MuJoCo's gravcomp on every body the driven joints move."""
    joints: list[str] = []
    """The driven joints in command order (default: the joints of the model's actuators)."""
    locked_joints: dict[str, Finite] = {}
    """Joints held fixed, {joint: value [rad (m)]}: removed from the model, the body placed
    where the joint at that value puts it (a humanoid's arm from its full-body description:
    lock every joint but the arm's). A free or ball joint locks at 0: the model's reference
    pose. Never driven (robot.joints); their actuators are removed."""
    exclude_contacts: list[tuple[str, str]] = []
    """Body pairs MuJoCo never collides."""
    contacts_at_rest: Literal['exclude', 'keep'] = 'exclude'
    """The robot's parts in contact at the start or goal posture (overlapping collision
    meshes): exclude them (psl check names them) or keep them."""


class Demonstration(_Section):
    """``demonstration``: the waypoints the default policy is fitted to."""

    times: Vector
    """[s] of the waypoints, rising from 0 to duration."""
    positions: Matrix
    """[rad (m)] one row of joint positions per time, from start_posture to goal_posture."""


class TaskParameterEntry(_Section):
    """One entry of ``task_parameters``; its ``binds`` by kind (`psl_task.bindings`)."""

    name: str
    """The task parameter's name."""
    low: float
    """The lower end of its range (< high)."""
    high: float
    """The upper end of its range."""
    default: float | None = None
    """Its default value (default: the middle of the range)."""
    unit: str = ''
    """Its unit, for people (m, kg, s, rad)."""
    binds: dict[str, Any]
    """What its value moves: {kind: KIND, ...the kind's keys} (the binding kinds below)."""


class TaskFile(_Section):
    """The top level of a task YAML."""

    name: str | None = None
    """The task's name (default: the file's stem)."""
    description: str = ''
    """One line about the task, for people."""
    model: str | None = None
    """The model file; or robot.model (give it once)."""
    end_effector_site: str | None = None
    """The end effector's site; or robot.end_effector (give it once)."""
    robot: RobotSection = RobotSection()
    """The robot: model, end effector, driven joints and what psl adds."""
    control_rate: Positive
    """[Hz] of the controller; a whole divisor of the physics rate 1 / timestep."""
    duration: Positive
    """[s] the length of the motion (the demonstration's)."""
    settle_time: NonNegative = 0.0
    """[s] the episode goes on after the motion."""
    start_posture: Vector
    """(n_joints,) [rad (m)] where the episode starts, in command order."""
    goal_posture: Vector
    """(n_joints,) [rad (m)] where the movement ends: the demonstration's last waypoint."""
    task_parameters: list[TaskParameterEntry]
    """tau: the task parameters, in this order."""
    controller: ControllerSpec
    """The PD gains."""
    policy: PolicySpec
    """How theta encodes the commanded trajectory."""
    demonstration: Demonstration
    """The waypoints the default theta is fitted to."""
    reward: RewardSpec
    """The reward's weights, success threshold and geometry."""
    target: TargetSpec | None = None
    """The default target (needed by target_position / target_orientation bindings)."""
    safety: SafetySpec = SafetySpec()
    """What a candidate must keep before it runs."""
    homing: HomingSpec = HomingSpec()
    """How an episode begins."""
    scene: list[SceneObject] = []
    """Bodies psl adds to the model (obstacles, tables, markers)."""


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
