"""Batch mode: a whole population of policies rolled out in-process with `mujoco.rollout`.

The task's PD + feed-forward law (`psl_controller.pd_law.PDLaw`) is realised inside the model,
so no Python runs per physics step: every actuator becomes a general actuator with gain 1 and
the law's affine bias (`PDLaw.actuator_bias`), clipped to the law's torque limits
(``forcerange``), and the control of step k is the law's state-independent part
(`PDLaw.actuator_control`) of the policy's reference on the control grid. That is the graph's
controller law evaluated on the same state at the same step; only the order of the
floating-point additions differs. The task parameters that move things (mocap bodies) enter
through the control vector (``mjSTATE_MOCAP_POS``); those that change the model (body masses)
get a copy of the batch model per task instance. A task whose control period spans several
physics steps (``n_substeps``) holds the law's torque over them, as the graph does: there the
law runs in Python once per control period (`BatchRollouts._run_held`). The reward's sensors
(`psl_task.reward_geometry`) are part of the batch model, so the reward needs no Python loop
over steps either. Every candidate's reference passes the task's safety check
(`psl_task.safety_check`) first; a refused one is not simulated and gets the penalty. Imports no
ROS.

Sim to real (``model_error``, `psl_task.model_error.ModelError`): the simulated robot differs
from the task's model (heavier, with joint friction and damping), as a real robot does. The
error is applied to the simulated models only (the batch model after compile, and the held
model); everything the skill computes from a model — the safety check, the inverse-dynamics
feed-forward, the reward geometry — keeps the task's nominal model, as it must on a real robot.
The identity error (the default) leaves every result bit-identical.

A noisy robot (``measurement_noise``, `MeasurementNoise`): the joint angles and velocities the
controller and the reward see are the true ones plus Gaussian noise, drawn per rollout from a
generator seeded by the noise's seed, the rollout itself (its reference and task instance:
`rollout_key`) and how often this object rolled that out before, so a session resumed from a
checkpoint draws the noise the uninterrupted one drew, and a repeated rollout new noise. The
PD law acts on the measurement; in the actuators the law
is ``ctrl + b_1 q + b_2 qd`` with the true state, so a noise sample n_q, n_qd of step k enters
exactly as the extra control ``-(Kp n_q + Kd n_qd)`` in that step's ctrl (before the force
range clips the sum, as the law clips). The reward is computed on the measured angles, its
geometry from their kinematic replay (as the graph's evaluator scores joint states); the results
carry the measured angles. No noise (the default) leaves every result bit-identical.
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import math
import time
import weakref

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from psl_controller.pd_law import PDLaw, law_for
from psl_controller.policy import Reference
from psl_optimizer.reward import Reward
from psl_optimizer.rollouts import RolloutResult, Rollouts, aborted_result, refused_result
from psl_task.arm_model import ArmModel
from psl_task.model_error import ModelError
from psl_task.key_values import parse_key_values
from psl_task.model_spec import task_spec
from psl_task.reward_geometry import RewardGeometry
from psl_task.safety_check import SafetyCheck, tracking_abort
from psl_task.task import TaskDefinition

FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
CONTROL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_MOCAP_POS


@dataclasses.dataclass(frozen=True)
class MeasurementNoise:
    """Gaussian noise on the measured joint angles and velocities of a noisy robot."""

    position: float = 0.0        # [rad] standard deviation on every measured joint angle
    velocity: float = 0.0        # [rad/s] standard deviation on every measured joint velocity
    seed: int = 0                # of the generator every draw comes from, in rollout order

    def __post_init__(self):
        for name in ('position', 'velocity'):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0.0:
                raise ValueError(f'measurement noise {name} must be a finite number >= 0, '
                                 f'not {value!r}')
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f'measurement noise seed must be a whole number >= 0, not '
                             f'{self.seed!r}')

    @property
    def is_off(self) -> bool:
        return self.position == 0.0 and self.velocity == 0.0

    def sample(self, key: int, occurrence: int, shape: tuple) -> tuple[np.ndarray, np.ndarray]:
        """n_q, n_qd (shape each, (N+1, n)) of the `occurrence`-th rollout (0: the first) of
        the rollout `key` (`rollout_key`)."""
        rng = np.random.default_rng([self.seed, key, occurrence])
        return rng.normal(0.0, self.position, shape), rng.normal(0.0, self.velocity, shape)

    @classmethod
    def parse(cls, text: str) -> 'MeasurementNoise':
        """From ``"position=0.001,velocity=0.01,seed=0"`` (any subset; empty: none).
        ValueError naming what is wrong."""
        return parse_key_values(cls, text, 'measurement noise')


def rollout_key(reference: Reference, tau: np.ndarray) -> int:
    """A rollout's identity for its noise: a 64-bit digest of its reference (q, qd, u_ffwd)
    and task instance."""
    digest = hashlib.blake2b(digest_size=8)
    for array in (reference.q, reference.qd, reference.u_ffwd, tau):
        digest.update(np.ascontiguousarray(array, dtype=float).tobytes())
    return int.from_bytes(digest.digest(), 'little')


def stacked(references: list[Reference]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q, qd and u_ffwd of references of one episode length, each stacked (B, N+1, n)."""
    return tuple(np.stack([getattr(r, field) for r in references])
                 for field in ('q', 'qd', 'u_ffwd'))


