"""Task reward assembled from named cost components (dm_control style: small pure functions).

Every component is a non-negative cost, written once and vectorised over a population of
rollouts (one rollout is a population of one): arrays carry the rollout first, ``(B, ...)``.
The reward is ``-sum(weight_i * cost_i)`` with the weights from the task YAML, and a rollout
fulfils its task instance when the reward reaches the task's success threshold. `Reward`
scores graph-mode and batch-mode rollouts alike; the geometric components read the task's
`psl_task.reward_geometry` (MuJoCo sensors, recorded by batch mode's rollout or evaluated on a
kinematic replay of the measured joint angles in graph mode). Imports no ROS.

Components come from one registry (`psl_task.reward_components`, the entry point group
``psl.reward_components``): the seven built-ins below (the ``*_cost`` functions of a
`RolloutData`, registered by this package's setup.cfg) and whatever a user's package
registers. A component sees read-only views of its inputs (`RolloutData`, the task included:
`psl_task.reward_components.read_only`) and is called within the task's
``reward.component_timeout``. One that raises (a write into its inputs too), returns what is
not a finite real cost per rollout, or does not return in time fails the rollouts it could not
score: they get the task's penalty and the reason (`RewardResult.failure`); the others are
scored.
"""
from __future__ import annotations

import dataclasses
import types
from typing import Mapping

import mujoco
import numpy as np

from psl_task import quaternion
from psl_task import reward_components
from psl_task.reward_components import ComponentFailed, ComponentTimedOut, read_only
from psl_task.reward_geometry import Measurements, RewardGeometry
from psl_task.task import TaskDefinition

# psl's own components, each scored for every rollout (the evaluation message carries them,
# weighted or not); in this order, then the task's other weighted components
COMPONENTS = ('goal_error', 'penetration', 'clearance', 'smoothness', 'effort',
              'tracking_error', 'orientation_error')
FAILED = 'component_failed'     # the one component of a rollout a component failed to score


@dataclasses.dataclass(frozen=True)
class RolloutData:
    """What a reward component sees of a population of B rollouts of one task, T states each
    (S_0 .. S_N, one per control period); a component gets it read-only (`Reward.evaluate`:
    the arrays read-only views, the mappings and the task read-only)."""

    task: TaskDefinition            # its reward section, target, control period
    q: np.ndarray                   # (B, T, n) measured joint angles [rad]
    torque: np.ndarray              # (B, T, n) torque applied in the step before each state
    q_ref: np.ndarray               # (B, T, n) the reference the controller tracked
    measured: Measurements          # the reward geometry along the rollouts
    taus: np.ndarray                # (B, E) task instances
    goal_position: np.ndarray       # (B, 3) [m] each rollout's goal (after a goal change: the
                                    # new goal's)
    goal_rotation: np.ndarray       # (B, 3, 3) its orientation (identity without a target)
    world: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    # body name -> (B, T, 7) pose per state: position [m], orientation (w, x, y, z), of each
    # body the task observes (reward.observe); measured by MuJoCo in simulation, from the
    # body's pose topic on a robot

    @property
    def dt(self) -> float:
        """The control period [s] between two states."""
        return self.task.control_period

    def __len__(self) -> int:
        return len(self.q)


def _finite(name: str, array: np.ndarray, ndim: int) -> np.ndarray:
    array = np.asarray(array, dtype=float)
    if array.ndim != ndim:
        raise ValueError(f'{name} must have {ndim} dimensions (rollout first), got shape '
                         f'{array.shape}')
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{name} must be finite')
    return array


def goal_error(ee_final: np.ndarray, ee_goal: np.ndarray) -> np.ndarray:
    """Euclidean distance [m] of each rollout's final end-effector position to its goal:
    ee_final (B, 3), ee_goal (B, 3) -> (B,)."""
    ee_final, ee_goal = _finite('ee_final', ee_final, 2), _finite('ee_goal', ee_goal, 2)
    if ee_final.shape != ee_goal.shape or ee_final.shape[1] != 3:
        raise ValueError(f'ee_final {ee_final.shape} and ee_goal {ee_goal.shape} must both be '
                         '(B, 3)')
    return np.linalg.norm(ee_final - ee_goal, axis=1)


