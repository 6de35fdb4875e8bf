"""The safety check before a rollout: a candidate's commanded trajectory is executed only if it
keeps the task's ``safety`` limits (`psl_task.task.SafetySpec`).

Both rollout modes call it on the reference of every candidate before anything moves: batch mode
(`psl_optimizer.batch_rollout`) before ``mujoco.rollout``, the graph's executor before it sends
the trajectory and resets the episode. A refused candidate is not executed; it gets the reward
``penalty - violation`` and the reason. Checked, in this order (the first failure is the reason):

1. the reference (positions, velocities, the feed-forward) is finite;
2. every driven joint stays ``joint_margin`` inside its range (limited joints). One law for
   every reference, with the posture it leaves from (`outside`: how far each joint is outside
   its range with the margin, 0 inside): no joint gets farther outside than that posture and
   its earlier points were (its distance to the range never grows), and every joint ends
   inside. A candidate leaves from the start posture, inside: it must stay inside throughout.
   A homing reference (`check` with ``start``, the measured posture) may leave from outside,
   where a foreign goal or a push left the arm: a motion toward the range passes, one further
   out is refused;
3. ``|qd_ref|`` within the arm's velocity bound (``ArmModel.limits``: a URDF's velocity limit,
   else `psl_task.joint_limits.MAX_VELOCITY`, and ``max_velocity`` where lower) and
   ``|qdd_ref| <= max_acceleration`` (qdd the forward difference of qd_ref,
   `reference_acceleration`);
4. the feed-forward ``u_ffwd`` within each joint's torque limits (``ArmModel.torque_low`` /
   ``torque_high``);
5. the reference as psl sends it to a controller (a point per control period, positions and
   velocities, the last at rest: `psl_controller.robot_link.trajectory_msg`) between its
   points: the cubic a JointTrajectoryController interpolates inside the joint ranges and the
   velocity bound, within the slack every controller psl serves allows
   (`psl_task.joint_limits.interpolation_excess`). Rules 3-5 are the rule those controllers
   hold every goal to (`psl_controller.goal_limits`), on the same limits: a candidate the
   check passes is a goal they take, so batch mode runs nothing the graph's controller would
   reject, and a homing or a live goal change that passed is taken too;
6. the torque that makes the model follow the reference (``mj_inverse`` on the task instance:
   what the PD + feed-forward law must supply when it tracks) stays within ``torque_share``
   times each joint's torque limit;
7. ``collisions``: in a kinematic replay of the reference (every ``replay_period`` s) no robot
   geom penetrates an obstacle of ``reward.obstacle_geoms``; ``self_collision``: no contact
   between geoms of two robot bodies (MuJoCo's own filter drops parent and child).

The violation (>= 0) grows with how far the candidate is from safe, so that CMA-ES, which sees
the penalty, is led back: the excess in rad (range, and the interpolation's beyond its slack),
the excess ratio (velocity, acceleration, torque; the feed-forward's excess as a share of the
torque limit, the interpolation's velocity beyond its slack as a share of the bound) or in m
(penetration).

While it moves, ``max_tracking_error`` bounds ``|q - q_ref|`` of every driven joint: the
controller aborts the episode at the first state past it and holds. The rollout then counts
as the penalty, ``penalty - violation`` with the violation the error beyond the bound at that
state, in both modes (`tracking_abort` replays the controller's check on a batch episode).
Imports no ROS.
"""
from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from psl_task.arm_model import ArmModel
from psl_task.joint_limits import control_points, interpolation_excess
from psl_task.model_spec import robot_bodies

NOT_FINITE_VIOLATION = 1e6


@dataclasses.dataclass(frozen=True)
class Verdict:
    """The outcome for one candidate: safe, or the reason and how far from safe."""

    safe: bool
    reason: str = ''
    violation: float = 0.0          # >= 0; 0 when safe

    def penalty(self, base: float) -> float:
        """The reward of a refused candidate: base - violation."""
        return float(base - self.violation)


SAFE = Verdict(True)


def abort_reason(joint: str, error: float, seconds: float, bound: float) -> str:
    """The controller's reason for a tracking abort (one wording in both modes)."""
    return (f'episode aborted: joint {joint!r} is {error:.4g} rad from its reference at '
            f'{seconds:.3f} s, beyond the bound {bound:g} (safety.max_tracking_error)')


