"""Task definitions: a YAML file next to its MJCF model names everything a task varies.

A task YAML holds the model file, the task parameters tau (names, ranges, and how each one
is applied to the model), the start and goal postures, the controller gains, the movement
representation, the demonstration the default policy is fitted to, the reward weights and
the success threshold. The ``controller``, ``policy`` and ``reward`` sections are typed
(`ControllerSpec`, `PolicySpec`, `RewardSpec`): every optional key has its default here and only
here, and a key a section does not know is refused (a typo never passes silently). Tasks are found by name in the embedded ``tasks/`` folder and in the
folders listed in ``PSL_TASK_PATH`` (colon-separated), or given as a path to a YAML file.
The ``model`` key is a path to the MJCF file: absolute (``~`` expanded), or relative to the
folder of the YAML file (not to the working directory).

Imports no ROS: usable from the nodes, the batch rollouts, tests and notebooks.
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from psl_task.package_paths import PREFIX as PACKAGE_PREFIX, PackageNotFound, resolve

EMBEDDED_TASKS = Path(__file__).resolve().parent / 'tasks'
BINDING_KINDS = ('mocap_position', 'body_mass', 'target_position', 'target_orientation',
                 'duration')
# bindings that change what the episode looks like (the target, the movement's duration)
# rather than the model: they bind no body
TASK_BINDINGS = ('target_position', 'target_orientation', 'duration')
SPACES = ('joint', 'end_effector')     # where the DMP runs (policy.space)
SCENE_TYPES = {'box': 3, 'sphere': 1, 'capsule': 2, 'cylinder': 2}   # type -> size entries
END_EFFECTOR_SITE = 'psl_end_effector'  # the site psl adds for end_effector: {body, offset}
RESETS = ('teleport', 'drive')          # how an episode begins (homing.reset)


class TaskError(ValueError):
    """A task that cannot be found or loaded, or task parameters it does not accept."""


@dataclasses.dataclass(frozen=True)
class TaskParameter:
    """One entry of tau: its range and where it goes in the model."""

    name: str
    low: float
    high: float
    default: float
    binds: dict[str, Any]
    unit: str = ''


@dataclasses.dataclass(frozen=True, eq=False)
class TargetSpec:
    """The ``target`` section: the point (and orientation) the end effector must reach, at
    the end of the movement, by default; ``target_position`` / ``target_orientation`` task
    parameters replace single coordinates of it per instance."""

    position: np.ndarray            # (3,) m, world frame
    orientation: np.ndarray         # (3,) rad, extrinsic x-y-z rotation angles of the frame
    body: str = ''                  # a mocap body moved to the instance's target (display)


@dataclasses.dataclass(frozen=True, eq=False)
class SceneObject:
    """One entry of the ``scene`` section: a body psl adds to the model (a mocap body with
    one geom of the same name), e.g. an obstacle, a table or a target marker."""

    name: str
    type: str                       # box | sphere | capsule | cylinder (SCENE_TYPES)
    size: np.ndarray                # MuJoCo's geom size for the type (half-sizes, radius, ...)
    position: np.ndarray            # (3,) m, world frame
    orientation: np.ndarray         # (3,) rad, extrinsic x-y-z
    contacts: bool = False          # collide with the robot (default: scored geometrically)
    rgba: tuple[float, ...] = (0.8, 0.2, 0.2, 0.6)


@dataclasses.dataclass(frozen=True, eq=False)
class ControllerSpec:
    """The ``controller`` section: gains of the PD + feed-forward law, per joint (actuator
    order). Torque limits come from the model."""

    kp: np.ndarray                  # (n_joints,) N m / rad
    kd: np.ndarray                  # (n_joints,) N m s / rad


@dataclasses.dataclass(frozen=True)
class PolicySpec:
    """The ``policy`` section: how theta encodes the commanded trajectory
    (`psl_controller.policy`)."""

    n_basis: int                    # Gaussians per joint of the DMP (and the feed-forward)
    kind: str = 'dmp'               # dmp | gmr (psl_controller.policy.KINDS)
    k_s: float = 400.0              # DMP spring constant of eq. 2.23 (k_d = 2 sqrt(k_s))
    canonical: str = 'linear'       # canonical system of the phase: linear | exponential
    feedforward: bool = False       # theta = [theta_K, theta_D]: feed-forward torque on the basis
    n_components: int = 6           # gmr: Gaussians of the mixture
    fit_seed: int = 0               # gmr: seed of the EM fit to the demonstration
    learn_goal: bool = False        # theta_K = [weights, goal]: the DMP goal is learned too
    space: str = 'joint'            # joint | end_effector: the DMP's output (SPACES)


@dataclasses.dataclass(frozen=True)
class RewardSpec:
    """The ``reward`` section: weights of the named components (`psl_optimizer.reward`), the
    success threshold and what the geometric components measure."""

    weights: dict[str, float]       # component name -> weight; missing components count zero
    success_threshold: float        # fulfilled when reward >= this
    clearance_margin: float = 0.0   # m; closer than this to an obstacle costs (clearance)
    obstacle_geoms: tuple[str, ...] = ()    # geoms the arm must keep clear of
    arm_geoms: tuple[str, ...] = ()         # the arm's geoms measured against them


@dataclasses.dataclass(frozen=True)
class SafetySpec:
    """The ``safety`` section: what a candidate's commanded trajectory must keep before it is
    executed (`psl_task.safety_check`), in either rollout mode. By default the reference must be
    finite and inside the joint ranges; every other limit is off until the task sets it."""

    joint_margin: float = 0.0           # rad (m) kept inside each limited joint's range
    max_velocity: float = float('inf')  # rad/s (m/s), |qd_ref| of every driven joint
    max_acceleration: float = float('inf')  # rad/s^2, |qdd_ref|
    torque_share: float = float('inf')  # inverse-dynamics torque along the reference, as a
                                        # share of each joint's torque limit (1: within them)
    collisions: bool = False            # no penetration of reward.obstacle_geoms in a
                                        # kinematic replay of the reference
    self_collision: bool = False        # no contact between the robot's own geoms in it
    replay_period: float = 0.01         # s between the replayed states of the collision check
    penalty: float = -100.0             # reward of a refused candidate, minus its violation


@dataclasses.dataclass(frozen=True)
class HomingSpec:
    """The ``homing`` section: how an episode begins. ``teleport`` (simulation only) puts the
    arm at the start posture at rest; ``drive`` moves it there through the controller first,
    along a quintic within the velocity and acceleration limits, and waits until it has
    settled (`psl_controller.homing`)."""

    reset: str = 'teleport'             # teleport | drive (RESETS); psl up --reset overrides
    max_velocity: float = 1.0           # rad/s (m/s) of any joint along the homing path
    max_acceleration: float = 4.0       # rad/s^2
    min_duration: float = 0.2           # s, the shortest homing motion
    settle_time: float = 0.3            # s held at the start posture after the motion
    tolerance: float = 0.01             # rad from the start posture (and rad/s of velocity)
                                        # within which the arm counts as there


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

    def _bound(self, tau: np.ndarray | None, kind: str):
        """(value, binding) of each task parameter of this kind in tau (default instance
        for None)."""
        tau = self.tau_default if tau is None else tau
        return [(float(v) + float(p.binds.get('offset', 0.0)), p.binds)
                for v, p in zip(tau, self.parameters) if p.binds['kind'] == kind]

    def duration_of(self, tau: np.ndarray | None = None) -> float:
        """The movement's duration [s] on the task instance tau: its ``duration`` task
        parameter, else the task's ``duration``."""
        bound = self._bound(tau, 'duration')
        return bound[0][0] if bound else self.duration

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
        for value, binds in self._bound(tau, 'target_position'):
            position[int(binds['axis'])] = value
        for value, binds in self._bound(tau, 'target_orientation'):
            angles[int(binds['axis'])] = value
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


