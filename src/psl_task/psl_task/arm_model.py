"""The physics of a task: its MuJoCo model with the task parameters applied.

`ArmModel` steps the simulation with joint torques (held over the control period's
`n_substeps` physics steps) and gives named accessors (joint names, torque limits,
end-effector pose), the limits psl holds the arm to (`limits`: `psl_task.joint_limits`) and the
task parameters' bindings. What the reward measures on it is `psl_task.reward_geometry`.
Imports no ROS.
"""
from __future__ import annotations

import copy
import functools

import mujoco
import numpy as np

from psl_task.joint_limits import MAX_VELOCITY, JointLimits
from psl_task.model_spec import robot_geoms, task_model, urdf_velocity_limits
from psl_task.task import TaskDefinition, TaskError


class ArmModel:
    """A task's model: the driven hinge/slide joints with one torque actuator each (command
    order `joint_names`); every other joint passive (`passive_joints`)."""

    def __init__(self, task: TaskDefinition):
        self.task = task
        self.model = task_model(task)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.n_substeps = substeps(task, m.opt.timestep)
        self._check_motors()
        # the driven joints in command order (task_spec left one actuator on each): the
        # actuators' targets, reordered to robot.joints when the task names them
        targets = [int(m.actuator_trnid[i, 0]) for i in range(m.nu)]
        if len(set(targets)) != m.nu:
            twice = sorted({m.joint(j).name for j in targets if targets.count(j) > 1})
            raise TaskError(f'{task.model_path}: joints {twice} have more than one actuator; '
                            'psl sends one torque per joint: keep exactly one actuator on '
                            'each')
        if task.joints:
            self.joint_ids = np.array([m.joint(name).id for name in task.joints])
        else:
            self.joint_ids = np.array(targets, dtype=int)
        self.actuator_ids = np.array([targets.index(j) for j in self.joint_ids], dtype=int)
        self.joint_names = [m.joint(int(j)).name for j in self.joint_ids]
        for j in self.joint_ids:
            if int(m.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE),
                                          int(mujoco.mjtJoint.mjJNT_SLIDE)):
                raise TaskError(f'{task.model_path}: the actuated joint {m.joint(int(j)).name!r} '
                                'is not a hinge or slide: psl drives one torque per joint; '
                                'name the driven joints in robot.joints')
        # every other joint moves freely (an object on the table, a gripper left alone)
        self.passive_joints = [m.joint(j).name or f'#{j}' for j in range(m.njnt)
                               if j not in set(self.joint_ids.tolist())]
        if task.n_joints != len(self.joint_ids):
            raise TaskError(
                f'{task.path}: start_posture has {task.n_joints} entries, the model drives '
                f'{len(self.joint_ids)} joints ({", ".join(self.joint_names)}): give '
                'start_posture, goal_posture, controller.kp/kd and every demonstration row '
                f'{len(self.joint_ids)} entries, in this order (or name the driven joints in '
                'robot.joints)')
        self.qpos_adr = m.jnt_qposadr[self.joint_ids]
        self.dof_adr = m.jnt_dofadr[self.joint_ids]
        if not np.all(m.actuator_ctrllimited[self.actuator_ids]):
            raise TaskError(f'{task.model_path}: every actuator needs a ctrlrange (torque limit)')
        self._check_postures()
        # the torque that reaches the joint: ctrlrange, narrowed by the actuator's forcerange
        # and the joint's actuatorfrcrange where the model sets them
        act = self.actuator_ids
        self.torque_low = m.actuator_ctrlrange[act, 0].copy()
        self.torque_high = m.actuator_ctrlrange[act, 1].copy()
        for limited, limits in ((m.actuator_forcelimited[act], m.actuator_forcerange[act]),
                                (m.jnt_actfrclimited[self.joint_ids],
                                 m.jnt_actfrcrange[self.joint_ids])):
            limited = limited.astype(bool)
            self.torque_low[limited] = np.maximum(self.torque_low, limits[:, 0])[limited]
            self.torque_high[limited] = np.minimum(self.torque_high, limits[:, 1])[limited]
        self.limits = self._limits()
        self.ee_site = self._id(mujoco.mjtObj.mjOBJ_SITE, task.end_effector_site)
        # the geoms the reward measures against the obstacles: reward.arm_geoms, or every geom
        # of the bodies the joints move when omitted
        self.arm_geoms = task.reward.arm_geoms or (
            robot_geoms(self.model, self.joint_ids) if task.reward.obstacle_geoms else ())
        for name in self.arm_geoms + task.reward.obstacle_geoms:
            self.geom(name)                    # the reward's geoms exist: fail at load
        # each binding's applier (None: it changes neither model nor data, e.g. the target)
        self._bindings = [p.binds.applier(self) for p in task.parameters]
        # bindings that move things (data-level); a kinematic replay applies only these, so it
        # never changes the dynamics (e.g. a payload mass) of the live simulation
        self._kinematic = [not p.binds.changes_model for p in task.parameters]
        # the target's display body follows the instance's target (a mocap body, no dynamics)
        self._target_mocap = -1
        if task.target is not None and task.target.body:
            self._target_mocap = self.mocap(task.target.body)
        self.tau = task.tau_default.copy()

    # -- set-up -------------------------------------------------------------------------
    def _check_motors(self) -> None:
        """psl sends joint torques: every actuator must be a plain motor on a joint (no bias,
        no activation dynamics; a geared one is made gear 1 with its ctrlrange scaled by
        `model_spec`), so that ctrl is the joint torque."""
        m = self.model
        plain = ((m.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT)
                 & (m.actuator_dyntype == mujoco.mjtDyn.mjDYN_NONE)
                 & (m.actuator_gaintype == mujoco.mjtGain.mjGAIN_FIXED)
                 & (m.actuator_gainprm[:, 0] == 1.0)
                 & (m.actuator_biastype == mujoco.mjtBias.mjBIAS_NONE)
                 & (m.actuator_gear[:, 0] == 1.0))
        if not np.all(plain):
            names = [m.actuator(i).name or f'on joint {m.joint(m.actuator_trnid[i, 0]).name}'
                     if m.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT
                     else m.actuator(i).name or f'#{i}' for i in np.flatnonzero(~plain)]
            raise TaskError(
                f'{self.task.model_path}: actuators {names} are not plain joint motors; psl '
                'needs <motor joint="..." ctrlrange="-limit limit"/> on every joint, '
                'ctrl = joint torque (times its gear)')

    def _check_postures(self) -> None:
        """Start and goal posture and every demonstration waypoint within the joints' ranges
        (for joints with a range)."""
        m, task = self.model, self.task
        low, high = m.jnt_range[self.joint_ids, 0], m.jnt_range[self.joint_ids, 1]
        limited = m.jnt_limited[self.joint_ids].astype(bool)
        postures = [('start_posture', task.start_posture), ('goal_posture', task.goal_posture)]
        postures += [(f'demonstration waypoint {i} (t = {t:g} s)', q)
                     for i, (t, q) in enumerate(zip(task.demo_times, task.demo_positions))]
        for what, q in postures:
            outside = limited & ((q < low) | (q > high))
            if np.any(outside):
                j = int(np.flatnonzero(outside)[0])
                raise TaskError(f'{task.path}: {what} puts joint {self.joint_names[j]!r} at '
                                f'{q[j]:g}, outside its range [{low[j]:g}, {high[j]:g}] in '
                                f'{task.model_path.name}: move it inside')

    def _limits(self) -> JointLimits:
        """The limits psl holds the arm to (`psl_task.joint_limits`): the joint ranges, the
        URDF's velocity limits (else MAX_VELOCITY) within the task's safety.max_velocity, the
        torque limits."""
        m, ids = self.model, self.joint_ids
        limited = m.jnt_limited[ids].astype(bool)
        velocity = urdf_velocity_limits(self.task, self.joint_names)
        velocity = np.minimum(np.where(np.isfinite(velocity), velocity, MAX_VELOCITY),
                              float(self.task.safety.max_velocity))
        return JointLimits(tuple(self.joint_names),
                           np.where(limited, m.jnt_range[ids, 0], -np.inf),
                           np.where(limited, m.jnt_range[ids, 1], np.inf),
                           velocity, self.torque_low, self.torque_high)

    def geom(self, name: str) -> int:
        """The id of the geom called `name`; TaskError if the model has none."""
        return self._id(mujoco.mjtObj.mjOBJ_GEOM, name)

    def _id(self, kind: mujoco.mjtObj, name: str) -> int:
        idx = mujoco.mj_name2id(self.model, kind, name)
        if idx < 0:
            raise TaskError(f'{self.task.model_path}: no {kind.name[6:].lower()} named {name!r}')
        return idx

    def mocap(self, name: str) -> int:
        """The mocap index of the body called `name`; TaskError if it is not a mocap body."""
        mocap = self.model.body_mocapid[self.body(name)]
        if mocap < 0:
            raise TaskError(f'{self.task.model_path}: body {name!r} is not mocap (a task '
                            'parameter moves it: <body name=... mocap="true">)')
        return int(mocap)

    def body(self, name: str) -> int:
        """The id of the body called `name`; TaskError if the model has none."""
        return self._id(mujoco.mjtObj.mjOBJ_BODY, name)

    @property
    def changes_model(self) -> bool:
        """True when some task parameter changes the model itself (e.g. a payload mass),
        not only the data (mocap positions)."""
        return not all(self._kinematic)

    def apply_tau(self, tau: np.ndarray, data: mujoco.MjData | None = None,
                  model: mujoco.MjModel | None = None) -> np.ndarray:
        """Place the task instance in the model (obstacle position, payload mass, ...); by
        default in this arm's own model and data (then it is the arm's `tau`), else in the
        given ones (same bodies). tau must be valid already (`TaskDefinition.validate_tau`;
        `reset` validates); returns it."""
        for apply, value in zip(self._bindings, tau):
            if apply is not None:
                apply(self.model if model is None else model,
                      self.data if data is None else data, value)
        self._place_target(tau, self.data if data is None else data)
        if data is None and model is None:
            self.tau = tau
        return tau

    def move_bodies(self, tau: np.ndarray, data: mujoco.MjData) -> None:
        """Apply only the task parameters that move things (mocap positions) to data; the
        model, and so the dynamics, stay as they are. tau must be valid already
        (`TaskDefinition.validate_tau`): this runs on every rollout of a population."""
        for apply, kinematic, value in zip(self._bindings, self._kinematic, tau):
            if kinematic and apply is not None:
                apply(self.model, data, value)
        self._place_target(tau, data)

    def _place_target(self, tau: np.ndarray, data: mujoco.MjData) -> None:
        """The target's display body (``target.body``) at the instance's target."""
        if self._target_mocap >= 0:
            position, rotation = self.task.target_of(tau)
            data.mocap_pos[self._target_mocap] = position
            mujoco.mju_mat2Quat(data.mocap_quat[self._target_mocap], rotation.reshape(-1))

    # -- simulation ---------------------------------------------------------------------
    def reset(self, tau: np.ndarray) -> np.ndarray:
        """Start posture at rest, task parameters applied, time zero. Returns tau as
        validated; TaskError before anything changes for a tau the task refuses."""
        tau = self.task.validate_tau(tau)
        mujoco.mj_resetData(self.model, self.data)
        self.apply_tau(tau)
        self.data.qpos[self.qpos_adr] = self.task.start_posture
        mujoco.mj_forward(self.model, self.data)
        return tau

    def inverse_dynamics(self, tau: np.ndarray, q: np.ndarray, qd: np.ndarray,
                         qdd: np.ndarray) -> np.ndarray:
        """Joint torques (T, n) that make the model, with task instance tau applied (e.g. a
        payload mass, in a private copy), move along q, qd, qdd (T, n) (`mujoco.mj_inverse`).
        tau must be valid already."""
        model = copy.copy(self.model)
        data = mujoco.MjData(model)
        self.apply_tau(tau, data, model)
        torque = np.empty_like(q)
        for k in range(len(q)):
            data.qpos[self.qpos_adr] = q[k]
            data.qvel[self.dof_adr] = qd[k]
            data.qacc[self.dof_adr] = qdd[k]
            mujoco.mj_inverse(model, data)
            torque[k] = data.qfrc_inverse[self.dof_adr]
        return torque

    def place(self, tau: np.ndarray) -> np.ndarray:
        """The task instance placed around the arm as it is (no teleport: a real arm's next
        episode starts where the last one ended), the bodies the reward observes back at their
        model pose at rest (the ball back in the hand, as a person puts it there); tau
        validated first. Returns it."""
        tau = self.apply_tau(self.task.validate_tau(tau))
        model, data = self.model, self.data
        for name in self.task.reward.observe:
            body = self.body(name)
            for j in range(model.body_jntadr[body],
                           model.body_jntadr[body] + model.body_jntnum[body]):
                size = {int(mujoco.mjtJoint.mjJNT_FREE): 7,
                        int(mujoco.mjtJoint.mjJNT_BALL): 4}.get(int(model.jnt_type[j]), 1)
                dofs = {7: 6, 4: 3}.get(size, 1)
                qpos, dof = model.jnt_qposadr[j], model.jnt_dofadr[j]
                data.qpos[qpos:qpos + size] = model.qpos0[qpos:qpos + size]
                data.qvel[dof:dof + dofs] = 0.0
        mujoco.mj_forward(model, data)
        return tau

    def take_state(self, other: 'ArmModel') -> None:
        """The state (time, joints, velocities) of another task's arm of the same robot."""
        self.data.time = other.data.time
        self.data.qpos[:] = other.data.qpos
        self.data.qvel[:] = other.data.qvel
        mujoco.mj_forward(self.model, self.data)

    def clip_torque(self, torque: np.ndarray) -> np.ndarray:
        return np.clip(torque, self.torque_low, self.torque_high)

    def step(self, torque: np.ndarray) -> np.ndarray:
        """One control period with the given joint torques, held over its `n_substeps`
        physics steps; returns the torques actually applied (clipped to the actuator
        limits)."""
        applied = self.clip_torque(np.asarray(torque, dtype=float))
        self.data.ctrl[self.actuator_ids] = applied
        mujoco.mj_step(self.model, self.data, nstep=self.n_substeps)
        return applied

    @property
    def q(self) -> np.ndarray:
        return self.data.qpos[self.qpos_adr].copy()

    @property
    def qd(self) -> np.ndarray:
        return self.data.qvel[self.dof_adr].copy()

    def end_effector_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Position (3,) and orientation quaternion (w, x, y, z) of the end-effector site in
        the current state. After `mj_step` the data's poses are still those of the state before
        the step, so this runs a kinematics pass first (it changes nothing the next step uses)."""
        mujoco.mj_kinematics(self.model, self.data)
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, self.data.site_xmat[self.ee_site])
        return self.data.site_xpos[self.ee_site].copy(), quat


    def set_body_pose(self, name: str, pose: np.ndarray) -> None:
        """Put body `name`, moved by a free joint (a thrown ball), at the pose (7,): position,
        quaternion (w, x, y, z) — the inverse of `body_pose` for a body whose frame is its
        free joint's (a replay of measured poses). ValueError for a body without one."""
        model, body = self.model, self.body(name)
        free = [j for j in range(model.body_jntadr[body],
                                 model.body_jntadr[body] + model.body_jntnum[body])
                if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
        if not free:
            raise ValueError(f'body {name!r} has no free joint to place it by')
        adr = model.jnt_qposadr[free[0]]
        self.data.qpos[adr:adr + 7] = pose

    def body_pose(self, body: int) -> np.ndarray:
        """The pose (7,) of body `body`'s frame in the current state: position, quaternion
        (w, x, y, z) — what a framepos and a framequat sensor of the body read
        (`psl_task.reward_geometry`). Runs a kinematics pass first, as `end_effector_pose`."""
        mujoco.mj_kinematics(self.model, self.data)
        return np.concatenate([self.data.xpos[body], self.data.xquat[body]])


def substeps(task: TaskDefinition, timestep: float) -> int:
    """Physics steps per control period, ``round(1 / (control_rate * timestep))``: the command
    is held over them. TaskError unless control_rate divides the physics rate 1 / timestep."""
    ratio = 1.0 / (task.control_rate * timestep)
    n = int(round(ratio))
    if n < 1 or abs(ratio - n) > 1e-9 * ratio:
        physics = 1.0 / timestep
        rates = ', '.join(f'{physics / k:g}' for k in range(1, 6))
        raise TaskError(f'{task.path}: control_rate {task.control_rate:g} Hz must divide the '
                        f'physics rate 1 / timestep = {physics:g} Hz of {task.model_path.name} '
                        f'a whole number of times (e.g. {rates} Hz): the command is held '
                        'over that many physics steps')
    return n


@functools.lru_cache(maxsize=32)
def joint_names_of(task: TaskDefinition) -> list[str]:
    """The task model's actuated joints, in actuator order (the order of every command)."""
    return ArmModel(task).joint_names
