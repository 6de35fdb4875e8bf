"""A task's movement representation: theta -> commanded joint trajectory on the control grid.

For ``policy.kind: dmp`` the kinematics are one DMP per joint (eq. 2.23-2.24) from the task's
start posture to its goal posture; the default theta is the least-squares fit of the task's
demonstration. With ``policy.kind: gmr`` the kinematics are instead a Gaussian mixture over
[phase, q] conditioned on the phase (eq. 2.25, `psl_controller.gmr_trajectory`;
``n_components``, default 6): theta_K = the components' means and slopes, fitted to the same
demonstration by EM; start and goal are then not guaranteed, only learned. Both expose theta_K
as one flat vector (get_theta / set_theta) and ``integrate(dt, t_end)``.
With ``policy.feedforward: true`` theta is one flat vector
``[theta_K, theta_D]``: theta_K as above, theta_D the weights of the feed-forward torque
u_ffwd(t) on the DMP's basis (`psl_controller.feedforward`, same size),
default theta_D = 0. Without the option theta = theta_K and u_ffwd is zero.

Task variability the DMP carries (``kind: dmp`` only):
- ``policy.learn_goal: true``: theta_K = [weights, goal], the DMP goal is learned per instance
  (default: the demonstration's end);
- a ``duration`` task parameter: the same theta stretched in time to the instance's duration
  (the DMP's temporal scaling, `DMP` ``time_scale``); the control grid stays, the episode
  follows the duration;
- ``policy.space: end_effector``: the DMP runs over the end-effector position (3-D, start and
  default goal from the demonstration's end-effector path) and the joint reference is its
  differential inverse kinematics on the task's model (`psl_task.inverse_kinematics`), computed
  from theta before the rollout, the same in graph and batch mode;
- with ``policy.orientation: true`` as well (end-effector space only) the hand's orientation
  is a unit-quaternion DMP on the same phase (Ude et al. 2014, `psl_controller.pose_dmp`):
  theta_K = [position weights, position goal, orientation weights, goal rotation vector]
  (the goals with ``learn_goal``; the rotation relative to the demonstration's last
  orientation), and the inverse kinematics follows position and orientation.
Imports no ROS; the DMP executor node and batch rollouts both call `TaskPolicy.reference`.
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import time

import numpy as np

from psl_controller.dmp import DMP, demonstration_from_waypoints
from psl_controller.feedforward import FeedForward
from psl_controller.gmr_trajectory import GMRTrajectory
from psl_controller.pose_dmp import PoseDMP
from psl_controller.quaternion_dmp import QuaternionDMP
from psl_task.task import TaskDefinition


KINDS = ('dmp', 'gmr')     # how theta_K encodes the joint trajectory
THETA_SPREADS = 1000.0     # a rollout's theta entries lie within this many default spreads
HAND_PATHS_KEPT = 64       # end-effector space: joint paths kept for a theta_K seen again


@dataclasses.dataclass(frozen=True)
class Reference:
    """Commanded trajectory sampled every control period, t = k * dt for k = 0..num_steps."""

    t: np.ndarray       # (T,)
    q: np.ndarray       # (T, n_joints)
    qd: np.ndarray      # (T, n_joints)
    u_ffwd: np.ndarray  # (T, n_joints)


class TaskPolicy:
    """theta (flat vector) -> Reference, for one task (and its instances tau)."""

    def __init__(self, task: TaskDefinition):
        spec = task.policy
        if spec.kind not in KINDS:
            raise ValueError(f'task {task.name!r}: unknown policy kind {spec.kind!r}; known: '
                             f'{", ".join(KINDS)}')
        varies_duration = any(p.binds.sets_duration for p in task.parameters)
        if spec.kind != 'dmp' and (spec.learn_goal or spec.space != 'joint' or varies_duration):
            raise ValueError(f'task {task.name!r}: learn_goal, space end_effector and a duration '
                             'task parameter need policy kind dmp')
        if spec.orientation and spec.space != 'end_effector':
            raise ValueError(f'task {task.name!r}: policy.orientation needs space end_effector '
                             '(the hand\'s orientation is a DMP of its own only there)')
        self.task = task
        dt = task.control_period
        t, y = demonstration_from_waypoints(task.demo_times, task.demo_positions, dt)
        self.ik = None
        # wall time spent in the inverse kinematics, the paths it solved and the paths
        # reused from `_hand_path`'s (benchmarks)
        self.ik_seconds, self.ik_paths, self.ik_reused = 0.0, 0, 0
        self._hand_paths: dict[tuple, tuple] = {}     # `_hand_path`'s, oldest first
        quat = None
        if spec.space == 'end_effector':
            self.ik = end_effector_ik(task)
            poses = [self.ik.pose(q) for q in y]             # the demonstration's hand path
            y = np.array([x for x, _ in poses])
            quat = np.array([r for _, r in poses])
        # the DMP's phase and basis also carry the feed-forward, whatever encodes theta_K
        self.dmp = DMP(n_dims=y.shape[1], n_basis=spec.n_basis, duration=task.duration,
                       y0=y[0], goal=y[-1], k_s=spec.k_s, canonical=spec.canonical,
                       learn_goal=spec.learn_goal)
        self.dmp.fit(t, y, dt)
        if spec.kind == 'gmr':
            self.movement = GMRTrajectory(task.n_joints, spec.n_components, task.duration)
            self.movement.fit(t, y, seed=spec.fit_seed)
        elif spec.orientation:
            self.movement = PoseDMP(self.dmp, self._orientation_dmp(quat[0], quat[-1]))
            self.movement.orientation.fit(t, quat, dt)
        else:
            self.movement = self.dmp
        self._torque_limits = torque_limits(task) if spec.feedforward else (None, None)
        self.feedforward = (FeedForward(self.dmp.canonical, self.dmp.basis, task.n_joints,
                                        *self._torque_limits)
                            if spec.feedforward else None)
        self._stretched: dict[float, tuple] = {}      # duration -> (movement, feedforward)
        n_kin = self.movement.num_parameters
        n_dyn = self.feedforward.num_parameters if spec.feedforward else 0
        self.kinematics = slice(0, n_kin)               # theta_K in theta
        self.dynamics = slice(n_kin, n_kin + n_dyn)     # theta_D in theta (empty without)
        # the learned goal in theta (empty without learn_goal): the DMP's goal, or the pose's
        # position goal; the pose's goal rotation vector (empty without orientation)
        n_goal = self.dmp.n_dims if spec.learn_goal else 0
        self.goal = slice(self.dmp.num_weights, self.dmp.num_weights + n_goal)
        self.orientation_goal = (self.movement.orientation_goal if spec.orientation
                                 else slice(n_kin, n_kin))
        self.default_theta = np.concatenate([self.movement.get_theta(), np.zeros(n_dyn)])
        # range policy of a rollout: an entry this far from the default is an absurd magnitude
        self.theta_bound = THETA_SPREADS * max(1.0, float(np.max(np.abs(self.default_theta))))

    def _orientation_dmp(self, q0: np.ndarray, goal: np.ndarray,
                         time_scale: float = 1.0) -> QuaternionDMP:
        """The hand's orientation DMP on the position DMP's phase (its settings)."""
        spec = self.task.policy
        return QuaternionDMP(n_basis=spec.n_basis, duration=self.task.duration * time_scale,
                             q0=q0, goal=goal, k_s=spec.k_s, canonical=spec.canonical,
                             learn_goal=spec.learn_goal, time_scale=time_scale)

    @property
    def num_parameters(self) -> int:
        return self.default_theta.size

    def fit_demonstration(self, times: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """theta whose movement reproduces a demonstration: joint angles positions (T, n) at
        times (T,) [s, increasing], its time mapped linearly onto [0, the task's duration];
        theta_K fitted as the default theta is to the YAML's demonstration (in end-effector
        space to the hand's path, with ``policy.orientation`` to its orientation too; a
        learned goal becomes the demonstration's end), theta_D zero. The policy itself is not
        changed. Raises ValueError for shapes other than these, fewer than 2 samples,
        non-finite values or times that do not increase."""
        times = np.asarray(times, dtype=float)
        positions = np.asarray(positions, dtype=float)
        if (times.ndim != 1 or len(times) < 2 or positions.shape != (len(times),
                                                                     self.task.n_joints)):
            raise ValueError(f'a demonstration is times (T,) and positions (T, '
                             f'{self.task.n_joints}) with T >= 2, got {times.shape} and '
                             f'{positions.shape}')
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(positions))):
            raise ValueError('a demonstration must be finite')
        if np.any(np.diff(times) <= 0.0):
            raise ValueError('demonstration times must increase')
        t = (times - times[0]) * (self.task.duration / (times[-1] - times[0]))
        movement = copy.deepcopy(self.movement)
        spec = self.task.policy
        if self.ik is None:
            y = positions
        else:
            poses = [self.ik.pose(q) for q in positions]
            y = np.array([x for x, _ in poses])
        if spec.kind == 'gmr':
            movement.fit(t, y, seed=spec.fit_seed)
        elif self.controls_orientation:
            movement.fit(t, y, np.array([r for _, r in poses]), self.task.control_period)
        else:
            movement.fit(t, y, self.task.control_period)
        return np.concatenate([movement.get_theta(), np.zeros(self.dynamics.stop
                                                              - self.dynamics.start)])

    @property
    def controls_orientation(self) -> bool:
        """Whether the hand's orientation is a DMP of its own (``policy.orientation``)."""
        return isinstance(self.movement, PoseDMP)

    @property
    def has_feedforward(self) -> bool:
        return self.feedforward is not None

    def with_feedforward(self, theta: np.ndarray, theta_d: np.ndarray) -> np.ndarray:
        """theta with its theta_D block replaced (theta_K kept). Raises ValueError for a task
        without feed-forward or sizes that do not fit."""
        if self.feedforward is None:
            raise ValueError(f'task {self.task.name!r} has no feed-forward (policy.feedforward)')
        theta = np.array(theta, dtype=float)
        theta_d = np.asarray(theta_d, dtype=float).reshape(-1)
        n_dyn = self.feedforward.num_parameters
        if theta.shape != self.default_theta.shape or theta_d.size != n_dyn:
            raise ValueError(f'theta needs {self.num_parameters} and theta_D '
                             f'{n_dyn} entries')
        theta[self.dynamics] = theta_d
        return theta

    def _for_duration(self, duration: float):
        """(movement, feed-forward) of the instance's duration: the task's own, or the DMP
        stretched in time (same theta, same shape, `DMP` time_scale)."""
        if duration == self.task.duration:
            return self.movement, self.feedforward
        if duration not in self._stretched:
            if len(self._stretched) >= 64:
                self._stretched.pop(next(iter(self._stretched)))
            spec, base = self.task.policy, self.dmp
            dmp = DMP(n_dims=base.n_dims, n_basis=base.n_basis, duration=duration,
                      y0=base.y0, goal=base.goal, k_s=spec.k_s, canonical=spec.canonical,
                      learn_goal=spec.learn_goal, time_scale=duration / self.task.duration)
            feedforward = (FeedForward(dmp.canonical, dmp.basis, self.task.n_joints,
                                       *self._torque_limits)
                           if self.feedforward is not None else None)
            movement = dmp
            if self.controls_orientation:
                turn = self.movement.orientation
                movement = PoseDMP(dmp, self._orientation_dmp(
                    turn.q0, turn.default_goal, duration / self.task.duration))
            self._stretched[duration] = (movement, feedforward)
        return self._stretched[duration]

    def feedforward_for(self, tau: np.ndarray | None = None) -> FeedForward:
        """The feed-forward signal on the instance's phase (its duration): what theta_D
        means on task instance tau. ValueError for a task without feed-forward."""
        if self.feedforward is None:
            raise ValueError(f'task {self.task.name!r} has no feed-forward (policy.feedforward)')
        return self._for_duration(self.task.duration_of(tau))[1]

    def check_theta(self, theta: np.ndarray) -> np.ndarray:
        """theta as a float array, or ValueError for the wrong size, NaN/inf or an absurd
        magnitude (the range policy of a rollout)."""
        theta = np.asarray(theta, dtype=float)
        if theta.shape != self.default_theta.shape:
            raise ValueError(f'task {self.task.name!r} takes theta with '
                             f'{self.num_parameters} entries, got {theta.size}')
        if not np.all(np.isfinite(theta)):
            raise ValueError('theta contains NaN or inf')
        far = np.abs(theta - self.default_theta) > self.theta_bound
        if np.any(far):
            i = int(np.flatnonzero(far)[0])
            raise ValueError(f'theta[{i}] = {theta[i]:g} lies more than {self.theta_bound:g} '
                             f'from the default policy ({self.default_theta[i]:g}) of task '
                             f'{self.task.name!r}: a units or scaling error')
        return theta

    def reference(self, theta: np.ndarray, tau: np.ndarray | None = None) -> Reference:
        """The commanded trajectory for theta over one episode of the task instance tau
        (default: the task's default instance; only a duration task parameter changes the
        reference). Raises ValueError for a theta of the wrong size, with NaN/inf or absurd
        magnitudes, or (end-effector space) a path the arm cannot follow."""
        theta = self.check_theta(theta)
        duration = self.task.duration_of(tau)
        movement, feedforward = self._for_duration(duration)
        dt = self.task.control_period
        num_steps = self.task.num_steps_of(tau)
        if self.ik is None:
            movement.set_theta(theta[self.kinematics])
            return self._reference_of(movement.integrate(dt, num_steps * dt), theta,
                                      feedforward, dt)
        t, q, qd = self._hand_path(movement, theta[self.kinematics], duration, num_steps, dt)
        u_ffwd = (feedforward.signal(theta[self.dynamics], t)
                  if feedforward is not None else np.zeros_like(q))
        return Reference(t=t, q=q, qd=qd, u_ffwd=u_ffwd)

    def _hand_path(self, movement, theta_k: np.ndarray, duration: float, num_steps: int,
                   dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t, q, qd) of the hand path theta_K commands over num_steps periods, in joint
        space (the inverse kinematics), read-only; the last `HAND_PATHS_KEPT` are kept by
        (theta_K, duration, num_steps), which determine them: a theta_K seen again (ILC or
        CMA-ES changing only theta_D, the summary's feed-forward variants of one path) gives
        the very arrays of its first solve."""
        key = (theta_k.tobytes(), duration, num_steps)
        kept = self._hand_paths.pop(key, None)
        if kept is None:
            movement.set_theta(theta_k)
            traj = movement.integrate(dt, num_steps * dt)
            q, qd = self._joint_path(traj, dt)
            t = np.array(traj.t)
            t.setflags(write=False)
            kept = (t, q, qd)
            if len(self._hand_paths) >= HAND_PATHS_KEPT:
                self._hand_paths.pop(next(iter(self._hand_paths)))
        else:
            self.ik_reused += 1
        self._hand_paths[key] = kept                   # the most recent last
        return kept

    def references(self, thetas: np.ndarray, taus: np.ndarray) -> list[Reference]:
        """`reference` of each row of thetas (B, F) on its task instance taus (B, E), within
        rounding: a DMP in joint space integrates the rollouts of one duration as one
        population (`DMP.integrate_population`, `FeedForward.signal_population`); other
        movements go one by one. Raises what `reference` raises, naming the row."""
        thetas = np.asarray(thetas, dtype=float)
        if thetas.ndim != 2 or len(thetas) != len(taus):
            raise ValueError(f'thetas must be (B, {self.num_parameters}) with one task '
                             f'instance per row, got {thetas.shape} and {len(taus)}')
        if self.task.policy.kind != 'dmp' or self.ik is not None:
            return [self.reference(theta, tau) for theta, tau in zip(thetas, taus)]
        for b, theta in enumerate(thetas):
            try:
                self.check_theta(theta)
            except ValueError as exc:
                raise ValueError(f'theta {b}: {exc}') from None
        dt = self.task.control_period
        rows: dict[tuple[float, int], list[int]] = {}
        for b, tau in enumerate(taus):
            key = (self.task.duration_of(tau), self.task.num_steps_of(tau))
            rows.setdefault(key, []).append(b)
        references: list[Reference | None] = [None] * len(thetas)
        for (duration, num_steps), index in rows.items():
            movement, feedforward = self._for_duration(duration)
            group = thetas[index]
            traj = movement.integrate_population(dt, group[:, self.kinematics], num_steps * dt)
            u_ffwd = (feedforward.signal_population(group[:, self.dynamics], traj.t)
                      if feedforward is not None else np.zeros_like(traj.y))
            for i, b in enumerate(index):
                references[b] = Reference(t=traj.t, q=traj.y[i], qd=traj.yd[i],
                                          u_ffwd=u_ffwd[i])
        return references

    def reference_with_new_goal(self, theta: np.ndarray, tau: np.ndarray | None,
                                t_switch: float, new_goal) -> Reference:
        """`reference` with a goal change: the same trajectory up to ``t_switch`` (seconds
        from the episode start; the first control period at or after it), then the DMP's
        attractor moving smoothly to ``new_goal`` (`DMP.integrate_goal_change`, no jump in
        q, qd). ``new_goal`` is in the DMP's space: joint angles (n_joints,) [rad], or for
        ``policy.space: end_effector`` the hand point (3,) [m] (with ``policy.orientation``
        also (7,): the point and the hand's orientation, a unit quaternion [w, x, y, z],
        turned to with the position's goal filter), whose path is then followed
        by inverse kinematics (q is then the same up to the switch, qd, a central
        difference of q, up to the period before). Raises ValueError for a policy kind other
        than dmp, a new goal of the wrong size or not finite, a switch time outside the
        episode, and whatever `reference` refuses."""
        if self.task.policy.kind != 'dmp':
            raise ValueError(f'task {self.task.name!r}: a goal change needs policy kind dmp, '
                             f'not {self.task.policy.kind!r}')
        new_goal = np.atleast_1d(np.asarray(new_goal, dtype=float))
        if self.controls_orientation:
            sizes, space = (3, 7), ('the hand point [m], or the point and the hand\'s '
                                    'orientation as a unit quaternion [w, x, y, z]')
        else:
            sizes = (self.dmp.n_dims,)
            space = ('the hand point [m]' if self.ik is not None
                     else f'the joint angles [rad] of the {self.task.n_joints} joints')
        if new_goal.ndim != 1 or new_goal.size not in sizes:
            raise ValueError(f'task {self.task.name!r}: the new goal needs '
                             f'{" or ".join(map(str, sizes))} values ({space}), got '
                             f'{new_goal.size}')
        if not np.all(np.isfinite(new_goal)):
            raise ValueError(f'the new goal must be finite, got {new_goal.tolist()}')
        theta = self.check_theta(theta)
        dt = self.task.control_period
        t_end = self.task.num_steps_of(tau) * dt
        if not (np.isfinite(t_switch) and 0.0 <= t_switch < t_end):
            raise ValueError(f'the goal change time must lie in [0, {t_end:g}) s, the episode, '
                             f'got {t_switch!r}')
        movement, feedforward = self._for_duration(self.task.duration_of(tau))
        movement.set_theta(theta[self.kinematics])
        traj = movement.integrate_goal_change(dt, t_switch, new_goal, t_end)
        if self.ik is None:
            return self._reference_of(traj, theta, feedforward, dt)
        # the joint path up to the switch is the reference's, bit for bit: the inverse
        # kinematics (its knots and splines) see the path after a sample, so it continues
        # from the reference's posture at the switch
        switch = min(len(traj.t) - 1, int(np.ceil(t_switch / dt - 1e-9)))
        before, _ = self._joint_path(movement.integrate(dt, t_end), dt)
        after, _ = self._joint_path(traj, dt, start=before[switch], first=switch)
        q = np.concatenate([before[:switch + 1], after[1:]])
        u_ffwd = (feedforward.signal(theta[self.dynamics], traj.t)
                  if feedforward is not None else np.zeros_like(q))
        return Reference(t=traj.t, q=q, qd=np.gradient(q, dt, axis=0), u_ffwd=u_ffwd)

    def _reference_of(self, traj, theta: np.ndarray, feedforward: FeedForward | None,
                      dt: float) -> Reference:
        """The Reference of a movement integrated in joint space and theta_D's feed-forward
        on the same grid (end-effector space: `_hand_path`)."""
        u_ffwd = (feedforward.signal(theta[self.dynamics], traj.t)
                  if feedforward is not None else np.zeros_like(traj.y))
        return Reference(t=traj.t, q=traj.y, qd=traj.yd, u_ffwd=u_ffwd)

    def _joint_path(self, traj, dt: float, start: np.ndarray | None = None, first: int = 0
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Joint angles and velocities (T, n) that follow the hand path traj.y (T, 3) (and
        with a pose DMP its orientations traj.quat (T, 4)) from sample ``first`` on, from
        the start posture or ``start`` (differential inverse kinematics; qd its finite
        difference)."""
        began = time.perf_counter()
        quat = getattr(traj, 'quat', None)
        solution = self.ik.solve(traj.y[first:],
                                 self.task.start_posture if start is None else start, dt,
                                 orientation_ref=None if quat is None else quat[first:])
        self.ik_seconds += time.perf_counter() - began
        self.ik_paths += 1
        return solution.q, solution.qd


@functools.lru_cache(maxsize=16)
def policy_for(task: TaskDefinition) -> TaskPolicy:
    return TaskPolicy(task)


def torque_limits(task: TaskDefinition) -> tuple[np.ndarray, np.ndarray]:
    """The arm's torque limits (low, high) per driven joint (``ArmModel``), which the
    feed-forward is clipped into (`psl_controller.feedforward`)."""
    from psl_task.arm_model import ArmModel
    arm = ArmModel(task)
    return arm.torque_low.copy(), arm.torque_high.copy()


def end_effector_ik(task: TaskDefinition):
    """Differential inverse kinematics (`psl_task.inverse_kinematics.DifferentialIK`) of the
    task's end-effector site on its own model, pulled toward the start posture in the null
    space, its steps within the arm's joint velocity bounds (``ArmModel.limits.velocity``)."""
    from psl_task.arm_model import ArmModel
    from psl_task.inverse_kinematics import DifferentialIK
    arm = ArmModel(task)
    return DifferentialIK(arm.model, task.end_effector_site, arm.qpos_adr, arm.dof_adr,
                          q_rest=task.start_posture, max_velocity=arm.limits.velocity)
