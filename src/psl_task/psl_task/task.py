"""Task definitions: a YAML file next to its MJCF model names everything a task varies.

A task YAML holds the model file, the task parameters tau (names, ranges, and how each one
is applied to the model: `psl_task.bindings`), the start and goal postures, the controller
gains, the movement representation, the demonstration the default policy is fitted to, the
reward weights and the success threshold. Every section is typed in `psl_task.schema`: every
optional key has its default there and only there, and a key no section knows is refused with
the nearest valid key (a typo never passes silently). Tasks are found by name in the embedded
``tasks/`` folder and in the folders listed in ``PSL_TASK_PATH`` (colon-separated), or given
as a path to a YAML file. The ``model`` key is a path to the MJCF file: absolute (``~``
expanded), or relative to the folder of the YAML file (not to the working directory).

Imports no ROS: usable from the nodes, the batch rollouts, tests and notebooks.
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from psl_task.bindings import Binding
from psl_task.package_paths import PREFIX as PACKAGE_PREFIX, PackageNotFound, resolve
from psl_task.schema import (ControllerSpec, HomingSpec, PolicySpec, RewardSpec, SafetySpec,
                             SceneObject, TargetSpec, TaskFile, parse_task_file)

EMBEDDED_TASKS = Path(__file__).resolve().parent / 'tasks'
END_EFFECTOR_SITE = 'psl_end_effector'  # the site psl adds for end_effector: {body, offset}


class TaskError(ValueError):
    """A task that cannot be found or loaded, or task parameters it does not accept."""


@dataclasses.dataclass(frozen=True)
class TaskParameter:
    """One entry of tau: its range and where it goes (its binding)."""

    name: str
    low: float
    high: float
    default: float
    binds: Binding
    unit: str = ''


@dataclasses.dataclass(frozen=True, eq=False)   # hashed by identity: load_task caches
class TaskDefinition:
    """Everything a task varies and how it is scored (see the module docstring)."""

    name: str
    path: Path                      # the YAML file
    model_path: Path                # the MJCF or URDF file
    description: str
    end_effector_site: str
    control_rate: float             # Hz
    duration: float                 # s, length of the motion
    settle_time: float              # s, the episode goes on after the motion
    start_posture: np.ndarray       # (n_joints,)
    goal_posture: np.ndarray        # (n_joints,)
    parameters: tuple[TaskParameter, ...]
    controller: ControllerSpec
    policy: PolicySpec
    demo_times: np.ndarray          # (n_waypoints,)
    demo_positions: np.ndarray      # (n_waypoints, n_joints)
    reward: RewardSpec
    target: TargetSpec | None = None
    safety: SafetySpec = SafetySpec()
    homing: HomingSpec = HomingSpec()
    scene: tuple[SceneObject, ...] = ()
    # end effector given as a body and an offset (psl adds the site END_EFFECTOR_SITE there);
    # empty when the model has the site already
    end_effector_body: str = ''
    end_effector_offset: np.ndarray | None = None
    # a URDF's package://NAME/... paths: NAME -> folder (then ROS_PACKAGE_PATH, AMENT_PREFIX_PATH)
    package_paths: dict[str, Path] = dataclasses.field(default_factory=dict)
    torque_limits: np.ndarray | None = None   # (n,) N m for motors psl adds (else the model's)
    gravity_compensation: bool = False  # MuJoCo's gravcomp on the bodies the joints move
    # robot.joints: the driven joints in command order (empty: every joint with an actuator,
    # or every hinge/slide joint of a model without actuators); the rest stay passive
    joints: tuple[str, ...] = ()
    # robot.locked_joints: joint -> value [rad (m)], compiled as fixed
    # (psl_task.model_spec.lock_joints)
    locked_joints: dict[str, float] = dataclasses.field(default_factory=dict)
    # robot.exclude_contacts: body pairs MuJoCo never collides; robot.contacts_at_rest:
    # exclude (default) or keep the robot's parts in contact at the start or goal posture
    # (psl_task.model_spec.contacts_at_rest)
    exclude_contacts: tuple[tuple[str, str], ...] = ()
    contacts_at_rest: str = 'exclude'

    @property
    def tau_names(self) -> list[str]:
        return [p.name for p in self.parameters]

    @property
    def tau_low(self) -> np.ndarray:
        return np.array([p.low for p in self.parameters])

    @property
    def tau_high(self) -> np.ndarray:
        return np.array([p.high for p in self.parameters])

    @property
    def tau_default(self) -> np.ndarray:
        return np.array([p.default for p in self.parameters])

    @property
    def n_joints(self) -> int:
        return len(self.start_posture)

    @property
    def control_period(self) -> float:
        return 1.0 / self.control_rate

    @property
    def control_period_ns(self) -> int:
        return int(round(1e9 / self.control_rate))

    @property
    def num_steps(self) -> int:
        """Control periods in one episode (motion plus settling)."""
        return int(round((self.duration + self.settle_time) * self.control_rate))

    def _bound(self, tau: np.ndarray | None):
        """(value, binding) of each task parameter in tau (default instance for None), the
        binding's offset added."""
        tau = self.tau_default if tau is None else tau
        return [(float(v) + p.binds.offset, p.binds) for v, p in zip(tau, self.parameters)]

    def duration_of(self, tau: np.ndarray | None = None) -> float:
        """The movement's duration [s] on the task instance tau: its ``duration`` task
        parameter, else the task's ``duration``."""
        bound = [value for value, binds in self._bound(tau) if binds.sets_duration]
        return bound[0] if bound else self.duration

    def num_steps_of(self, tau: np.ndarray | None = None) -> int:
        """Control periods in the episode of instance tau (its motion plus settling)."""
        return int(round((self.duration_of(tau) + self.settle_time) * self.control_rate))

    def target_of(self, tau: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The instance's target: position (3,) [m] and orientation as a rotation matrix
        (3, 3), the ``target`` section with the ``target_position`` and
        ``target_orientation`` task parameters applied. TaskError for a task without
        target."""
        if self.target is None:
            raise TaskError(f'task {self.name!r} has no target section')
        position, angles = self.target.position.copy(), self.target.orientation.copy()
        for value, binds in self._bound(tau):
            binds.move_target(value, position, angles)
        return position, rotation_xyz(angles)

    def validate_tau(self, tau: Any) -> np.ndarray:
        """Return tau as a float array, or raise TaskError saying what is wrong with it."""
        tau = np.asarray(tau, dtype=float)
        if tau.ndim != 1 or tau.size != len(self.parameters):
            raise TaskError(
                f'task {self.name!r} takes {len(self.parameters)} task parameters '
                f'({", ".join(self.tau_names)}), got {tau.size}')
        if not np.all(np.isfinite(tau)):
            raise TaskError(f'task parameters must be finite, got {tau.tolist()}')
        for value, p in zip(tau, self.parameters):
            if not p.low <= value <= p.high:
                raise TaskError(
                    f'{p.name} = {value:g} is outside its range [{p.low:g}, {p.high:g}] '
                    f'in task {self.name!r}')
        return tau

    def sample_tau(self, rng: np.random.Generator) -> np.ndarray:
        """A task instance drawn uniformly from the parameter ranges."""
        return rng.uniform(self.tau_low, self.tau_high)


def rotation_xyz(angles: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of extrinsic rotations about x, then y, then z by the angles
    (3,) [rad]: R = Rz Ry Rx."""
    cx, cy, cz = np.cos(angles)
    sx, sy, sz = np.sin(angles)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def task_search_path() -> list[Path]:
    extra = [Path(p) for p in os.environ.get('PSL_TASK_PATH', '').split(':') if p]
    return extra + [EMBEDDED_TASKS]


def list_tasks() -> list[str]:
    """Names of all tasks on the search path."""
    names = set()
    for folder in task_search_path():
        names.update(p.stem for p in folder.glob('*.yaml'))
    return sorted(names)


MAX_TASK_REFERENCE = 1024       # characters of a task name or YAML path
MAX_TASK_FILE = 2**20           # bytes of a task YAML


def find_task_file(name_or_path: str) -> Path:
    """The YAML of a task name (on the search path) or path. Raises TaskError for an unknown
    task, a reference longer than MAX_TASK_REFERENCE and a file that cannot be read."""
    if len(name_or_path) > MAX_TASK_REFERENCE:
        raise TaskError(f'a task name or path of {len(name_or_path)} characters: at most '
                        f'{MAX_TASK_REFERENCE}')
    if '\0' in name_or_path:
        raise TaskError('a task name or path cannot hold a NUL character')
    try:
        return _find_task_file(name_or_path)
    except OSError as exc:          # too long a file name, no permission, ...
        raise TaskError(f'task {name_or_path[:100]!r}: {exc.strerror or exc}') from None


def _find_task_file(name_or_path: str) -> Path:
    candidate = Path(name_or_path)
    if candidate.suffix in ('.yaml', '.yml'):
        if candidate.is_file():
            return candidate.resolve()
        raise TaskError(f'task file {name_or_path} does not exist')
    for folder in task_search_path():
        path = folder / f'{name_or_path}.yaml'
        if path.is_file():
            return path.resolve()
    raise TaskError(f'unknown task {name_or_path!r}; known tasks: {", ".join(list_tasks())}')


def task_id(task: TaskDefinition) -> str:
    """The string another process passes to `load_task` to get this task: its name when the
    name finds this very file on the search path, otherwise the YAML's absolute path (a task
    loaded from a file elsewhere, or whose name differs from its file name)."""
    try:
        if find_task_file(task.name) == task.path:
            return task.name
    except TaskError:
        pass
    return str(task.path)


_CACHE: dict[tuple[Path, float], TaskDefinition] = {}


def load_task(name_or_path: str) -> TaskDefinition:
    """Load a task by name (search path) or by YAML path. Raises TaskError."""
    path = find_task_file(name_or_path)
    try:
        stat = path.stat()
    except OSError as exc:
        raise TaskError(f'{path}: {exc.strerror or exc}') from None
    if stat.st_size > MAX_TASK_FILE:
        raise TaskError(f'{path}: {stat.st_size} bytes, more than a task file may hold '
                        f'({MAX_TASK_FILE})')
    key = (path, stat.st_mtime)
    if key not in _CACHE:
        _CACHE[key] = _parse(path)
    return _CACHE[key]


def _parse(path: Path) -> TaskDefinition:
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise TaskError(f'{path}: not valid YAML: {exc}') from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise TaskError(f'{path}: cannot be read: {exc}') from None
    return task_from_data(path, data)


def task_from_data(path: Path, data: Any) -> TaskDefinition:
    """The task of a YAML file's contents `data` as if read from `path` (relative model paths
    relative to its folder; the file need not exist): what `load_task` builds, for a task
    written by a program (``psl init``'s drafts). Raises TaskError."""
    try:
        return _build(path, data)
    except KeyError as exc:
        raise TaskError(f'{path}: missing key {exc}') from exc
    except (TypeError, ValueError) as exc:
        if isinstance(exc, TaskError):
            raise
        raise TaskError(f'{path}: {exc}') from exc


def _build(path: Path, data: Any) -> TaskDefinition:
    """The task of a file's contents: the schema first (`psl_task.schema`), then what the
    sections hold together."""
    try:
        spec, bindings = parse_task_file(data)
    except ValueError as exc:
        raise TaskError(f'{path}: {exc}') from None
    robot = spec.robot
    if (robot.model is None) == (spec.model is None):
        raise TaskError(f'{path}: give the model once, as robot.model (or the top-level model)')
    model_path = _model_path(path, robot.model or spec.model, robot.package_paths)
    start = spec.start_posture
    n = start.size
    params = []
    for entry, binds in zip(spec.task_parameters, bindings):
        if not entry.low < entry.high:
            raise TaskError(f'{path}: task parameter {entry.name!r} needs low < high')
        try:
            binds.check_range(entry.name, entry.low + binds.offset, entry.high + binds.offset)
        except ValueError as exc:
            raise TaskError(f'{path}: {exc}') from None
        params.append(TaskParameter(
            name=entry.name, low=entry.low, high=entry.high,
            default=(0.5 * (entry.low + entry.high) if entry.default is None
                     else entry.default),
            binds=binds, unit=entry.unit))
    if sum(p.binds.sets_duration for p in params) > 1:
        raise TaskError(f'{path}: at most one task parameter binds the duration')
    if spec.target is None and any(p.binds.needs_target for p in params):
        kinds = sorted({p.binds.kind for p in params if p.binds.needs_target})
        raise TaskError(f'{path}: {" / ".join(kinds)} task parameters need a target section '
                        '(target: {position: [x, y, z]})')
    demo_positions = spec.demonstration.positions
    if demo_positions.ndim != 2 or demo_positions.shape[1] != n:
        found = (f'rows of {demo_positions.shape[1]}' if demo_positions.ndim == 2
                 else f'shape {demo_positions.shape}')
        raise TaskError(f'{path}: demonstration positions must be rows of {n} joint angles, '
                        f'one per entry of start_posture (one per driven joint); found {found}')
    demo_times = spec.demonstration.times
    if demo_times.size != len(demo_positions):
        raise TaskError(f'{path}: demonstration times must be {len(demo_positions)} finite '
                        f'numbers (one per row of positions), got {demo_times.tolist()}')
    for key, vector in (('goal_posture', spec.goal_posture), ('controller.kp', spec.controller.kp),
                        ('controller.kd', spec.controller.kd),
                        ('robot.torque_limits', robot.torque_limits)):
        if vector is not None and vector.size != n:
            raise TaskError(f'{path}: {key} must be {n} finite numbers (one per entry of '
                            f'start_posture), got {vector.tolist()}')
    goal = spec.goal_posture
    for what, posture, row in (('start_posture', start, 0), ('goal_posture', goal, -1)):
        if not np.allclose(demo_positions[row], posture, rtol=0.0, atol=1e-6):
            raise TaskError(f'{path}: the demonstration must {"start" if row == 0 else "end"} '
                            f'at {what} {posture.tolist()} (the DMP runs from its first to '
                            f'its last waypoint), got {demo_positions[row].tolist()}')
    if robot.joints and len(robot.joints) != n:
        raise TaskError(f'{path}: robot.joints names {len(robot.joints)} driven joints, '
                        f'start_posture has {n} entries: give one posture entry per driven '
                        'joint, in the order of robot.joints')
    if len(set(robot.joints)) != len(robot.joints):
        raise TaskError(f'{path}: robot.joints names a joint twice: {robot.joints}')
    both = [name for name in robot.joints if name in robot.locked_joints]
    if both:
        raise TaskError(f'{path}: robot.locked_joints locks {both[0]!r}, which robot.joints '
                        'drives: a joint is driven or locked, not both')
    duration = spec.duration
    if np.any(np.diff(demo_times) <= 0.0) or demo_times[0] != 0.0 or \
            abs(demo_times[-1] - duration) > 1e-9 * max(1.0, duration):
        raise TaskError(f'{path}: demonstration times must rise from 0 to duration '
                        f'({duration:g} s): the DMP starts at the first waypoint and ends at '
                        f'the last; got {demo_times.tolist()}')
    names = [o.name for o in spec.scene]
    if len(set(names)) != len(names):
        twice = sorted({name for name in names if names.count(name) > 1})
        raise TaskError(f'{path}: two scene objects are called {twice[0]!r}')
    return TaskDefinition(
        name=spec.name if spec.name is not None else path.stem,
        path=path,
        model_path=model_path,
        description=spec.description,
        **_end_effector(spec, path),
        control_rate=spec.control_rate,
        duration=duration,
        settle_time=spec.settle_time,
        start_posture=start,
        goal_posture=goal,
        parameters=tuple(params),
        controller=spec.controller,
        policy=spec.policy,
        demo_times=demo_times,
        demo_positions=demo_positions,
        reward=spec.reward,
        target=spec.target,
        safety=spec.safety,
        homing=spec.homing,
        scene=tuple(spec.scene),
        package_paths=_package_paths(robot.package_paths, path),
        torque_limits=robot.torque_limits,
        gravity_compensation=robot.gravity_compensation,
        joints=tuple(robot.joints),
        locked_joints={str(k): float(v) for k, v in robot.locked_joints.items()},
        exclude_contacts=tuple(robot.exclude_contacts),
        contacts_at_rest=robot.contacts_at_rest,
    )


def _model_path(path: Path, model: str, package_paths: dict[str, str]) -> Path:
    """The model file: absolute (or ~/...) as given; a relative path is relative to the YAML
    file's folder; package://NAME/... through psl_task.package_paths."""
    if model.startswith(PACKAGE_PREFIX):
        model_path = package_file(path, model, 'robot.model',
                                  _package_paths(package_paths, path)).resolve()
    else:
        model_path = (path.parent / Path(model).expanduser()).resolve()
    if not model_path.is_file():
        raise TaskError(f'{path}: model file {model_path} does not exist')
    return model_path


def package_file(task: 'TaskDefinition | Path', url: str, what: str,
                 package_paths: dict[str, Path] | None = None) -> Path:
    """The file a ``package://NAME/...`` url of a task names (`psl_task.package_paths`);
    TaskError naming what was searched and the fix when the package is nowhere."""
    path = task.path if isinstance(task, TaskDefinition) else task
    if isinstance(task, TaskDefinition):
        package_paths = task.package_paths
    try:
        return resolve(url, package_paths)
    except PackageNotFound as exc:
        raise TaskError(f'{path}: {what} {url}: package {exc.name!r} is nowhere: give '
                        f'robot.package_paths: {{{exc.name}: FOLDER}}, or install it '
                        f'(searched {", ".join(exc.searched)})') from None


def _package_paths(section: dict[str, str], path: Path) -> dict[str, Path]:
    """robot.package_paths: package name -> folder (relative to the YAML's folder)."""
    return {str(k): (path.parent / Path(str(v)).expanduser()).resolve()
            for k, v in section.items()}


def _end_effector(spec: TaskFile, path: Path) -> dict:
    """end_effector_site (and body, offset) from robot.end_effector ({site: NAME} or
    {body: NAME, offset: [x, y, z]}) or the top-level end_effector_site."""
    given = spec.robot.end_effector
    if (given is None) == (spec.end_effector_site is None):
        raise TaskError(f'{path}: give the end effector once, as robot.end_effector '
                        '({site: NAME} or {body: NAME, offset: [x, y, z]}) or end_effector_site')
    if given is None:
        return {'end_effector_site': spec.end_effector_site}
    if given.site is not None:
        return {'end_effector_site': given.site}
    return {'end_effector_site': END_EFFECTOR_SITE, 'end_effector_body': given.body,
            'end_effector_offset': (np.zeros(3) if given.offset is None else given.offset)}
