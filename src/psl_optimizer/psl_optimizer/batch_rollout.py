"""Batch mode: a whole population of policies rolled out in-process with `mujoco.rollout`.

The PD + feed-forward law is realised inside the model, so no Python runs per physics step:
every actuator becomes a general actuator with ``force = ctrl - Kp q - Kd qd`` (gain 1, affine
bias ``[0, -Kp, -Kd]``) clipped to the model's torque limits (``forcerange``), and the control
of step k is ``ctrl_k = Kp q_ref(t_k) + Kd qd_ref(t_k) + u_ffwd(t_k)`` from the policy's reference
on the control grid. That is the graph's controller law evaluated on the same state at the same
step; only the order of the floating-point additions differs. The task parameters that move
things (mocap bodies) enter through the control vector (``mjSTATE_MOCAP_POS``); those that
change the model (body masses) get a copy of the batch model per task instance. The obstacle
distances and the end-effector position are MuJoCo sensors appended to the batch model (after
any sensors of the task's own model), so the reward needs no Python loop over steps either.
Imports no ROS.
"""
from __future__ import annotations

import copy
import dataclasses

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from psl_controller.policy import Reference, policy_for
from psl_optimizer.reward import RewardResult, evaluate_population
from psl_sim.arm_model import ArmModel
from psl_sim.task import TaskDefinition

FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
CONTROL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_MOCAP_POS


@dataclasses.dataclass(frozen=True)
class BatchResult:
    """One rollout of a population member: the arrays the graph's evaluator sees."""

    q: np.ndarray          # (N+1, n) measured joint angles, S_0..S_N
    torque: np.ndarray     # (N+1, n) torque applied in the step before each state (row 0: 0)
    q_ref: np.ndarray      # (N+1, n) commanded joint angles
    evaluation: RewardResult


def batch_model(task: TaskDefinition, arm: ArmModel) -> mujoco.MjModel:
    """The task's model with PD actuators (gains from the task) and reward sensors."""
    spec = mujoco.MjSpec.from_file(str(task.model_path))
    for i, actuator in enumerate(spec.actuators):
        actuator.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        actuator.gainprm[0] = 1.0
        actuator.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        actuator.biasprm[0:3] = [0.0, -task.kp[i], -task.kd[i]]
        actuator.forcerange = [arm.torque_low[i], arm.torque_high[i]]
        actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
    model = arm.model
    for g1 in arm.arm_geoms:
        for g2 in arm.obstacle_geoms:
            sensor = spec.add_sensor()
            sensor.type = mujoco.mjtSensor.mjSENS_GEOMDIST
            sensor.objtype = sensor.reftype = mujoco.mjtObj.mjOBJ_GEOM
            sensor.objname, sensor.refname = model.geom(g1).name, model.geom(g2).name
            sensor.cutoff = 10.0
    sensor = spec.add_sensor()
    sensor.type = mujoco.mjtSensor.mjSENS_FRAMEPOS
    sensor.objtype = mujoco.mjtObj.mjOBJ_SITE
    sensor.objname = task.end_effector_site
    return spec.compile()