def batch_model(task: TaskDefinition, law: PDLaw, geometry: RewardGeometry,
                joint_of_actuator: np.ndarray,
                model_error: ModelError = ModelError()) -> mujoco.MjModel:
    """The task's model with the law as its actuators and the reward's sensors; actuator a
    drives joint ``joint_of_actuator[a]`` of the law (command order); the robot made to differ
    from the model by `model_error` (after compile; the identity: untouched)."""
    spec = task_spec(task)
    bias = law.actuator_bias()
    for actuator, i in zip(spec.actuators, joint_of_actuator):
        actuator.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        actuator.gainprm[0] = 1.0
        actuator.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        actuator.biasprm[0:3] = bias[i]
        actuator.forcerange = [law.torque_low[i], law.torque_high[i]]
        actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
    geometry.add_sensors(spec)
    model = spec.compile()
    model_error.apply(model, geometry.arm.joint_ids)
    return model


class BatchRollouts(Rollouts):
    """Evaluate many thetas (and task instances) of one task at once.

    Args:
        task: the task.
        n_threads: MjData per thread of ``mujoco.rollout``.
        law: the PD + feed-forward law (default: the task's, `law_for`).
        model_error: how the simulated robot differs from the task's model (sim to real; see
            the module docstring); the default is none.
        measurement_noise: the noise on the measured joint states (`MeasurementNoise`; see
            the module docstring); the default is none.
    """

    def __init__(self, task: TaskDefinition, n_threads: int = 2, law: PDLaw | None = None,
                 model_error: ModelError = ModelError(),
                 measurement_noise: MeasurementNoise = MeasurementNoise()):
        super().__init__(task)
        self.model_error = model_error
        self.measurement_noise = measurement_noise
        self._occurrences: dict[int, int] = {}     # rollout_key -> rollouts so far
        self.arm = ArmModel(task)
        self.law = law or law_for(task)
        self.geometry = RewardGeometry(self.arm)
        self.reward = Reward(task, self.geometry)
        self.safety = SafetyCheck(self.arm)
        # the law is in command order (ArmModel.joint_names); the actuators in model order
        self.joint_of_actuator = np.argsort(self.arm.actuator_ids)
        self.model = batch_model(task, self.law, self.geometry, self.joint_of_actuator,
                                 model_error)
        self.datas = [mujoco.MjData(self.model) for _ in range(max(1, n_threads))]
        # a thread pool of its own, kept from call to call (ended with this object)
        self.pool = mj_rollout.Rollout(nthread=len(self.datas) if len(self.datas) > 1 else 0)
        weakref.finalize(self, self.pool.close)
        self.simulation_seconds = 0.0      # wall time spent simulating, over all calls
        self._scratch = data = mujoco.MjData(self.model)   # for this thread, beside the physics
        mujoco.mj_resetData(self.model, data)
        data.qpos[self.arm.qpos_adr] = task.start_posture
        self.initial_state = np.empty(mujoco.mj_stateSize(self.model, FULL))
        mujoco.mj_getState(self.model, data, self.initial_state, FULL)
        self.mocap_template = data.mocap_pos.copy()          # (n_mocap, 3)

    def controls(self, q_ref: np.ndarray, qd_ref: np.ndarray, u_ffwd: np.ndarray,
                 taus: np.ndarray) -> np.ndarray:
        """(B, N+1, nu + 3 n_mocap): the law's control of the references q_ref, qd_ref, u_ffwd
        (B, N+1, n), then the mocap positions of each (validated) task instance."""
        ctrl = self.law.actuator_control(q_ref, qd_ref, u_ffwd)[..., self.joint_of_actuator]
        mocap = np.empty((len(taus), self.model.nmocap, 3))
        data = self._scratch
        for b, tau in enumerate(taus):
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
                self.arm.apply_tau(tau, self._scratch, model)
                copies[tuple(tau)] = model
        return [copies[tuple(tau)] for tau in taus]

    @functools.cached_property
    def held_model(self) -> mujoco.MjModel:
        """For a task with substeps: the task's model with its plain motors (the law runs in
        Python, once per control period, as the controller node does) and the reward's
        sensors; the robot made to differ by `model_error`."""
        spec = task_spec(self.task)
        self.geometry.add_sensors(spec)
        model = spec.compile()
        self.model_error.apply(model, self.arm.joint_ids)
        return model

    def run(self, thetas: np.ndarray, taus: np.ndarray) -> list[RolloutResult]:
        """Roll out thetas (B, F) on task instances taus (B, E) or one tau (E,)."""
        thetas, taus = self._inputs(thetas, taus)
        references = self.policy.references(thetas, taus)
        results: list[RolloutResult | None] = [None] * len(thetas)
        lengths = np.array([len(r.t) for r in references])
        # instances of different durations: one population per episode length
        for length in np.unique(lengths):
            index = np.flatnonzero(lengths == length)
            group = [references[i] for i in index]
            arrays = stacked(group)                                  # each (B, N+1, n)
            verdicts = self.safety.screen(taus[index], *arrays)
            for i, verdict in zip(index, verdicts):
                if not verdict.safe:         # not executed: the penalty and the reason
                    results[i] = refused_result(verdict.reason,
                                                verdict.penalty(self.task.safety.penalty),
                                                verdict.violation)
            safe = np.array([verdict.safe for verdict in verdicts])
            if safe.any():
                chosen = [r for r, ok in zip(group, safe) if ok]
                for i, result in zip(index[safe], self._run(
                        chosen, taus[index[safe]], *(a[safe] for a in arrays))):
                    results[i] = self._bounded(result)
        return self._count(results)

    def _bounded(self, result: RolloutResult) -> RolloutResult:
        """The result, or the penalty of an episode the controller would have aborted
        (`psl_task.safety_check.tracking_abort`: its tracking error passed the task's
        ``safety.max_tracking_error``)."""
        verdict = tracking_abort(result.q, result.q_ref, self.task.safety.max_tracking_error,
                                 self.arm.joint_names, self.task.control_period)
        if verdict.safe:
            return result
        return aborted_result(verdict.reason, verdict.penalty(self.task.safety.penalty),
                              verdict.violation)

    def _run(self, references: list[Reference], taus: np.ndarray, q_ref: np.ndarray,
             qd_ref: np.ndarray, u_ffwd: np.ndarray) -> list[RolloutResult]:
        """The rollouts of checked references whose episodes have the same length, their
        arrays stacked (B, N+1, n)."""
        if self.arm.n_substeps > 1:
            return self._run_held(references, taus, q_ref)
        control = self.controls(q_ref, qd_ref, u_ffwd, taus)
        noise = self._noise(references, taus)
        if noise is not None:     # the law on the measurement: -(Kp n_q + Kd n_qd) more ctrl
            extra = -(self.law.kp * noise[0] + self.law.kd * noise[1])       # (B, N+1, n)
            control[..., :self.model.nu] += extra[..., self.joint_of_actuator]
        state, sensors = self._simulate(self.models(taus), control)
        return self._results(references, taus, q_ref, qd_ref, u_ffwd, state, sensors, noise)

    def _noise(self, references: list[Reference], taus: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray] | None:
        """Measurement noise n_q, n_qd, each (B, N+1, n), of these rollouts (None: a robot
        without noise), each rollout's from `MeasurementNoise.sample`."""
        noise = self.measurement_noise
        if noise.is_off:
            return None
        n_q, n_qd = [], []
        for reference, tau in zip(references, taus):
            key = rollout_key(reference, tau)
            occurrence = self._occurrences.get(key, 0)
            self._occurrences[key] = occurrence + 1
            a, b = noise.sample(key, occurrence, reference.q.shape)
            n_q.append(a)
            n_qd.append(b)
        return np.array(n_q), np.array(n_qd)

    def _simulate(self, models: mujoco.MjModel | list[mujoco.MjModel],
                  control: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States and sensors (B, N+1, ...) of `mujoco.rollout` on the controls (its threads
        use `datas`). N+1 steps: the sensors of step k see state k, so step N gives state N's
        sensors; the state after that extra step is not used."""
        start = time.perf_counter()
        try:
            return self.pool.rollout(models, self.datas, self.initial_state[None], control,
                                     control_spec=CONTROL)
        finally:
            self.simulation_seconds += time.perf_counter() - start

    def _results(self, references: list[Reference], taus: np.ndarray, q_ref: np.ndarray,
                 qd_ref: np.ndarray, u_ffwd: np.ndarray, state: np.ndarray,
                 sensors: np.ndarray, noise: tuple[np.ndarray, np.ndarray] | None = None
                 ) -> list[RolloutResult]:
        """The measured rollouts and their rewards from `_simulate`'s states and sensors
        (with measurement noise: on the measured states, the geometry replayed)."""
        n, count = len(self.arm.joint_names), len(references)
        nq = self.model.nq
        whole = np.concatenate([np.broadcast_to(self.initial_state[1:1 + nq], (count, 1, nq)),
                                state[:, :-1, 1:1 + nq]], axis=1)    # S_0..S_N, every joint
        qpos = state[:, :, 1 + self.arm.qpos_adr]                    # states 1..N+1
        qvel = state[:, :, 1 + self.model.nq + self.arm.dof_adr]
        q = np.concatenate([np.broadcast_to(self.task.start_posture, (count, 1, n)),
                            qpos[:, :-1]], axis=1)                   # S_0..S_N
        qd = np.concatenate([np.zeros((count, 1, n)), qvel[:, :-1]], axis=1)
        if noise is not None:                       # what the controller and reward measure
            q, qd = q + noise[0], qd + noise[1]
        # torque applied in step k: the law on state k (the actuator's force, clipped alike)
        u = self.law.torque(q, qd, q_ref, qd_ref, u_ffwd)
        torque = np.concatenate([np.zeros((count, 1, n)), u[:, :-1]], axis=1)
        evaluations, world = self._evaluate(q, torque, q_ref, taus, sensors, noise is not None)
        return [RolloutResult(evaluation=evaluations[b], q=q[b], torque=torque[b],
                              reference=references[b],
                              world={k: v[b] for k, v in world.items()}, qpos=whole[b])
                for b in range(len(references))]

    def _evaluate(self, q: np.ndarray, torque: np.ndarray, q_ref: np.ndarray,
                  taus: np.ndarray, sensors: np.ndarray, noisy: bool):
        """The rewards of the rollouts from their sensors, and the observed bodies' poses
        ({body: (B, T, 7)}); with measurement noise, the arm's geometry replayed from the
        measured angles (as graph mode scores joint states), the bodies as the sensors saw
        them."""
        measured = self.geometry.read(sensors)
        if noisy:
            return (self.reward.evaluate_replayed(q, torque, q_ref, taus, world=measured.world),
                    measured.world)
        return self.reward.evaluate(q, torque, q_ref, measured, taus), measured.world

    def _run_held(self, references: list[Reference], taus: np.ndarray,
                  q_ref: np.ndarray) -> list[RolloutResult]:
        """A task whose control period spans several physics steps: the law's torque of state
        k is held over the period's `ArmModel.n_substeps` steps, as in the graph (the
        simulator's `ArmModel.step`). The law in the actuator would act on every physics
        step, so here each rollout steps its own MjData in Python, one control period at a
        time, with the law evaluated on the state at the period's start."""
        arm, law, n_sub = self.arm, self.law, self.arm.n_substeps
        n_steps, n = references[0].q.shape[0], len(arm.joint_names)
        q = np.empty((len(taus), n_steps, n))
        qd = np.empty_like(q)
        torque = np.zeros_like(q)
        sensors = np.empty((len(taus), n_steps, self.held_model.nsensordata))
        whole = np.empty((len(taus), n_steps, self.held_model.nq))
        noise = self._noise(references, taus)
        start = time.perf_counter()          # the stepping with its law counts as simulation
        for b, (reference, tau) in enumerate(zip(references, taus)):
            model = self.held_model
            if arm.changes_model:               # a task parameter changes the model (a mass)
                model = copy.copy(self.held_model)
                arm.apply_tau(tau, mujoco.MjData(model), model)
            data = mujoco.MjData(model)
            data.qpos[arm.qpos_adr] = self.task.start_posture
            arm.move_bodies(tau, data)
            mujoco.mj_forward(model, data)
            for k in range(n_steps):
                q[b, k], qd[b, k] = data.qpos[arm.qpos_adr], data.qvel[arm.dof_adr]
                whole[b, k] = data.qpos
                if noise is not None:                 # the law on the measurement
                    q[b, k] += noise[0][b, k]
                    qd[b, k] += noise[1][b, k]
                u = law.torque(q[b, k], qd[b, k], reference.q[k], reference.qd[k],
                               reference.u_ffwd[k])
                data.ctrl[arm.actuator_ids] = u
                mujoco.mj_step(model, data)              # the sensors of state k
                sensors[b, k] = data.sensordata
                mujoco.mj_step(model, data, nstep=n_sub - 1)
                if k + 1 < n_steps:
                    torque[b, k + 1] = u
        self.simulation_seconds += time.perf_counter() - start
        evaluations, world = self._evaluate(q, torque, q_ref, taus, sensors, noise is not None)
        return [RolloutResult(evaluation=evaluations[b], q=q[b], torque=torque[b],
                              reference=references[b],
                              world={k: v[b] for k, v in world.items()}, qpos=whole[b])
                for b in range(len(taus))]