def tracking_abort(q: np.ndarray, q_ref: np.ndarray, bound: float, joint_names,
                   dt: float) -> Verdict:
    """The controller's tracking bound replayed on an episode's measured angles q and
    reference q_ref (T, n) on the control grid (`psl_controller.pd_controller_node`: at the
    first state whose ``|q - q_ref|`` passes `bound` on any joint it aborts the episode):
    SAFE, or that state's reason and violation (the error beyond the bound)."""
    if not np.isfinite(bound):
        return SAFE
    error = np.abs(np.asarray(q) - np.asarray(q_ref))
    over = error.max(axis=1) > bound
    if not over.any():
        return SAFE
    k = int(np.argmax(over))
    j = int(np.argmax(error[k]))
    return Verdict(False, abort_reason(joint_names[j], float(error[k, j]), k * dt, bound),
                   float(error[k, j] - bound))


def reference_acceleration(qd: np.ndarray, dt: float) -> np.ndarray:
    """The acceleration (T, n) of each control period: the forward difference of the commanded
    velocity qd (T, n) (with one semi-implicit Euler step per period, the acceleration that
    reaches the next commanded velocity); the last period repeats the one before."""
    qdd = np.diff(qd, axis=0) / dt                                      # (T-1, n)
    return np.vstack([qdd, qdd[-1:]]) if len(qdd) else np.zeros_like(qd)


def inside_from(q: np.ndarray, low: np.ndarray, high: np.ndarray) -> int:
    """The first index of the samples q (T, n) from which every sample is inside every
    range [low, high] (0: all are; T: the last is not)."""
    outside = np.any((q < low) | (q > high), axis=1)
    return int(len(q) - np.argmax(outside[::-1])) if outside.any() else 0