class BatchRollout:
    """Evaluate many thetas (and task instances) of one task at once."""

    def __init__(self, task: TaskDefinition, n_threads: int = 2):
        self.task = task
        self.arm = ArmModel(task)
        self.policy = policy_for(task)
        self.model = batch_model(task, self.arm)
        self.datas = [mujoco.MjData(self.model) for _ in range(max(1, n_threads))]
        self.n_pairs = len(self.arm.arm_geoms) * len(self.arm.obstacle_geoms)
        self.sensor_start = self.arm.model.nsensordata   # ours follow the model's own sensors
        self.n_steps = task.num_steps
        data = self.datas[0]
        mujoco.mj_resetData(self.model, data)
        data.qpos[self.arm.qpos_adr] = task.start_posture
        self.initial_state = np.empty(mujoco.mj_stateSize(self.model, FULL))
        mujoco.mj_getState(self.model, data, self.initial_state, FULL)
        self.mocap_template = data.mocap_pos.copy()          # (n_mocap, 3)

    def controls(self, references: list[Reference], taus: np.ndarray) -> np.ndarray:
        """(B, N+1, nu + 3 n_mocap): ctrl_k = Kp q_ref + Kd qd_ref + u_ffwd, then mocap."""
        kp, kd = self.task.kp, self.task.kd
        ctrl = np.stack([kp * r.q + kd * r.qd + r.u_ffwd for r in references])   # (B, N+1, nu)
        mocap = np.empty((len(taus), self.model.nmocap, 3))
        for b, tau in enumerate(taus):
            data = self.datas[0]
            data.mocap_pos[:] = self.mocap_template
            self.arm.move_bodies(tau, data)
            mocap[b] = data.mocap_pos
        n_mocap = 3 * self.model.nmocap
        mocap = np.broadcast_to(mocap.reshape(len(taus), 1, n_mocap),
                                (len(taus), ctrl.shape[1], n_mocap))
        return np.concatenate([ctrl, mocap], axis=2)

    def models(self, taus: np.ndarray) -> mujoco.MjModel | list[mujoco.MjModel]:
        """The batch model, or one copy per rollout when task parameters change the model
        (e.g. a payload mass); rollouts of the same instance share a copy."""
        if not self.arm.changes_model:
            return self.model
        copies: dict[tuple, mujoco.MjModel] = {}
        for tau in taus:
            if tuple(tau) not in copies:
                model = copy.copy(self.model)
                self.arm.apply_tau(tau, self.datas[0], model)
                copies[tuple(tau)] = model
        return [copies[tuple(tau)] for tau in taus]

    def run(self, thetas: np.ndarray, taus: np.ndarray) -> list[BatchResult]:
        """Roll out thetas (B, F) on task instances taus (B, E) or one tau (E,)."""
        thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
        taus = np.asarray(taus, dtype=float)
        taus = np.broadcast_to(taus, (len(thetas), taus.shape[-1])) if taus.ndim == 1 else taus
        taus = np.array([self.task.validate_tau(t) for t in taus])
        references = [self.policy.reference(theta) for theta in thetas]
        control = self.controls(references, taus)
        # N+1 steps: the sensors of step k see state k, so step N gives state N's sensors;
        # the state after that extra step is not used.
        state, sensors = mj_rollout.rollout(self.models(taus), self.datas,
                                            self.initial_state[None], control,
                                            control_spec=CONTROL)
        n = len(self.arm.joint_names)
        qpos = state[:, :, 1 + self.arm.qpos_adr]                    # states 1..N+1
        qvel = state[:, :, 1 + self.model.nq + self.arm.dof_adr]
        q = np.concatenate([np.broadcast_to(self.task.start_posture, (len(thetas), 1, n)),
                            qpos[:, :-1]], axis=1)                   # S_0..S_N
        qd = np.concatenate([np.zeros((len(thetas), 1, n)), qvel[:, :-1]], axis=1)
        q_ref = np.stack([r.q for r in references])                 # (B, N+1, n)
        qd_ref = np.stack([r.qd for r in references])
        u_ffwd = np.stack([r.u_ffwd for r in references])
        # torque applied in step k: the same law, clipped like the actuator's forcerange
        u = np.clip(self.task.kp * (q_ref - q) + self.task.kd * (qd_ref - qd) + u_ffwd,
                    self.arm.torque_low, self.arm.torque_high)
        torque = np.concatenate([np.zeros((len(thetas), 1, n)), u[:, :-1]], axis=1)
        start, n_pairs = self.sensor_start, self.n_pairs
        distance = sensors[:, :, start:start + n_pairs].min(axis=2) if n_pairs else None
        ee_final = sensors[:, -1, start + n_pairs:start + n_pairs + 3]
        evaluations = evaluate_population(self.arm, q, torque, q_ref, ee_final, distance)
        return [BatchResult(q=q[b], torque=torque[b], q_ref=q_ref[b], evaluation=evaluations[b])
                for b in range(len(thetas))]
