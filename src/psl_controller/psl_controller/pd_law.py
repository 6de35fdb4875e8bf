"""The PD + feed-forward joint torque law with torque limits (DESIGN.md section 4), written once.

    u = clip(Kp (q_ref - q) + Kd (qd_ref - qd) + u_ffwd,  torque_low, torque_high)

`PDLaw` holds the gains and limits (validated once, when it is made) and evaluates the law on
any leading dimensions (one state, a trajectory, a population of trajectories). Everything
that needs the law derives from it: the controller node computes `torque` on each state; batch
mode realises the same law inside MuJoCo as a general actuator, force =
clip(ctrl + b_1 q + b_2 qd), with ``ctrl = actuator_control(...)`` and ``[0, b_1, b_2] =
actuator_bias()`` (an affine split of the same expression); ILC takes the feedback part of an
applied torque with `feedback`. `law_for` gives a task's law. Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np

from psl_task.arm_model import ArmModel
from psl_task.task import TaskDefinition


@dataclasses.dataclass(frozen=True, eq=False)
class PDLaw:
    """Gains and torque limits of the law, per joint (actuator order).

    Raises:
        ValueError: arrays of different lengths or not finite, negative gains, or a lower
            torque limit above the upper one.
    """

    kp: np.ndarray                  # (n,) N m / rad, >= 0
    kd: np.ndarray                  # (n,) N m s / rad, >= 0
    torque_low: np.ndarray          # (n,) N m
    torque_high: np.ndarray         # (n,) N m, >= torque_low

    def __post_init__(self):
        arrays = {}
        for field in dataclasses.fields(self):
            value = np.array(getattr(self, field.name), dtype=float)
            if value.ndim != 1 or not np.all(np.isfinite(value)):
                raise ValueError(f'{field.name} must be a vector of finite numbers, got {value}')
            value.setflags(write=False)
            arrays[field.name] = value
        sizes = {name: value.size for name, value in arrays.items()}
        if len(set(sizes.values())) != 1:
            raise ValueError(f'the law needs one value per joint in each of {sizes}')
        for name in ('kp', 'kd'):
            if np.any(arrays[name] < 0.0):
                raise ValueError(f'{name} must be >= 0, got {arrays[name]}')
        if np.any(arrays['torque_low'] > arrays['torque_high']):
            raise ValueError(f'torque_low {arrays["torque_low"]} above torque_high '
                             f'{arrays["torque_high"]}')
        for name, value in arrays.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, '_tiles', {})

    @classmethod
    def symmetric(cls, kp, kd, torque_limit) -> 'PDLaw':
        """A law clipping to [-torque_limit, torque_limit]; scalars apply to every joint of
        kp's length."""
        kp = np.atleast_1d(np.asarray(kp, dtype=float))
        n = kp.size
        kd, limit = (np.broadcast_to(np.asarray(v, dtype=float), (n,)) for v in (kd, torque_limit))
        if np.any(limit < 0.0):
            raise ValueError(f'torque_limit must be >= 0, got {limit}')
        return cls(kp, kd, -limit, limit)

    @property
    def n_joints(self) -> int:
        return self.kp.size

    def torque(self, q, qd, q_ref, qd_ref, u_ffwd) -> np.ndarray:
        """The law: u = clip(Kp (q_ref - q) + Kd (qd_ref - qd) + u_ffwd), shape (..., n).

        Inputs are not checked (this runs on every control step): shapes (..., n) that
        broadcast, finite values; a message boundary validates them first."""
        error, error_d = np.subtract(q_ref, q), np.subtract(qd_ref, qd)
        kp, kd, low, high = self._per_element(error, error_d, u_ffwd)
        u = kp * error + kd * error_d + u_ffwd
        return np.clip(u, low, high)

    def actuator_control(self, q_ref, qd_ref, u_ffwd) -> np.ndarray:
        """The state-independent part of the law, Kp q_ref + Kd qd_ref + u_ffwd (..., n): the
        control signal of a MuJoCo general actuator realising it (see `actuator_bias`)."""
        q_ref, qd_ref = np.asarray(q_ref), np.asarray(qd_ref)
        kp, kd, _, _ = self._per_element(q_ref, qd_ref, u_ffwd)
        return kp * q_ref + kd * qd_ref + u_ffwd

    def _per_element(self, a: np.ndarray, b: np.ndarray, c) -> tuple[np.ndarray, ...]:
        """kp, kd, torque_low, torque_high laid out to the shape of arrays a, b and c when
        they share one of two or more dimensions (a trajectory, a population): numpy multiplies
        full arrays several times faster than it broadcasts a short joint axis, and the values,
        so the results, are the same. Otherwise (one state, mixed shapes) the vectors
        themselves. A few shapes are kept."""
        shape = a.shape
        if len(shape) < 2 or b.shape != shape or np.shape(c) != shape:
            return self.kp, self.kd, self.torque_low, self.torque_high
        tiles = self._tiles
        if shape not in tiles:
            if len(tiles) >= 8:
                tiles.clear()
            tiles[shape] = tuple(np.broadcast_to(v, shape).copy() for v in
                                 (self.kp, self.kd, self.torque_low, self.torque_high))
        return tiles[shape]

    def actuator_bias(self) -> np.ndarray:
        """Affine bias parameters [b_0, b_1, b_2] = [0, -Kp, -Kd] per joint (n, 3): with gain 1
        and force range [torque_low, torque_high], a general actuator's force
        clip(ctrl + b_0 + b_1 q + b_2 qd) is the law when ctrl = `actuator_control`."""
        return np.column_stack([np.zeros(self.n_joints), -self.kp, -self.kd])

    @staticmethod
    def feedback(applied: np.ndarray, u_ffwd: np.ndarray) -> np.ndarray:
        """What the feedback (PD) part contributed to an applied torque: u - u_ffwd (..., n)
        (after clipping, so saturation counts against the feedback)."""
        return applied - u_ffwd


@functools.lru_cache(maxsize=32)
def law_for(task: TaskDefinition) -> PDLaw:
    """The task's law: gains from its ``controller`` section, limits from its model (the
    torque that reaches each joint, `ArmModel.torque_low` / `torque_high`)."""
    arm = ArmModel(task)
    return PDLaw(task.controller.kp, task.controller.kd, arm.torque_low, arm.torque_high)
