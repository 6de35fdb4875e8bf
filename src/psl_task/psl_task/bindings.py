"""Binding kinds: how a task parameter's value reaches the model or the episode.

A task parameter's ``binds`` section names its kind and the keys that kind takes:

    binds: {kind: mocap_position, body: obstacle, axis: 2, offset: 0.1}

Each kind is one class here, registered in `BINDINGS` (as `psl_memory.registry` holds the
readouts): what keys it takes (its fields, validated by pydantic, unknown keys refused), what
range it accepts (`check_range`), what it does to the model or its data (`applier`, built once
per `psl_task.arm_model.ArmModel`), to the instance's target (`move_target`) or to the
movement's duration (`sets_duration`), and whether it changes the model itself
(`changes_model`: a kinematic replay, e.g. the safety check's or the reward's, then leaves it
out, and a batch of instances needs a model each). Adding a kind is one class and one
`register` call; no other module tests kind names.

The value a binding applies is the task parameter's value plus the binding's ``offset``.
Imports no ROS.
"""
from __future__ import annotations

from typing import Any, Callable, ClassVar, Literal, Protocol

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict

Applier = Callable[[mujoco.MjModel, mujoco.MjData, float], None]
Axis = Literal[0, 1, 2]


class Arm(Protocol):
    """What a binding needs of `psl_task.arm_model.ArmModel` (which imports the task, which
    imports this module) to resolve its names once."""

    model: mujoco.MjModel

    def body(self, name: str) -> int: ...

    def mocap(self, name: str) -> int: ...


class Binding(BaseModel):
    """One kind of binding; its fields are the keys of ``binds`` besides ``kind``."""

    model_config = ConfigDict(frozen=True, extra='forbid',
                              use_attribute_docstrings=True)   # a key's docstring: its description

    kind: ClassVar[str]
    changes_model: ClassVar[bool] = False   # the model itself (a mass), not only its data
    sets_duration: ClassVar[bool] = False   # the value is the movement's duration [s]
    needs_target: ClassVar[bool] = False    # the task needs a target section
    offset: float = 0.0
    """Added to the task parameter's value before it is applied."""

    def check_range(self, name: str, low: float, high: float) -> None:
        """Raises ValueError when the parameter's range [low, high] (offset applied) does
        not suit the kind."""

    def applier(self, arm: Arm) -> Applier | None:
        """The function that applies a value to a model and its data of `arm`'s robot
        (same bodies), or None when the kind changes neither; resolves names once
        (TaskError for a body the model lacks)."""
        return None

    def move_target(self, value: float, position: np.ndarray, angles: np.ndarray) -> None:
        """Apply `value` (offset included) to the instance's target position (3,) [m] and
        x-y-z angles (3,) [rad], in place."""


class MocapPosition(Binding):
    """One coordinate of a mocap body's position [m] (an obstacle, a marker)."""

    kind: ClassVar[str] = 'mocap_position'
    body: str
    """A mocap body of the model or the scene."""
    axis: Axis
    """The coordinate: 0 = x, 1 = y, 2 = z (world frame)."""

    def applier(self, arm: Arm) -> Applier:
        mocap, axis, offset = arm.mocap(self.body), self.axis, self.offset

        def apply(model, data, value):
            data.mocap_pos[mocap, axis] = value + offset
        return apply


class BodyMass(Binding):
    """A body's mass [kg] (a payload): changes the model, so the dynamics."""

    kind: ClassVar[str] = 'body_mass'
    changes_model: ClassVar[bool] = True
    body: str
    """The body whose mass the value is."""

    def check_range(self, name: str, low: float, high: float) -> None:
        if not low > 0.0:
            raise ValueError(f'task parameter {name!r} binds a mass: its range must stay '
                             f'above 0 kg, lowest {low:g}')

    def applier(self, arm: Arm) -> Applier:
        body, offset = arm.body(self.body), self.offset

        def apply(model, data, value):
            model.body_mass[body] = value + offset
        return apply


class TargetPosition(Binding):
    """One coordinate of the target's position [m] (the ``target`` section)."""

    kind: ClassVar[str] = 'target_position'
    needs_target: ClassVar[bool] = True
    axis: Axis
    """The coordinate: 0 = x, 1 = y, 2 = z (world frame)."""

    def move_target(self, value: float, position: np.ndarray, angles: np.ndarray) -> None:
        position[self.axis] = value


class TargetOrientation(Binding):
    """One of the target frame's x-y-z rotation angles [rad]."""

    kind: ClassVar[str] = 'target_orientation'
    needs_target: ClassVar[bool] = True
    axis: Axis
    """The angle: about x (0), y (1) or z (2), extrinsic."""

    def move_target(self, value: float, position: np.ndarray, angles: np.ndarray) -> None:
        angles[self.axis] = value


class Duration(Binding):
    """The movement's duration [s] (at most one per task)."""

    kind: ClassVar[str] = 'duration'
    sets_duration: ClassVar[bool] = True

    def check_range(self, name: str, low: float, high: float) -> None:
        if not low > 0.0:
            raise ValueError(f'task parameter {name!r} binds the duration: its range must '
                             f'stay above 0 s, lowest {low:g}')


BINDINGS: dict[str, type[Binding]] = {}


def register(kind: type[Binding]) -> type[Binding]:
    """Add a binding kind (usable as a class decorator); a name taken already is refused."""
    if kind.kind in BINDINGS and BINDINGS[kind.kind] is not kind:
        raise ValueError(f'binding kind {kind.kind!r} is registered already')
    BINDINGS[kind.kind] = kind
    return kind


for _kind in (MocapPosition, BodyMass, TargetPosition, TargetOrientation, Duration):
    register(_kind)


def binding_kind(binds: Any) -> type[Binding]:
    """The class of a ``binds`` mapping's kind; KeyError naming the known kinds otherwise."""
    kind = binds.get('kind') if isinstance(binds, dict) else None
    if kind not in BINDINGS:
        raise KeyError(kind)
    return BINDINGS[kind]
