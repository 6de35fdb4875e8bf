"""Batch mode: a whole population of policies rolled out in-process with `mujoco.rollout`.

The task's PD + feed-forward law (`psl_controller.pd_law.PDLaw`) is realised inside the model,
so no Python runs per physics step: every actuator becomes a general actuator with gain 1 and
the law's affine bias (`PDLaw.actuator_bias`), clipped to the law's torque limits
(``forcerange``), and the control of step k is the law's state-independent part
(`PDLaw.actuator_control`) of the policy's reference on the control grid. That is the graph's
controller law evaluated on the same state at the same step; only the order of the
floating-point additions differs. The task parameters that move things (mocap bodies) enter
through the control vector (``mjSTATE_MOCAP_POS``); those that change the model (body masses)
get a copy of the batch model per task instance. The reward's sensors
(`psl_sim.reward_geometry`) are part of the batch model, so the reward needs no Python loop
over steps either. Imports no ROS.
"""
from __future__ import annotations

import copy

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from psl_controller.pd_law import PDLaw, law_for
from psl_controller.policy import Reference
from psl_optimizer.reward import Reward
from psl_optimizer.rollouts import RolloutResult, Rollouts
from psl_sim.arm_model import ArmModel
from psl_sim.model_spec import task_spec
from psl_sim.reward_geometry import RewardGeometry
from psl_sim.task import TaskDefinition

FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
CONTROL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_MOCAP_POS


def batch_model(task: TaskDefinition, law: PDLaw, geometry: RewardGeometry) -> mujoco.MjModel:
    """The task's model with the law as its actuators and the reward's sensors."""
    spec = task_spec(task)
    bias = law.actuator_bias()
    for i, actuator in enumerate(spec.actuators):
        actuator.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        actuator.gainprm[0] = 1.0
        actuator.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        actuator.biasprm[0:3] = bias[i]
        actuator.forcerange = [law.torque_low[i], law.torque_high[i]]
        actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
    geometry.add_sensors(spec)
    return spec.compile()


class BatchRollouts(Rollouts):
    """Evaluate many thetas (and task instances) of one task at once.

    Args:
        task: the task.
        n_threads: MjData per thread of ``mujoco.rollout``.
        law: the PD + feed-forward law (default: the task's, `law_for`).
    """

    def __init__(self, task: TaskDefinition, n_threads: int = 2, law: PDLaw | None = None):
        super().__init__(task)
        self.arm = ArmModel(task)
        self.law = law or law_for(task)
        self.geometry = RewardGeometry(self.arm)
        self.reward = Reward(task, self.geometry)
        self.model = batch_model(task, self.law, self.geometry)
        self.datas = [mujoco.MjData(self.model) for _ in range(max(1, n_threads))]
        data = self.datas[0]
        mujoco.mj_resetData(self.model, data)
        data.qpos[self.arm.qpos_adr] = task.start_posture
        self.initial_state = np.empty(mujoco.mj_stateSize(self.model, FULL))
        mujoco.mj_getState(self.model, data, self.initial_state, FULL)
        self.mocap_template = data.mocap_pos.copy()          # (n_mocap, 3)

    def controls(self, references: list[Reference], taus: np.ndarray) -> np.ndarray:
        """(B, N+1, nu + 3 n_mocap): the law's control of each reference, then the mocap
        positions of each (validated) task instance."""
        ctrl = np.stack([self.law.actuator_control(r.q, r.qd, r.u_ffwd)
                         for r in references])                       # (B, N+1, nu)
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

    def run(self, thetas: np.ndarray, taus: np.ndarray) -> list[RolloutResult]:
        """Roll out thetas (B, F) on task instances taus (B, E) or one tau (E,)."""
        thetas, taus = self._inputs(thetas, taus)
        steps = np.array([self.task.num_steps_of(tau) for tau in taus])
        if np.all(steps == steps[0]):
            return self._run(thetas, taus)
        # instances of different durations: one mujoco.rollout per episode length
        results: list[RolloutResult | None] = [None] * len(thetas)
        for n in np.unique(steps):
            index = np.flatnonzero(steps == n)
            for i, result in zip(index, self._run(thetas[index], taus[index])):
                results[i] = result
        return results

    def _run(self, thetas: np.ndarray, taus: np.ndarray) -> list[RolloutResult]:
        """`run` on validated inputs whose episodes have the same length."""
        references = [self.policy.reference(theta, tau) for theta, tau in zip(thetas, taus)]
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
        # torque applied in step k: the law on state k (the actuator's force, clipped alike)
        u = self.law.torque(q, qd, q_ref, qd_ref, u_ffwd)
        torque = np.concatenate([np.zeros((len(thetas), 1, n)), u[:, :-1]], axis=1)
        evaluations = self.reward.evaluate(q, torque, q_ref, self.geometry.read(sensors), taus)
        return [RolloutResult(evaluation=evaluations[b], q=q[b], torque=torque[b],
                              reference=references[b]) for b in range(len(thetas))]