def _require(data: dict, key: str, path: Path) -> Any:
    if key not in data:
        raise TaskError(f'{path}: missing key {key!r}')
    return data[key]


def _vector(value: Any, key: str, n: int | None, path: Path) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim != 1 or (n is not None and arr.size != n) or not np.all(np.isfinite(arr)):
        want = f'{n} finite numbers' if n is not None else 'a list of finite numbers'
        raise TaskError(f'{path}: {key} must be {want}, got {value!r}')
    return arr


def _parse(path: Path) -> TaskDefinition:
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise TaskError(f'{path}: not valid YAML: {exc}') from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise TaskError(f'{path}: cannot be read: {exc}') from None
    try:
        return _build(path, data)
    except KeyError as exc:
        raise TaskError(f'{path}: missing key {exc}') from exc
    except (TypeError, ValueError) as exc:
        if isinstance(exc, TaskError):
            raise
        raise TaskError(f'{path}: {exc}') from exc


def _build(path: Path, data: Any) -> TaskDefinition:
    if not isinstance(data, dict):
        raise TaskError(f'{path}: a task file is a mapping of keys')
    robot = data.get('robot', {})
    robot_keys = {'model', 'end_effector', 'package_paths', 'torque_limits',
                  'gravity_compensation', 'joints'}
    if not isinstance(robot, dict) or set(robot) - robot_keys:
        raise TaskError(f'{path}: robot is a mapping with the keys {", ".join(sorted(robot_keys))}')
    if ('model' in robot) == ('model' in data):
        raise TaskError(f'{path}: give the model once, as robot.model (or the top-level model)')
    # absolute (or ~/...) as given; a relative path is relative to the YAML file's folder;
    # package://NAME/... through psl_task.package_paths
    model = str(robot['model'] if 'model' in robot else data['model'])
    package_paths = _package_paths(robot.get('package_paths', {}), path)
    if model.startswith(PACKAGE_PREFIX):
        model_path = package_file(path, model, 'robot.model', package_paths).resolve()
    else:
        model_path = (path.parent / Path(model).expanduser()).resolve()
    if not model_path.is_file():
        raise TaskError(f'{path}: model file {model_path} does not exist')
    start = _vector(_require(data, 'start_posture', path), 'start_posture', None, path)
    n = start.size
    params = []
    for entry in _require(data, 'task_parameters', path):
        binds = dict(entry.get('binds', {}))
        if binds.get('kind') not in BINDING_KINDS:
            raise TaskError(f'{path}: task parameter {entry.get("name")!r} binds kind must be '
                            f'one of {BINDING_KINDS}, got {binds.get("kind")!r}')
        low, high = float(entry['low']), float(entry['high'])
        if not low < high:
            raise TaskError(f'{path}: task parameter {entry["name"]!r} needs low < high')
        _check_binding(binds, str(entry['name']), low + float(binds.get('offset', 0.0)), path)
        params.append(TaskParameter(
            name=str(entry['name']), low=low, high=high,
            default=float(entry.get('default', 0.5 * (low + high))),
            binds=binds, unit=str(entry.get('unit', ''))))
    kinds = [p.binds['kind'] for p in params]
    if kinds.count('duration') > 1:
        raise TaskError(f'{path}: at most one task parameter binds the duration')
    target = _target(data['target'], path) if 'target' in data else None
    if target is None and {'target_position', 'target_orientation'} & set(kinds):
        raise TaskError(f'{path}: target_position / target_orientation task parameters need a '
                        'target section (target: {position: [x, y, z]})')
    controller = _section(data, 'controller', path)
    demo = _require(data, 'demonstration', path)
    demo_positions = np.asarray(demo['positions'], dtype=float)
    if demo_positions.ndim != 2 or demo_positions.shape[1] != n:
        found = (f'rows of {demo_positions.shape[1]}' if demo_positions.ndim == 2
                 else f'shape {demo_positions.shape}')
        raise TaskError(f'{path}: demonstration positions must be rows of {n} joint angles, '
                        f'one per entry of start_posture (one per driven joint); found {found}')
    demo_times = _vector(demo['times'], 'demonstration times', len(demo_positions), path)
    goal = _vector(_require(data, 'goal_posture', path), 'goal_posture', n, path)
    for what, posture, row in (('start_posture', start, 0), ('goal_posture', goal, -1)):
        if not np.allclose(demo_positions[row], posture, rtol=0.0, atol=1e-6):
            raise TaskError(f'{path}: the demonstration must {"start" if row == 0 else "end"} '
                            f'at {what} {posture.tolist()} (the DMP runs from its first to '
                            f'its last waypoint), got {demo_positions[row].tolist()}')
    joints = _joint_names(robot.get('joints', []), n, path)
    gravity_compensation = robot.get('gravity_compensation', False)
    if not isinstance(gravity_compensation, bool):
        raise TaskError(f'{path}: robot.gravity_compensation must be true or false')
    duration = float(_require(data, 'duration', path))
    if not duration > 0.0:
        raise TaskError(f'{path}: duration must be > 0 s, got {duration:g}')
    if np.any(np.diff(demo_times) <= 0.0) or demo_times[0] != 0.0 or \
            abs(demo_times[-1] - duration) > 1e-9 * max(1.0, duration):
        raise TaskError(f'{path}: demonstration times must rise from 0 to duration '
                        f'({duration:g} s): the DMP starts at the first waypoint and ends at '
                        f'the last; got {demo_times.tolist()}')
    return TaskDefinition(
        name=str(data.get('name', path.stem)),
        path=path,
        model_path=model_path,
        description=str(data.get('description', '')),
        **_end_effector(robot, data, path),
        control_rate=float(_require(data, 'control_rate', path)),
        duration=duration,
        settle_time=float(data.get('settle_time', 0.0)),
        start_posture=start,
        goal_posture=goal,
        parameters=tuple(params),
        controller=ControllerSpec(
            kp=_vector(_require(controller, 'kp', path), 'controller.kp', n, path),
            kd=_vector(_require(controller, 'kd', path), 'controller.kd', n, path)),
        policy=_policy(_section(data, 'policy', path), path),
        demo_times=demo_times,
        demo_positions=demo_positions,
        reward=_reward(_section(data, 'reward', path), path),
        target=target,
        safety=_safety(data.get('safety', {}), path),
        homing=_homing(data.get('homing', {}), path),
        scene=_scene(data.get('scene', []), path),
        package_paths=package_paths,
        torque_limits=(None if 'torque_limits' not in robot else _vector(
            robot['torque_limits'], 'robot.torque_limits', n, path)),
        gravity_compensation=gravity_compensation,
        joints=joints,
    )