def orientation_error(quat_final: np.ndarray, rotation_goal: np.ndarray) -> np.ndarray:
    """Angle [rad] of the rotation between each rollout's final end-effector frame and its
    target frame: quat_final (B, 4) unit quaternions (w, x, y, z), rotation_goal (B, 3, 3)
    rotation matrices -> (B,) in [0, pi]."""
    quat_final = _finite('quat_final', quat_final, 2)
    rotation_goal = _finite('rotation_goal', rotation_goal, 3)
    if quat_final.shape[1] != 4 or rotation_goal.shape != (len(quat_final), 3, 3):
        raise ValueError(f'quat_final {quat_final.shape} must be (B, 4) and rotation_goal '
                         f'{rotation_goal.shape} (B, 3, 3)')
    w, x, y, z = (quat_final / np.linalg.norm(quat_final, axis=1, keepdims=True)).T
    rotation = np.stack([                                  # the frame's rotation matrix
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)],
        axis=1)
    # trace(R_goal^T R) = 1 + 2 cos(angle)
    cos = 0.5 * (np.einsum('bij,bij->b', rotation_goal, rotation) - 1.0)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def penetration(distance: np.ndarray) -> np.ndarray:
    """Deepest penetration [m] of the arm into an obstacle over each rollout: the largest
    negative signed distance of distance (B, T), or 0 when the arm never touches one -> (B,)."""
    distance = _finite('distance', distance, 2)
    if distance.shape[1] == 0:
        raise ValueError('distance is empty')
    return np.maximum(0.0, -distance.min(axis=1))


def clearance(distance: np.ndarray, margin: float) -> np.ndarray:
    """Mean shortfall [m] of the signed distance (B, T) below the clearance margin >= 0
    -> (B,)."""
    if not margin >= 0:
        raise ValueError(f'margin must be >= 0, got {margin}')
    distance = _finite('distance', distance, 2)
    if distance.shape[1] == 0:
        raise ValueError('distance is empty')
    return np.mean(np.maximum(0.0, margin - distance), axis=1)


def smoothness(q: np.ndarray, dt: float) -> np.ndarray:
    """Mean squared joint acceleration [rad^2/s^4] of q (B, T, n), by second differences
    -> (B,); zero for fewer than three states."""
    q = _finite('q', q, 3)
    if dt <= 0:
        raise ValueError('dt must be > 0')
    if q.shape[1] < 3:
        return np.zeros(len(q))
    acc = np.diff(q, n=2, axis=1) / dt**2
    return np.mean(acc**2, axis=(1, 2))


def effort(torque: np.ndarray) -> np.ndarray:
    """Mean squared joint torque [N^2 m^2] of torque (B, T, n) -> (B,)."""
    torque = _finite('torque', torque, 3)
    if torque[0].size == 0:
        return np.zeros(len(torque))
    return np.mean(torque**2, axis=(1, 2))


