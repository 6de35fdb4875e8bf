"""How a robot differs from its task's model: the "real" robot of a sim-to-real measurement.

The reference chapter learns the dynamics modality because the model is wrong (masses, friction
and damping the model does not know). `ModelError` makes a task's compiled MuJoCo model such a
robot: every body the driven joints move (the robot) heavier by ``mass_scale`` (its inertia
scaled with it, so the shapes stay), and every driven joint with dry friction ``frictionloss``
[N m] and viscous damping ``damping`` [N m s/rad] added. One place for both rollout modes: batch
rollouts on a wrong model and psl's simulator playing a standard robot apply the same error.
Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from psl_task.key_values import parse_key_values
from psl_task.model_spec import robot_bodies


@dataclasses.dataclass(frozen=True)
class ModelError:
    """The difference of a robot from its model (the identity by default)."""

    mass_scale: float = 1.0       # robot bodies' masses and inertias times this
    frictionloss: float = 0.0     # [N m] dry friction added on every driven joint
    damping: float = 0.0          # [N m s/rad] viscous damping added on every driven joint

    def __post_init__(self):
        for name, low in (('mass_scale', 0.0), ('frictionloss', 0.0), ('damping', 0.0)):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < low \
                    or (name == 'mass_scale' and value == 0.0):
                raise ValueError(f'model error {name} must be a finite number '
                                 f'{"> 0" if name == "mass_scale" else ">= 0"}, not {value!r}')

    @property
    def is_identity(self) -> bool:
        return self == ModelError()

    @classmethod
    def parse(cls, text: str) -> ModelError:
        """From ``"mass_scale=1.3,frictionloss=0.05,damping=0.3"`` (any subset; empty: none).
        ValueError naming what is wrong."""
        return parse_key_values(cls, text, 'model error')

    def apply(self, model: mujoco.MjModel, joint_ids: np.ndarray) -> None:
        """Make `model` (compiled, changed in place) the robot this error describes; the driven
        joints are `joint_ids`. The derived constants are recomputed (`mj_setConst`)."""
        if self.is_identity:
            return
        robot = robot_bodies(model, np.asarray(joint_ids))
        model.body_mass[robot] *= self.mass_scale
        model.body_inertia[robot] *= self.mass_scale
        dofs = model.jnt_dofadr[np.asarray(joint_ids)]
        model.dof_frictionloss[dofs] += self.frictionloss
        model.dof_damping[dofs] += self.damping
        mujoco.mj_setConst(model, mujoco.MjData(model))