def _joint_names(entries: Any, n: int, path: Path) -> tuple[str, ...]:
    """robot.joints: distinct joint names, one per entry of start_posture (none: the
    model's actuated joints)."""
    if not isinstance(entries, list) or not all(isinstance(e, str) for e in entries):
        raise TaskError(f'{path}: robot.joints is a list of joint names, got {entries!r}')
    if entries and len(entries) != n:
        raise TaskError(f'{path}: robot.joints names {len(entries)} driven joints, '
                        f'start_posture has {n} entries: give one posture entry per driven '
                        'joint, in the order of robot.joints')
    if len(set(entries)) != len(entries):
        raise TaskError(f'{path}: robot.joints names a joint twice: {entries}')
    return tuple(entries)


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


def _package_paths(section: Any, path: Path) -> dict[str, Path]:
    """robot.package_paths: package name -> folder (relative to the YAML's folder)."""
    if not isinstance(section, dict):
        raise TaskError(f'{path}: robot.package_paths maps package names to folders')
    return {str(k): (path.parent / Path(str(v)).expanduser()).resolve()
            for k, v in section.items()}


def _end_effector(robot: dict, data: dict, path: Path) -> dict:
    """end_effector_site (and body, offset) from robot.end_effector ({site: NAME} or
    {body: NAME, offset: [x, y, z]}) or the top-level end_effector_site."""
    if ('end_effector' in robot) == ('end_effector_site' in data):
        raise TaskError(f'{path}: give the end effector once, as robot.end_effector '
                        '({site: NAME} or {body: NAME, offset: [x, y, z]}) or end_effector_site')
    if 'end_effector_site' in data:
        return {'end_effector_site': str(data['end_effector_site'])}
    spec = robot['end_effector']
    if not isinstance(spec, dict) or not (set(spec) == {'site'} or
                                          set(spec) <= {'body', 'offset'} and 'body' in spec):
        raise TaskError(f'{path}: robot.end_effector is {{site: NAME}} or {{body: NAME, '
                        f'offset: [x, y, z]}}, got {spec!r}')
    if 'site' in spec:
        return {'end_effector_site': str(spec['site'])}
    return {'end_effector_site': END_EFFECTOR_SITE, 'end_effector_body': str(spec['body']),
            'end_effector_offset': _vector(spec.get('offset', [0.0, 0.0, 0.0]),
                                           'robot.end_effector.offset', 3, path)}


