"""The task's joints picked out of a robot's JointState, by name.

A ros2_control robot's ``joint_state_broadcaster`` lists its joints in its own order, possibly
more than the task drives (a gripper, a second arm). psl reads the task's joints by name, in
the task's command order (`psl_task.arm_model.joint_names_of`): any order, extra joints
ignored, a missing one a clear error. Imports no ROS.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np


class MissingJoints(ValueError):
    """The robot's joint states lack joints the task drives."""


class JointSelection:
    """The indices of `joints` (the task's, command order) in a message's name list; the
    lookup of one name list is kept, so a stream in one order costs a comparison."""

    def __init__(self, joints: Sequence[str]):
        self.joints = tuple(joints)
        if len(set(self.joints)) != len(self.joints):
            raise ValueError(f'joint names repeat: {list(self.joints)}')
        self._names: tuple[str, ...] | None = None
        self._index: np.ndarray | None = None

    def indices(self, names: Sequence[str]) -> np.ndarray:
        """Where each of the task's joints is in `names`. MissingJoints names the absent."""
        names = tuple(names)
        if names != self._names:
            where = {name: i for i, name in enumerate(names)}
            missing = [j for j in self.joints if j not in where]
            if missing:
                raise MissingJoints(
                    f'the joint states lack the joint{"s" if len(missing) > 1 else ""} '
                    f'{", ".join(repr(m) for m in missing)} (they list '
                    f'{", ".join(names) or "none"}; the task drives '
                    f'{", ".join(self.joints)})')
            self._index = np.array([where[j] for j in self.joints], dtype=int)
            self._names = names
        return self._index

    def pick(self, names: Sequence[str], values: Sequence[float]) -> np.ndarray:
        """The task's joints' entries of `values` (a JointState field in `names` order); an
        empty field stays empty (JointState leaves a field it does not measure empty)."""
        values = np.asarray(values, dtype=float)
        if values.size == 0:
            return values
        if values.shape != (len(names),):
            raise ValueError(f'a joint state field has {values.size} values for '
                             f'{len(names)} names')
        return values[self.indices(names)]
