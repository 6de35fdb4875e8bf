"""The one place a task's MuJoCo model is read: `task_spec` gives a fresh, editable
`mujoco.MjSpec` of the task's model file. The simulation (`ArmModel`), the reward's sensors
(`RewardGeometry`) and batch mode's model (`batch_model`) all start from it, so whatever psl
adds to a robot as it comes (a site, motors, scene objects) is added here once and every mode
sees the same model. Imports no ROS.
"""
from __future__ import annotations

import mujoco

from psl_sim.task import TaskDefinition, TaskError


def task_spec(task: TaskDefinition) -> mujoco.MjSpec:
    """A new MjSpec of the task's model (the caller may edit and compile it).

    Raises:
        TaskError: the model file cannot be parsed.
    """
    try:
        return mujoco.MjSpec.from_file(str(task.model_path))
    except ValueError as exc:
        raise TaskError(f'cannot load model {task.model_path}: {exc}') from exc


def task_model(task: TaskDefinition) -> mujoco.MjModel:
    """The task's model, compiled from `task_spec`.

    Raises:
        TaskError: the model file cannot be parsed or compiled.
    """
    try:
        return task_spec(task).compile()
    except ValueError as exc:
        raise TaskError(f'cannot compile model {task.model_path}: {exc}') from exc