def _scene(entries: Any, path: Path) -> tuple[SceneObject, ...]:
    if not isinstance(entries, list):
        raise TaskError(f'{path}: scene is a list of objects')
    known = [f.name for f in dataclasses.fields(SceneObject)]
    objects, names = [], set()
    for entry in entries:
        if not isinstance(entry, dict) or 'name' not in entry:
            raise TaskError(f'{path}: every scene object is a mapping with a name, got {entry!r}')
        name = str(entry['name'])
        unknown = sorted(set(entry) - set(known))
        if unknown:
            raise TaskError(f'{path}: scene object {name!r} has unknown keys {unknown}; '
                            f'known: {", ".join(known)}')
        kind = str(entry.get('type', 'box'))
        if kind not in SCENE_TYPES:
            raise TaskError(f'{path}: scene object {name!r}: type must be one of '
                            f'{", ".join(SCENE_TYPES)}, got {kind!r}')
        if name in names:
            raise TaskError(f'{path}: two scene objects are called {name!r}')
        names.add(name)
        size = _vector(_require(entry, 'size', path), f'scene object {name!r} size',
                       SCENE_TYPES[kind], path)
        if not np.all(size > 0):
            raise TaskError(f'{path}: scene object {name!r}: sizes must be > 0, got '
                            f'{size.tolist()}')
        contacts = entry.get('contacts', False)
        if not isinstance(contacts, bool):
            raise TaskError(f'{path}: scene object {name!r}: contacts must be true or false')
        rgba = _vector(entry.get('rgba', SceneObject.rgba), f'scene object {name!r} rgba', 4,
                       path)
        objects.append(SceneObject(
            name=name, type=kind, size=size, contacts=contacts, rgba=tuple(rgba.tolist()),
            position=_vector(_require(entry, 'position', path),
                             f'scene object {name!r} position', 3, path),
            orientation=_vector(entry.get('orientation', [0.0, 0.0, 0.0]),
                                f'scene object {name!r} orientation', 3, path)))
    return tuple(objects)


