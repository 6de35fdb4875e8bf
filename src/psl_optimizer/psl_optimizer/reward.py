"""Task reward assembled from named cost components (dm_control style: small pure functions).

Every component is a non-negative cost; the reward is ``-sum(weight_i * cost_i)`` with the
weights from the task YAML, and a rollout fulfils its task instance when the reward reaches
the task's success threshold. The same code scores graph-mode and batch-mode rollouts.
Imports no ROS.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from psl_sim.arm_model import ArmModel

COMPONENTS = ('goal_error', 'penetration', 'clearance', 'smoothness', 'effort',
              'tracking_error')


def _finite(name: str, array: np.ndarray) -> np.ndarray:
    array = np.asarray(array, dtype=float)
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{name} must be finite')
    return array


def goal_error(ee_final: np.ndarray, ee_goal: np.ndarray) -> float:
    """Euclidean distance [m] of the final end-effector position (3,) to the goal (3,)."""
    ee_final, ee_goal = _finite('ee_final', ee_final), _finite('ee_goal', ee_goal)
    if ee_final.shape != (3,) or ee_goal.shape != (3,):
        raise ValueError(f'ee_final {ee_final.shape} and ee_goal {ee_goal.shape} must be (3,)')
    return float(np.linalg.norm(ee_final - ee_goal))


def penetration(distance: np.ndarray) -> float:
    """Deepest penetration [m] of the arm into an obstacle over the rollout: the largest
    negative signed distance (T,), or 0 when the arm never touches one."""
    distance = _finite('distance', distance)
    if distance.size == 0:
        raise ValueError('distance is empty')
    return float(max(0.0, -np.min(distance)))


def clearance(distance: np.ndarray, margin: float) -> float:
    """Mean shortfall [m] of the signed distance (T,) below the clearance margin >= 0."""
    if not margin >= 0:
        raise ValueError(f'margin must be >= 0, got {margin}')
    distance = _finite('distance', distance)
    if distance.size == 0:
        raise ValueError('distance is empty')
    return float(np.mean(np.maximum(0.0, margin - distance)))


def smoothness(q: np.ndarray, dt: float) -> float:
    """Mean squared joint acceleration [rad^2/s^4] of q (T, n), by second differences."""
    q = _finite('q', q)
    if dt <= 0:
        raise ValueError('dt must be > 0')
    if len(q) < 3:
        return 0.0
    acc = np.diff(q, n=2, axis=0) / dt**2
    return float(np.mean(acc**2))


def effort(torque: np.ndarray) -> float:
    """Mean squared joint torque [N^2 m^2] of torque (T, n)."""
    torque = _finite('torque', torque)
    return float(np.mean(torque**2)) if torque.size else 0.0


def tracking_error(q: np.ndarray, q_ref: np.ndarray) -> float:
    """RMS [rad] of reference minus measured joint angle, over time and joints."""
    q, q_ref = _finite('q', q), _finite('q_ref', q_ref)
    if q.shape != q_ref.shape:
        raise ValueError(f'q {q.shape} and q_ref {q_ref.shape} differ in shape')
    if q.size == 0:
        raise ValueError('q is empty')
    return float(np.sqrt(np.mean((q_ref - q) ** 2)))


@dataclasses.dataclass(frozen=True)
class RewardResult:
    reward: float
    fulfilled: bool
    components: dict[str, float]   # unweighted costs, in COMPONENTS order


def score(components: dict[str, float], weights: dict[str, float],
          success_threshold: float) -> RewardResult:
    """reward = -sum(weight * component); components without a weight count zero."""
    unknown = set(weights) - set(COMPONENTS)
    if unknown:
        raise ValueError(f'unknown reward components {sorted(unknown)}; known: {COMPONENTS}')
    reward = -sum(float(weights.get(name, 0.0)) * value for name, value in components.items())
    return RewardResult(reward=reward, fulfilled=bool(reward >= success_threshold),
                        components=dict(components))


def evaluate_rollout(arm: ArmModel, tau: np.ndarray, q: np.ndarray, torque: np.ndarray,
                     q_ref: np.ndarray) -> RewardResult:
    """Score one rollout of the arm's task (graph mode: geometry from a kinematic replay).

    Args:
        arm: the task's model (used for end-effector positions and obstacle distances).
        tau: the task instance (E,).
        q: measured joint angles (T, n), one row per control period, first = start.
        torque: applied joint torques (T, n).
        q_ref: commanded joint angles (T, n) the controller tracked.
    Returns:
        RewardResult with every component of COMPONENTS.
    Raises:
        ValueError: non-finite data or inconsistent shapes.
    """
    q = _finite('q', q)
    if q.ndim != 2 or q.shape[1] != len(arm.joint_names):
        raise ValueError(f'q {q.shape} must be (T, {len(arm.joint_names)})')
    ee, dist = arm.replay(q, tau)
    return evaluate_arrays(arm, q, torque, q_ref, ee[-1],
                           dist if np.isfinite(dist).all() else None)


def evaluate_arrays(arm: ArmModel, q: np.ndarray, torque: np.ndarray, q_ref: np.ndarray,
                    ee_final: np.ndarray, distance: np.ndarray | None) -> RewardResult:
    """Score a rollout from its arrays; `distance` (T,) is the smallest arm-obstacle signed
    distance per state, None when the task has no obstacle. Shared by graph and batch mode."""
    task = arm.task
    q, torque = _finite('q', q), _finite('torque', torque)
    if q.ndim != 2 or q.shape[1] != len(arm.joint_names) or torque.shape != q.shape:
        raise ValueError(f'q {q.shape} and torque {torque.shape} must both be '
                         f'(T, {len(arm.joint_names)})')
    cfg = task.reward
    components = {
        'goal_error': goal_error(ee_final, arm.ee_goal),
        'penetration': penetration(distance) if distance is not None else 0.0,
        'clearance': (clearance(distance, float(cfg.get('clearance_margin', 0.0)))
                      if distance is not None else 0.0),
        'smoothness': smoothness(q, task.control_period),
        'effort': effort(torque),
        'tracking_error': tracking_error(q, q_ref),
    }
    return score(components, cfg['weights'], float(cfg['success_threshold']))


def evaluate_population(arm: ArmModel, q: np.ndarray, torque: np.ndarray, q_ref: np.ndarray,
                        ee_final: np.ndarray, distance: np.ndarray | None) -> list[RewardResult]:
    """`evaluate_arrays` for a whole population at once (batch mode): q, torque, q_ref
    (B, T, n), ee_final (B, 3), distance (B, T) or None. Same components, vectorised."""
    q, torque, q_ref = _finite('q', q), _finite('torque', torque), _finite('q_ref', q_ref)
    if q.ndim != 3 or torque.shape != q.shape or q_ref.shape != q.shape:
        raise ValueError(f'q {q.shape}, torque {torque.shape}, q_ref {q_ref.shape} must all be '
                         '(B, T, n)')
    task, cfg = arm.task, arm.task.reward
    dt = task.control_period
    acc = np.diff(q, n=2, axis=1) / dt**2
    columns = {
        'goal_error': np.linalg.norm(_finite('ee_final', ee_final) - arm.ee_goal, axis=1),
        'penetration': (np.maximum(0.0, -_finite('distance', distance).min(axis=1))
                        if distance is not None else np.zeros(len(q))),
        'clearance': (np.mean(np.maximum(0.0, float(cfg.get('clearance_margin', 0.0))
                                         - distance), axis=1)
                      if distance is not None else np.zeros(len(q))),
        'smoothness': (np.mean(acc**2, axis=(1, 2)) if q.shape[1] >= 3
                       else np.zeros(len(q))),
        'effort': np.mean(torque**2, axis=(1, 2)),
        'tracking_error': np.sqrt(np.mean((q_ref - q) ** 2, axis=(1, 2))),
    }
    return [score({name: float(values[b]) for name, values in columns.items()},
                  cfg['weights'], float(cfg['success_threshold'])) for b in range(len(q))]
