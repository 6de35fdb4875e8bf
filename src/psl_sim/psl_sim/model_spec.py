"""The one place a task's MuJoCo model is read: `task_spec` gives a fresh, editable
`mujoco.MjSpec` of the task's model file. The simulation (`ArmModel`), the reward's sensors
(`RewardGeometry`) and batch mode's model (`batch_model`) all start from it, so whatever psl
adds to a robot as it comes (a site, motors, scene objects) is added here once and every mode
sees the same model. Imports no ROS.
"""
from __future__ import annotations

import mujoco
import numpy as np

from psl_sim.task import TaskDefinition, TaskError, rotation_xyz


GEOM_TYPES = {'box': mujoco.mjtGeom.mjGEOM_BOX, 'sphere': mujoco.mjtGeom.mjGEOM_SPHERE,
              'capsule': mujoco.mjtGeom.mjGEOM_CAPSULE,
              'cylinder': mujoco.mjtGeom.mjGEOM_CYLINDER}


def task_spec(task: TaskDefinition) -> mujoco.MjSpec:
    """A new MjSpec of the task's model (the caller may edit and compile it), with what the
    task YAML adds: the end-effector site on a body (``robot.end_effector: {body, offset}``)
    and the ``scene`` objects (each a mocap body with one geom of its name, no contacts unless
    ``contacts: true``).

    Raises:
        TaskError: the model file cannot be parsed, the end effector's body does not exist, or
            a scene object's name is taken.
    """
    try:
        spec = mujoco.MjSpec.from_file(str(task.model_path))
    except ValueError as exc:
        raise TaskError(f'cannot load model {task.model_path}: {exc}') from exc
    if task.end_effector_body:
        body = spec.body(task.end_effector_body)
        if body is None:
            bodies = [b.name for b in spec.bodies if b.name]
            raise TaskError(f'{task.path}: robot.end_effector names the body '
                            f'{task.end_effector_body!r}; {task.model_path.name} has '
                            f'{", ".join(bodies)}')
        body.add_site(name=task.end_effector_site, pos=task.end_effector_offset,
                      size=[0.01, 0.01, 0.01])
    if task.reward.obstacle_geoms and not task.reward.arm_geoms:
        _name_robot_geoms(spec.worldbody, moving=False)     # the default arm_geoms need names
    for obj in task.scene:
        taken = [kind for kind, found in (('body', spec.body(obj.name)),
                                          ('geom', spec.geom(obj.name))) if found is not None]
        if taken:
            raise TaskError(f'{task.path}: scene object {obj.name!r}: the model has a '
                            f'{taken[0]} of that name already; rename the object')
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, rotation_xyz(obj.orientation).reshape(-1))
        body = spec.worldbody.add_body(name=obj.name, pos=obj.position, quat=quat, mocap=True)
        body.add_geom(name=obj.name, type=GEOM_TYPES[obj.type], size=_geom_size(obj.size),
                      rgba=list(obj.rgba), contype=1 if obj.contacts else 0,
                      conaffinity=1 if obj.contacts else 0)
    return spec


def _name_robot_geoms(body, moving: bool) -> None:
    """Give every unnamed geom of a body that a joint moves a name (``psl_geom_<body>_<k>``):
    the reward's geomdist sensors name their geoms."""
    moving = moving or bool(body.joints)
    if moving and not body.mocap:
        for k, geom in enumerate(body.geoms):
            if not geom.name:
                geom.name = f'psl_geom_{body.name or "body"}_{k}'
    for child in body.bodies:
        _name_robot_geoms(child, moving)


def robot_geoms(model: mujoco.MjModel) -> tuple[str, ...]:
    """Names of the geoms on bodies that joints move (not welded to the world, not mocap): the
    arm geoms the reward measures when ``reward.arm_geoms`` is omitted."""
    moving = (model.body_weldid[model.geom_bodyid] != 0) & \
        (model.body_mocapid[model.geom_bodyid] < 0)
    return tuple(model.geom(int(g)).name for g in np.flatnonzero(moving)
                 if model.geom(int(g)).name)


def _geom_size(size: np.ndarray) -> list[float]:
    return list(size) + [0.0] * (3 - len(size))


def task_model(task: TaskDefinition) -> mujoco.MjModel:
    """The task's model, compiled from `task_spec`.

    Raises:
        TaskError: the model file cannot be parsed or compiled.
    """
    try:
        return task_spec(task).compile()
    except ValueError as exc:
        raise TaskError(f'cannot compile model {task.model_path}: {exc}') from exc