def _check_binding(binds: dict, name: str, lowest: float, path: Path) -> None:
    """The keys each binding kind needs."""
    kind = binds['kind']
    if kind in ('mocap_position', 'body_mass') and 'body' not in binds:
        raise TaskError(f'{path}: task parameter {name!r} ({kind}) needs a body')
    if kind in ('mocap_position', 'target_position', 'target_orientation'):
        if binds.get('axis') not in (0, 1, 2):
            raise TaskError(f'{path}: task parameter {name!r} ({kind}) needs axis 0, 1 or 2, '
                            f'got {binds.get("axis")!r}')
    if kind == 'duration' and not lowest > 0.0:
        raise TaskError(f'{path}: task parameter {name!r} binds the duration: its range must '
                        f'stay above 0 s, lowest {lowest:g}')


def _target(section: Any, path: Path) -> TargetSpec:
    if not isinstance(section, dict):
        raise TaskError(f'{path}: target must be a mapping of keys')
    _known_keys(section, TargetSpec, 'target', path)
    return TargetSpec(
        position=_vector(_require(section, 'position', path), 'target.position', 3, path),
        orientation=_vector(section.get('orientation', [0.0, 0.0, 0.0]), 'target.orientation',
                            3, path),
        body=str(section.get('body', '')))


def _section(data: dict, key: str, path: Path) -> dict:
    section = _require(data, key, path)
    if not isinstance(section, dict):
        raise TaskError(f'{path}: {key} must be a mapping of keys')
    return section


def _known_keys(section: dict, spec: type, key: str, path: Path) -> None:
    known = [f.name for f in dataclasses.fields(spec)]
    unknown = sorted(set(section) - set(known))
    if unknown:
        raise TaskError(f'{path}: {key} has unknown keys {unknown}; known: {", ".join(known)}')