def tracking_error(q: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """RMS [rad] of reference minus measured joint angle, over time and joints: q and q_ref
    (B, T, n) -> (B,)."""
    q, q_ref = _finite('q', q, 3), _finite('q_ref', q_ref, 3)
    if q.shape != q_ref.shape:
        raise ValueError(f'q {q.shape} and q_ref {q_ref.shape} differ in shape')
    if q[0].size == 0:
        raise ValueError('q is empty')
    return np.sqrt(np.mean((q_ref - q) ** 2, axis=(1, 2)))


# -- the built-in components: functions of RolloutData (psl_task.reward_components), registered
#    under their names in setup.cfg ([options.entry_points] psl.reward_components)
def goal_error_cost(r: RolloutData) -> np.ndarray:
    """`goal_error` of the last state's end effector and each rollout's goal."""
    return goal_error(r.measured.end_effector[:, -1], r.goal_position)


def penetration_cost(r: RolloutData) -> np.ndarray:
    """`penetration` of the arm-obstacle distance; zero for a task with no obstacle."""
    distance = r.measured.distance
    return penetration(distance) if distance is not None else np.zeros(len(r))


def clearance_cost(r: RolloutData) -> np.ndarray:
    """`clearance` below the task's ``reward.clearance_margin``; zero with no obstacle."""
    distance = r.measured.distance
    return (clearance(distance, r.task.reward.clearance_margin) if distance is not None
            else np.zeros(len(r)))


def smoothness_cost(r: RolloutData) -> np.ndarray:
    """`smoothness` of the measured joint angles, or of the reference
    (``reward.smoothness_of``)."""
    return smoothness(r.q if r.task.reward.smoothness_of == 'measured' else r.q_ref, r.dt)


def effort_cost(r: RolloutData) -> np.ndarray:
    """`effort` of the applied torque."""
    return effort(r.torque)


def tracking_error_cost(r: RolloutData) -> np.ndarray:
    """`tracking_error` of the measured joint angles to the reference."""
    return tracking_error(r.q, r.q_ref)


def orientation_error_cost(r: RolloutData) -> np.ndarray:
    """`orientation_error` of the last state's hand frame to each goal orientation; zero for
    a task without a target."""
    if r.task.target is None:
        return np.zeros(len(r))
    return orientation_error(r.measured.end_effector_quat[:, -1], r.goal_rotation)


@dataclasses.dataclass(frozen=True)
class RewardResult:
    reward: float
    fulfilled: bool
    components: dict[str, float]   # unweighted costs: COMPONENTS, then the task's others
    failure: str = ''              # why a component could not score it (then: the penalty)


def check_weights(weights: dict[str, float]) -> None:
    """ValueError for a weight of a component no package registers (the nearest named)."""
    reward_components.check_names(weights)


def score(components: dict[str, float], weights: dict[str, float],
          success_threshold: float) -> RewardResult:
    """reward = -sum(weight * component); components without a weight count zero."""
    reward = -sum(float(weights.get(name, 0.0)) * value for name, value in components.items())
    return RewardResult(reward=reward, fulfilled=bool(reward >= success_threshold),
                        components=dict(components))


def failed(reason: str, penalty: float) -> RewardResult:
    """The result of a rollout a component could not score: the task's penalty, not
    fulfilled, the reason."""
    return RewardResult(reward=float(penalty), fulfilled=False, components={FAILED: 1.0},
                        failure=reason)


def _one(rollouts: RolloutData, b: int) -> RolloutData:
    """Rollout b of a population, as a population of one."""
    m = rollouts.measured
    row = slice(b, b + 1)
    measured = Measurements(end_effector=m.end_effector[row],
                            end_effector_quat=m.end_effector_quat[row],
                            distance=None if m.distance is None else m.distance[row],
                            world=types.MappingProxyType({k: v[row]
                                                          for k, v in m.world.items()}))
    return dataclasses.replace(
        rollouts, q=rollouts.q[row], torque=rollouts.torque[row], q_ref=rollouts.q_ref[row],
        measured=measured, taus=rollouts.taus[row], goal_position=rollouts.goal_position[row],
        goal_rotation=rollouts.goal_rotation[row], world=measured.world)


class Reward:
    """A task's reward: the components above with the weights, threshold and clearance margin
    of its ``reward`` section, the goal and the distances from its `RewardGeometry`. The goal
    is the instance's target (`TaskDefinition.target_of`) for a task with a ``target``
    section, else the end effector at the goal posture; after a goal change during a rollout,
    the new goal's (`goal_of`, passed to `evaluate`). ``orientation_error`` needs a
    target.

    Raises:
        ValueError: a weight of an unknown component.
    """

    def __init__(self, task: TaskDefinition, geometry: RewardGeometry):
        check_weights(task.reward.weights)
        self.task, self.geometry = task, geometry
        self.spec = task.reward
        self.task_view = read_only(task)      # what the components see of the task
        # every component this reward scores, each loaded once (a plugin imported here)
        self.components = {name: reward_components.load(name)
                           for name in dict.fromkeys(COMPONENTS + tuple(self.spec.weights))}
        self.ee_goal = geometry.end_effector_at(task.goal_posture)      # (3,)
        if task.target is None and self.spec.weights.get('orientation_error', 0.0):
            raise ValueError(f'task {task.name!r}: the orientation_error component needs a '
                             'target section (target: {position: ..., orientation: ...})')

    def goals(self, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The goal position (B, 3) and orientation (B, 3, 3) of each task instance of taus
        (B, E)."""
        if self.task.target is None:
            return (np.broadcast_to(self.ee_goal, (len(taus), 3)),
                    np.broadcast_to(np.eye(3), (len(taus), 3, 3)))
        targets = [self.task.target_of(tau) for tau in taus]
        return np.array([p for p, _ in targets]), np.array([r for _, r in targets])

    def goal_of(self, dmp_goal) -> tuple[np.ndarray, np.ndarray | None]:
        """The goal position (3,) [m] and orientation (rotation matrix (3, 3), or None: the
        instance's stays) of a DMP goal (a goal changed during a rollout): the hand point
        itself when the task's DMP runs in end-effector space (``policy.space``), with a pose
        DMP (``policy.orientation``) optionally followed by the hand's orientation as a unit
        quaternion [w, x, y, z] (7 values); else the end effector at the joint goal posture
        (n_joints,).

        Raises:
            ValueError: a goal of the wrong size, not finite, or a quaternion part that is not
                of unit norm.
        """
        in_hand_space = self.task.policy.space == 'end_effector'
        sizes = ((3, 7) if self.task.policy.orientation else (3,)) if in_hand_space \
            else (self.task.n_joints,)
        goal = np.atleast_1d(np.asarray(dmp_goal, dtype=float))
        if goal.ndim != 1 or goal.size not in sizes or not np.all(np.isfinite(goal)):
            raise ValueError(f'task {self.task.name!r}: a DMP goal is '
                             f'{" or ".join(map(str, sizes))} finite values, got '
                             f'{goal.tolist()}')
        if not in_hand_space:
            return self.geometry.end_effector_at(goal), None
        if goal.size == 3:
            return goal.copy(), None
        quat = quaternion.as_unit_quaternion(goal[3:], 'the goal orientation')
        rotation = np.empty(9)
        mujoco.mju_quat2Mat(rotation, quat)
        return goal[:3].copy(), rotation.reshape(3, 3)

    def evaluate(self, q: np.ndarray, torque: np.ndarray, q_ref: np.ndarray,
                 measured: Measurements, taus: np.ndarray,
                 goal_positions: np.ndarray | None = None,
                 goal_rotations: np.ndarray | None = None) -> list[RewardResult]:
        """Score a population of rollouts.

        Args:
            q: measured joint angles (B, T, n), one row per control period, first = start.
            torque: torque applied in the step before each state (B, T, n).
            q_ref: commanded joint angles (B, T, n) the controller tracked.
            measured: the geometry along the rollouts (`RewardGeometry.read` or `replay`).
            taus: the rollouts' task instances (B, E) (their targets).
            goal_positions: (B, 3) [m] goal positions that replace those of `goals` for
                ``goal_error`` (the final goals of rollouts whose goal changed, `goal_of`);
                default: `goals`.
            goal_rotations: (B, 3, 3) goal orientations that replace those of `goals` for
                ``orientation_error`` (a pose goal changed, `goal_of`); default: `goals`.
        Returns:
            One RewardResult per rollout, with every component of COMPONENTS and the task's
            other weighted ones; a rollout a component failed on: `failed`.
        Raises:
            ValueError: non-finite data or inconsistent shapes.
        """
        q, torque = _finite('q', q, 3), _finite('torque', torque, 3)
        n = self.task.n_joints
        if q.shape[2] != n or torque.shape != q.shape:
            raise ValueError(f'q {q.shape} and torque {torque.shape} must both be (B, T, {n})')
        distance = measured.distance
        taus = np.atleast_2d(np.asarray(taus, dtype=float))
        if len(taus) != len(q):
            raise ValueError(f'{len(q)} rollouts but {len(taus)} task instances')
        goal_position, goal_rotation = self.goals(taus)
        if goal_positions is not None:
            goal_position = _finite('goal_positions', goal_positions, 2)
        if goal_rotations is not None:
            goal_rotation = _finite('goal_rotations', goal_rotations, 3)
        measured = read_only(measured)      # the components' views (psl's arrays stay)
        rollouts = RolloutData(task=self.task_view, q=read_only(q), torque=read_only(torque),
                               q_ref=read_only(np.asarray(q_ref, dtype=float)),
                               measured=measured, taus=read_only(taus),
                               goal_position=read_only(goal_position),
                               goal_rotation=read_only(goal_rotation), world=measured.world)
        failures: dict[int, str] = {}

        def columns_of(call) -> dict[str, np.ndarray]:      # on a worker thread
            columns = {}
            for name, function in self.components.items():
                if len(failures) == len(q):     # none left to score
                    break
                columns[name] = self._column(call, name, function, rollouts, failures)
            return columns
        try:
            columns = reward_components.CALLS.run(columns_of, self.spec.component_timeout)
        except ComponentTimedOut as late:       # every rollout not failed yet fails with it
            columns = {}
            for b in range(len(q)):
                failures.setdefault(b, str(late))
        results = []
        for b in range(len(q)):
            if b in failures:
                results.append(failed(failures[b], self.task.safety.penalty))
            else:
                results.append(score({name: float(values[b]) for name, values in columns.items()},
                                     self.spec.weights, self.spec.success_threshold))
        return results

    @staticmethod
    def _column(call, name: str, function, rollouts: RolloutData,
                failures: dict[int, str]) -> np.ndarray:
        """One component's costs (B,), called through `call` (`BoundedCalls.run`); a rollout
        it fails on (it raised or returned what is not a real cost on that rollout alone, or
        its cost is not finite) is entered in `failures` with the reason (its cost NaN) and
        the others are scored (while its call that passed the bound still runs, each rollout
        alone fails at once with the reason)."""
        try:
            values = reward_components.evaluate(name, function, rollouts, call)
        except ComponentFailed as population_failure:
            if len(rollouts) == 1:
                values = np.array([np.nan])
                failures.setdefault(0, str(population_failure))
            else:           # which rollouts: each alone
                values = np.empty(len(rollouts))
                for b in range(len(rollouts)):
                    one = _one(rollouts, b)
                    values[b] = Reward._column(call, name, function, one, sub := {})[0]
                    if sub:
                        failures.setdefault(b, sub[0])
                return values
        for b, reason in reward_components.failures(name, values).items():
            failures.setdefault(b, reason)
        return values

    def evaluate_replayed(self, q: np.ndarray, torque: np.ndarray, q_ref: np.ndarray,
                          taus: np.ndarray, goal_positions: np.ndarray | None = None,
                          goal_rotations: np.ndarray | None = None,
                          world: dict | None = None) -> list[RewardResult]:
        """`evaluate` with the geometry from a kinematic replay of q on the task instances
        taus (B, E): graph mode, where the joint states were measured, and the observed
        bodies' poses `world` ({body: (B, T, 7)}, `RewardGeometry.replay`)."""
        return self.evaluate(q, torque, q_ref, self.geometry.replay(q, taus, world), taus,
                             goal_positions, goal_rotations)