class SafetyCheck:
    """The task's safety limits on its arm (see the module docstring)."""

    def __init__(self, arm: ArmModel):
        self.arm, self.spec = arm, arm.task.safety
        self.limits = limits = arm.limits
        margin = self.spec.joint_margin        # unlimited: -inf, inf, with or without it
        self.low, self.high = limits.position_low + margin, limits.position_high - margin
        self.torque_limit = np.maximum(np.abs(limits.effort_low), np.abs(limits.effort_high))
        # the goal's segments last a whole number of ns (`goal_points`), as a controller reads
        self.segment = round(arm.task.control_period * 1e9) * 1e-9
        self._replay = None
        if self.spec.collisions or self.spec.self_collision:
            self._replay = mujoco.MjData(arm.model)
            self._robot_bodies = set(np.flatnonzero(robot_bodies(arm.model,
                                                                 arm.joint_ids)).tolist())
            self._obstacles = [arm.geom(g) for g in arm.task.reward.obstacle_geoms]
            self._arm = [arm.geom(g) for g in arm.arm_geoms]

    @property
    def checks_dynamics(self) -> bool:
        return bool(np.isfinite(self.spec.torque_share))

    @property
    def defaults_only(self) -> bool:
        """True when the task sets no limit beyond those `screen` checks in one vectorised
        pass (finite; the ranges; the arm's velocity and torque limits and the interpolation
        between points, rules 3-5): no acceleration bound, torque share or collision check."""
        s = self.spec
        return (not np.isfinite(s.max_acceleration) and not self.checks_dynamics
                and self._replay is None)

    def screen(self, taus: np.ndarray, q: np.ndarray, qd: np.ndarray,
               u_ffwd: np.ndarray) -> list[Verdict]:
        """`check` of a population, references q, qd, u_ffwd (B, T, n) on instances taus
        (B, E): the same verdicts. With the default limits the candidates that pass (nearly
        all) are found in one vectorised pass; only the others get the detailed `check` for
        their reason."""
        if not self.defaults_only:
            return [self.check(tau, qb, qdb, ub) for tau, qb, qdb, ub in zip(taus, q, qd, u_ffwd)]
        lim = self.limits
        with np.errstate(invalid='ignore', over='ignore'):
            passes = (np.isfinite(q).all(axis=(1, 2)) & np.isfinite(qd).all(axis=(1, 2))
                      & np.isfinite(u_ffwd).all(axis=(1, 2))
                      & (q >= self.low).all(axis=(1, 2)) & (q <= self.high).all(axis=(1, 2))
                      & (np.abs(qd) <= lim.velocity).all(axis=(1, 2))
                      & (u_ffwd >= lim.effort_low).all(axis=(1, 2))
                      & (u_ffwd <= lim.effort_high).all(axis=(1, 2)))
            if q.shape[1] > 1:          # every segment within its control points' hull
                b_position, b_velocity = control_points(
                    np.full(q.shape[1] - 1, self.segment), q, self._sent(qd))
                low, high, speed = lim.tolerated()
                passes &= ((b_position.min(axis=(0, 2)) >= low).all(axis=1)
                           & (b_position.max(axis=(0, 2)) <= high).all(axis=1)
                           & (np.abs(b_velocity).max(axis=(0, 2)) <= speed).all(axis=1))
        return [SAFE if ok else self.check(tau, qb, qdb, ub)
                for ok, tau, qb, qdb, ub in zip(passes, taus, q, qd, u_ffwd)]

    @staticmethod
    def _sent(qd: np.ndarray) -> np.ndarray:
        """The velocities (..., T, n) as a goal carries them: the last at rest (a JTC refuses
        a trajectory that ends moving: `psl_controller.goal_limits.goal_points`)."""
        sent = np.array(qd, dtype=float)
        sent[..., -1, :] = 0.0
        return sent

    def outside(self, q: np.ndarray) -> np.ndarray:
        """How far each joint of the postures q (..., n) is outside its range with the margin
        (rad, 0 inside)."""
        return np.maximum(np.maximum(self.low - q, q - self.high), 0.0)

    def check(self, tau: np.ndarray, q: np.ndarray, qd: np.ndarray, u_ffwd: np.ndarray,
              start: np.ndarray | None = None) -> Verdict:
        """The verdict on a reference q, qd and its feed-forward u_ffwd (T, n) for the (valid)
        task instance tau. `start`: the posture (n,) the reference leaves from, when it may be
        outside the ranges (a homing reference: the measured posture); None for a candidate,
        which leaves from the start posture (module docstring, 2)."""
        s, names, lim = self.spec, self.arm.joint_names, self.limits
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))
                and np.all(np.isfinite(u_ffwd))):
            return Verdict(False, 'the reference is not finite', NOT_FINITE_VIOLATION)
        excess = np.maximum(self.low - q, q - self.high)                  # (T, n)
        dt = self.arm.task.control_period
        if start is None:
            allowed = np.zeros_like(excess)     # from inside: a joint's distance stays 0
        else:                                   # from outside: it never grows
            allowed = np.minimum.accumulate(np.vstack(
                [self.outside(np.asarray(start, dtype=float))[None],
                 np.maximum(excess[:-1], 0.0)]), axis=0)
        over = excess - allowed                                           # (T, n)
        if np.any(over > 0.0):
            k, j = np.unravel_index(int(np.argmax(over)), over.shape)
            side = 'below' if q[k, j] < self.low[j] else 'above'
            bound = self.low[j] if side == 'below' else self.high[j]
            farther = '' if start is None or allowed[0, j] == 0.0 else (
                f', farther out than the {allowed[k, j]:.4g} rad it had come to (a homing '
                'from outside its range may only come closer to it)')
            return Verdict(False, f'joint {names[j]!r} at {q[k, j]:.4g} is {side} its limit '
                           f'{bound:.4g} (range with margin {s.joint_margin:g}) at t = '
                           f'{k * dt:.3f} s{farther}',
                           float(np.clip(over, 0.0, None).sum() * dt + over.max()))
        if start is not None and np.any(excess[-1] > 0.0):
            j = int(np.argmax(excess[-1]))
            return Verdict(False, f'joint {names[j]!r} ends at {q[-1, j]:.4g}, outside its range '
                           f'[{self.low[j]:.4g}, {self.high[j]:.4g}] (range with margin '
                           f'{s.joint_margin:g})', float(excess[-1, j]))
        qdd = reference_acceleration(qd, dt)
        for what, values, limit, unit in (('velocity', qd, lim.velocity, '/s'),
                                          ('acceleration', qdd, s.max_acceleration, '/s^2')):
            ratio = np.abs(values) / limit
            if np.any(ratio > 1.0):
                k, j = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
                return Verdict(False, f'joint {names[j]!r} reaches a {what} of '
                               f'{abs(values[k, j]):.4g} rad{unit}, above the limit '
                               f'{np.broadcast_to(limit, ratio.shape[1:])[j]:g} at '
                               f't = {k * dt:.3f} s', float(ratio.max() - 1.0))
        share = np.maximum(lim.effort_low - u_ffwd, u_ffwd - lim.effort_high) / np.where(
            self.torque_limit > 0.0, self.torque_limit, 1.0)              # (T, n)
        if np.any(share > 0.0):
            k, j = np.unravel_index(int(np.argmax(share)), share.shape)
            side, bound = (('below', lim.effort_low[j]) if u_ffwd[k, j] < lim.effort_low[j]
                           else ('above', lim.effort_high[j]))
            return Verdict(False, f'joint {names[j]!r}: the feed-forward of '
                           f'{u_ffwd[k, j]:.4g} N m at t = {k * dt:.3f} s is {side} its torque '
                           f'limit {bound:g} N m', float(share.max()))
        verdict = self._check_between(q, qd, start)
        if not verdict.safe:
            return verdict
        if self.checks_dynamics:
            torque = self.arm.inverse_dynamics(tau, q, qd, qdd)
            ratio = np.abs(torque) / (s.torque_share * self.torque_limit)
            if np.any(ratio > 1.0):
                k, j = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
                return Verdict(False, f'joint {names[j]!r} needs {abs(torque[k, j]):.4g} N m to '
                               f'follow the reference at t = {k * dt:.3f} s, above '
                               f'{s.torque_share:g} x its limit {self.torque_limit[j]:g} N m',
                               float(ratio.max() - 1.0))
        if self._replay is not None:
            return self._check_collisions(tau, q)
        return SAFE

    def _check_between(self, q: np.ndarray, qd: np.ndarray,
                       start: np.ndarray | None) -> Verdict:
        """Rule 5 (module docstring): the reference's points as a goal carries them (from its
        first point inside every range, for a homing from outside: the controller's own
        segment leads there), interpolated as a controller does."""
        first = 0 if start is None else inside_from(q, self.low, self.high)
        if len(q) - first < 2:
            return SAFE
        b_position, b_velocity = control_points(np.full(len(q) - first - 1, self.segment),
                                                q[first:], self._sent(qd)[first:])
        excess = interpolation_excess(self.limits, b_position, b_velocity)
        if excess is None:
            return SAFE
        k, dt = first + excess.index, self.arm.task.control_period
        unit = ' rad/s' if excess.field == 'velocity' else ' rad'
        violation = excess.over if excess.field == 'position' else excess.over / abs(
            excess.bound)
        return Verdict(False, f'joint {self.arm.joint_names[excess.joint]!r}: between the '
                       f'points at t = {k * dt:.3f} and {(k + 1) * dt:.3f} s, the cubic a '
                       f'controller interpolates reaches {excess.field} {excess.value:.4g}'
                       f'{unit}, {excess.side} its limit {excess.bound:.4g}{unit} by '
                       f'{excess.over + excess.slack:.3g}, more than the {excess.slack:.3g}'
                       f'{unit} the controllers psl serve tolerate', float(violation))

    def _check_collisions(self, tau: np.ndarray, q: np.ndarray) -> Verdict:
        arm, s, m, data = self.arm, self.spec, self.arm.model, self._replay
        mujoco.mj_resetData(m, data)
        arm.move_bodies(tau, data)
        dt = arm.task.control_period
        every = max(1, int(round(s.replay_period / dt)))
        steps = list(range(0, len(q), every))
        if steps[-1] != len(q) - 1:
            steps.append(len(q) - 1)
        fromto = np.empty(6)
        first, worst = None, 0.0            # the first touch (the reason), the deepest
        for k in steps:
            data.qpos[arm.qpos_adr] = q[k]
            mujoco.mj_kinematics(m, data)
            if s.collisions:
                for g1 in self._arm:
                    for g2 in self._obstacles:
                        distance = mujoco.mj_geomDistance(m, data, g1, g2, 0.0, fromto)
                        if distance < 0.0:
                            worst = max(worst, -distance)
                            first = first or (f'geom {m.geom(g1).name!r} enters obstacle '
                                              f'{m.geom(g2).name!r} at t = {k * dt:.3f} s')
            if s.self_collision:
                mujoco.mj_collision(m, data)
                for c in data.contact[:data.ncon]:
                    b1, b2 = int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])
                    if b1 != b2 and b1 in self._robot_bodies and b2 in self._robot_bodies \
                            and c.dist < 0.0:
                        worst = max(worst, -float(c.dist))
                        first = first or (f'the robot touches itself: geoms '
                                          f'{m.geom(c.geom1).name!r} and '
                                          f'{m.geom(c.geom2).name!r} at t = {k * dt:.3f} s')
        if first is not None:
            return Verdict(False, f'{first} (deepest {worst * 1000:.1f} mm)', worst)
        return SAFE