def _policy(section: dict, path: Path) -> PolicySpec:
    _known_keys(section, PolicySpec, 'policy', path)
    feedforward = section.get('feedforward', PolicySpec.feedforward)
    if not isinstance(feedforward, bool):
        raise TaskError(f'{path}: policy.feedforward must be true or false, got '
                        f'{feedforward!r}')
    learn_goal = section.get('learn_goal', PolicySpec.learn_goal)
    if not isinstance(learn_goal, bool):
        raise TaskError(f'{path}: policy.learn_goal must be true or false, got {learn_goal!r}')
    space = str(section.get('space', PolicySpec.space))
    if space not in SPACES:
        raise TaskError(f'{path}: policy.space must be one of {", ".join(SPACES)}, got '
                        f'{space!r}')
    n_basis = int(_require(section, 'n_basis', path))
    if n_basis < 1:
        raise TaskError(f'{path}: policy.n_basis must be at least 1, got {n_basis}')
    return PolicySpec(n_basis=n_basis,
                      kind=str(section.get('kind', PolicySpec.kind)),
                      k_s=float(section.get('k_s', PolicySpec.k_s)),
                      canonical=str(section.get('canonical', PolicySpec.canonical)),
                      feedforward=feedforward,
                      n_components=int(section.get('n_components', PolicySpec.n_components)),
                      fit_seed=int(section.get('fit_seed', PolicySpec.fit_seed)),
                      learn_goal=learn_goal, space=space)


def _homing(section: Any, path: Path) -> HomingSpec:
    if not isinstance(section, dict):
        raise TaskError(f'{path}: homing must be a mapping of keys')
    _known_keys(section, HomingSpec, 'homing', path)
    values = {k: float(v) for k, v in section.items() if k != 'reset'}
    for key, value in values.items():
        if not value > 0.0 or not np.isfinite(value):
            raise TaskError(f'{path}: homing.{key} must be > 0, got {value:g}')
    reset = str(section.get('reset', HomingSpec.reset))
    if reset not in RESETS:
        raise TaskError(f'{path}: homing.reset must be one of {", ".join(RESETS)}, got {reset!r}')
    return HomingSpec(reset=reset, **values)


def _safety(section: Any, path: Path) -> SafetySpec:
    if not isinstance(section, dict):
        raise TaskError(f'{path}: safety must be a mapping of keys')
    _known_keys(section, SafetySpec, 'safety', path)
    values = {}
    for field in dataclasses.fields(SafetySpec):
        if field.name not in section:
            continue
        value = section[field.name]
        if isinstance(field.default, bool):
            if not isinstance(value, bool):
                raise TaskError(f'{path}: safety.{field.name} must be true or false')
        else:
            value = float(value)
            if field.name != 'penalty' and not value >= 0.0:
                raise TaskError(f'{path}: safety.{field.name} must be >= 0, got {value:g}')
            if field.name == 'replay_period' and not value > 0.0:
                raise TaskError(f'{path}: safety.replay_period must be > 0 s')
            if field.name == 'penalty' and not np.isfinite(value):
                raise TaskError(f'{path}: safety.penalty must be finite')
        values[field.name] = value
    return SafetySpec(**values)


def _reward(section: dict, path: Path) -> RewardSpec:
    _known_keys(section, RewardSpec, 'reward', path)
    weights = _require(section, 'weights', path)
    if not isinstance(weights, dict):
        raise TaskError(f'{path}: reward.weights must map component names to weights')
    margin = float(section.get('clearance_margin', RewardSpec.clearance_margin))
    if not margin >= 0.0:
        raise TaskError(f'{path}: reward.clearance_margin must be >= 0, got {margin}')
    return RewardSpec(weights={str(k): float(v) for k, v in weights.items()},
                      success_threshold=float(_require(section, 'success_threshold', path)),
                      clearance_margin=margin,
                      obstacle_geoms=tuple(str(g) for g in section.get('obstacle_geoms', ())),
                      arm_geoms=tuple(str(g) for g in section.get('arm_geoms', ())))
