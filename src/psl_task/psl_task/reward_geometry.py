"""What the reward measures on the arm, written once as MuJoCo sensors, read in both modes.

The geometric reward components need, per state of a rollout, the end-effector position and
the smallest signed distance between the arm's geoms and the obstacles' (``reward.arm_geoms``,
``reward.obstacle_geoms`` of the task), and the end-effector frame's orientation.
`RewardGeometry` defines them as sensors, appended after any sensors of the task's own model:
one ``geomdist`` per (arm geom, obstacle geom) pair, one ``framepos`` and one ``framequat`` of
the end-effector site, then one ``framepos`` and one ``framequat`` of each body of the world the
task observes (``reward.observe``: a ball, a puck; its frame, as `ArmModel.body_pose` gives it).
A replay moves the arm only: the observed bodies' poses come from the simulation (batch mode's
sensors) or, in graph mode, from their pose topics (`psl_optimizer.reward_evaluator_node`). Batch mode adds them to its rollout model
(`add_sensors`) and `read`s what ``mujoco.rollout`` recorded; graph mode gets the same sensors
evaluated on a kinematic replay of the measured joint angles (`replay`). Either way the
numbers come from the same sensors of the same model at the same joint angles.
Imports no ROS.
"""
from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from psl_task.arm_model import ArmModel
from psl_task.model_spec import task_spec

CUTOFF = 10.0    # m; distances beyond this read as the cutoff (no obstacle is that far)


@dataclasses.dataclass(frozen=True)
class Measurements:
    """The reward's geometry along a population of rollouts."""

    end_effector: np.ndarray        # (B, T, 3) end-effector position per state
    end_effector_quat: np.ndarray   # (B, T, 4) its orientation (w, x, y, z) per state
    distance: np.ndarray | None     # (B, T) smallest arm-obstacle signed distance; None when
                                    # the task names no obstacle
    world: dict = dataclasses.field(default_factory=dict)   # body -> (B, T, 7) pose per state
                                    # (position, quaternion w x y z) of the bodies the task
                                    # observes (reward.observe)


class RewardGeometry:
    """The reward sensors of one task's arm (see the module docstring)."""

    def __init__(self, arm: ArmModel):
        self.arm = arm
        reward = arm.task.reward
        self.pairs = [(arm.geom(g1), arm.geom(g2)) for g1 in arm.arm_geoms
                      for g2 in reward.obstacle_geoms]        # (arm geom id, obstacle geom id)
        self.first = arm.model.nsensordata      # ours follow the model's own sensors
        self.observed = {name: arm.body(name) for name in reward.observe}   # TaskError: none
        spec = task_spec(arm.task)
        self.add_sensors(spec)
        self.model = spec.compile()             # the arm's model with the reward sensors
        self._data = mujoco.MjData(self.model)

    def add_sensors(self, spec: mujoco.MjSpec) -> None:
        """Append the reward sensors to a spec of the task's model (after its own sensors)."""
        model = self.arm.model
        for g1, g2 in self.pairs:
            sensor = spec.add_sensor()
            sensor.type = mujoco.mjtSensor.mjSENS_GEOMDIST
            sensor.objtype = sensor.reftype = mujoco.mjtObj.mjOBJ_GEOM
            sensor.objname, sensor.refname = model.geom(g1).name, model.geom(g2).name
            sensor.cutoff = CUTOFF
        frames = [(mujoco.mjtObj.mjOBJ_SITE, self.arm.task.end_effector_site)]
        frames += [(mujoco.mjtObj.mjOBJ_XBODY, name) for name in self.observed]
        for objtype, name in frames:
            for kind in (mujoco.mjtSensor.mjSENS_FRAMEPOS, mujoco.mjtSensor.mjSENS_FRAMEQUAT):
                sensor = spec.add_sensor()
                sensor.type = kind
                sensor.objtype = objtype
                sensor.objname = name

    def read(self, sensordata: np.ndarray) -> Measurements:
        """The measurements in sensor data (B, T, nsensordata) of a model with the sensors."""
        first, n_pairs = self.first, len(self.pairs)
        distance = None
        for pair in range(first, first + n_pairs):     # the nearest pair (exact, as a min)
            column = sensordata[:, :, pair]
            distance = column.copy() if distance is None else np.minimum(distance, column)
        ee = first + n_pairs
        world = {name: sensordata[:, :, ee + 7 * (i + 1):ee + 7 * (i + 2)]
                 for i, name in enumerate(self.observed)}
        return Measurements(end_effector=sensordata[:, :, ee:ee + 3],
                            end_effector_quat=sensordata[:, :, ee + 3:ee + 7],
                            distance=distance, world=world)

    def replay(self, q: np.ndarray, taus: np.ndarray, world: dict | None = None
               ) -> Measurements:
        """The sensors on a kinematic replay: joint angles q (B, T, n) of rollouts on the task
        instances taus (B, E). Only the task parameters that move things (mocap bodies) are
        applied; the replay has its own data and changes nothing of the arm's simulation. The
        observed bodies' poses are not the replay's: `world` ({body: (B, T, 7)}, measured; the
        task's observed bodies exactly), or None: none (a component that reads them fails).

        Raises:
            ValueError: q not (B, T, n) or not finite; TaskError: a tau the task refuses.
        """
        q = np.asarray(q, dtype=float)
        taus = np.atleast_2d(np.asarray(taus, dtype=float))
        n = len(self.arm.joint_names)
        if q.ndim != 3 or q.shape[2] != n or len(taus) != len(q):
            raise ValueError(f'q {q.shape} must be (B, T, {n}) with one tau per rollout, got '
                             f'{len(taus)}')
        if not np.all(np.isfinite(q)):
            raise ValueError('q must be finite')
        world = {} if world is None else self.check_world(world, q.shape[:2])
        model, data = self.model, self._data
        sensordata = np.empty(q.shape[:2] + (model.nsensordata,))
        for b, tau in enumerate(taus):
            self.arm.move_bodies(self.arm.task.validate_tau(tau), data)
            for k, qk in enumerate(q[b]):
                data.qpos[self.arm.qpos_adr] = qk
                mujoco.mj_fwdPosition(model, data)
                mujoco.mj_sensorPos(model, data)
                sensordata[b, k] = data.sensordata
        replayed = self.read(sensordata)
        return Measurements(end_effector=replayed.end_effector,
                            end_effector_quat=replayed.end_effector_quat,
                            distance=replayed.distance, world=world)

    def check_world(self, world: dict, shape: tuple[int, int]) -> dict:
        """The measured poses of the observed bodies, {body: (B, T, 7)} (`shape` = (B, T)),
        as arrays; ValueError for a body missing or not observed, a wrong shape, a value that
        is not finite."""
        if set(world) != set(self.observed):
            raise ValueError(f'the poses of {sorted(world)} were measured, the task observes '
                             f'{sorted(self.observed)}')
        out = {}
        for name, poses in world.items():
            poses = np.asarray(poses, dtype=float)
            if poses.shape != tuple(shape) + (7,) or not np.all(np.isfinite(poses)):
                raise ValueError(f'the poses of {name!r} must be {tuple(shape) + (7,)} finite '
                                 f'values, got shape {poses.shape}')
            out[name] = poses
        return out

    def end_effector_at(self, q: np.ndarray) -> np.ndarray:
        """End-effector position (3,) at joint angles q (n,) (the task's default instance)."""
        q = np.asarray(q, dtype=float)[None, None, :]
        return self.replay(q, self.arm.task.tau_default[None]).end_effector[0, 0].copy()
