"""The one place a task's MuJoCo model is read: `task_spec` gives a fresh, editable
`mujoco.MjSpec` of the task's model file. The simulation (`ArmModel`), the reward's sensors
(`RewardGeometry`) and batch mode's model (`batch_model`) all start from it, so whatever psl
adds to a robot as it comes (a site, motors, scene objects) is added here once and every mode
sees the same model. Imports no ROS.
"""
from __future__ import annotations

import os
from pathlib import Path
from xml.etree import ElementTree

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
        if task.model_path.suffix.lower() == '.urdf':
            spec = mujoco.MjSpec.from_string(urdf_text(task))
            spec.option.timestep = 1.0 / task.control_rate      # a URDF has no timestep
            # MuJoCo drops a URDF's contact-free geoms at compile: psl's scene objects are such
            spec.compiler.discardvisual = False
        else:
            spec = mujoco.MjSpec.from_file(str(task.model_path))
    except ValueError as exc:
        raise TaskError(f'cannot load model {task.model_path}: {exc}') from exc
    _add_motors(task, spec)
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
    if task.gravity_compensation:
        _compensate_gravity(spec.worldbody, moving=False)
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


def package_folder(task: TaskDefinition, package: str) -> Path:
    """Where ``package://package/`` points: ``robot.package_paths`` of the task, then the
    usual ROS search paths (ROS_PACKAGE_PATH folders named like the package or holding it,
    AMENT_PREFIX_PATH/share/package). TaskError naming what was searched otherwise."""
    if package in task.package_paths:
        return task.package_paths[package]
    searched = []
    for root in filter(None, os.environ.get('ROS_PACKAGE_PATH', '').split(':')):
        for candidate in (Path(root), Path(root) / package):
            searched.append(str(candidate))
            if candidate.name == package and candidate.is_dir():
                return candidate
    for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(':')):
        candidate = Path(prefix) / 'share' / package
        searched.append(str(candidate))
        if candidate.is_dir():
            return candidate
    raise TaskError(f'{task.path}: package://{package}/ of {task.model_path.name} is nowhere: '
                    f'give robot.package_paths: {{{package}: FOLDER}} (searched '
                    f'{", ".join(searched) or "no ROS_PACKAGE_PATH / AMENT_PREFIX_PATH"})')


def urdf_text(task: TaskDefinition) -> str:
    """The task's URDF with ``package://`` and relative mesh paths made absolute, meshes MuJoCo
    cannot read (.dae) dropped from visual elements and refused in collision elements, and
    Gazebo and transmission tags removed (MuJoCo ignores them anyway)."""
    try:
        root = ElementTree.parse(task.model_path).getroot()
    except ElementTree.ParseError as exc:
        raise TaskError(f'cannot read {task.model_path}: {exc}') from exc
    for tag in ('gazebo', 'transmission'):
        for element in root.findall(tag):
            root.remove(element)
    for link in root.iter('link'):
        for kind in ('visual', 'collision'):
            for element in link.findall(kind):
                mesh = element.find('geometry/mesh')
                if mesh is None:
                    continue
                filename = mesh.get('filename', '')
                if filename.startswith('package://'):
                    package, _, rest = filename[len('package://'):].partition('/')
                    resolved = package_folder(task, package) / rest
                else:
                    resolved = (task.model_path.parent / filename).resolve()
                if resolved.suffix.lower() == '.dae':
                    if kind == 'visual':
                        link.remove(element)      # MuJoCo reads STL, OBJ and MSH, not COLLADA
                        continue
                    raise TaskError(f'{task.path}: the collision mesh {filename} of link '
                                    f'{link.get("name")!r} is COLLADA (.dae), which MuJoCo '
                                    'cannot read: convert it to STL or OBJ')
                if not resolved.is_file():
                    raise TaskError(f'{task.path}: the mesh {filename} of link '
                                    f'{link.get("name")!r} is not a file ({resolved})')
                mesh.set('filename', str(resolved))
    return ElementTree.tostring(root, encoding='unicode')


def _add_motors(task: TaskDefinition, spec: mujoco.MjSpec) -> None:
    """A model without actuators (a URDF, a bare MJCF): a plain motor on every hinge and slide
    joint, in the model's joint order, its torque limit from ``robot.torque_limits``, else the
    joint's ``actuatorfrcrange`` (a URDF's effort limit)."""
    if len(spec.actuators):
        return
    joints = [j for j in spec.joints
              if j.type in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)]
    for i, joint in enumerate(joints):
        if task.torque_limits is not None and i < len(task.torque_limits):
            limit = float(task.torque_limits[i])
        elif joint.actfrclimited == mujoco.mjtLimited.mjLIMITED_TRUE or joint.actfrcrange[1] > 0:
            limit = float(max(abs(joint.actfrcrange[0]), abs(joint.actfrcrange[1])))
        else:
            raise TaskError(f'{task.path}: joint {joint.name!r} of {task.model_path.name} has no '
                            'motor and no torque limit: give robot.torque_limits (N m per joint)')
        motor = spec.add_actuator()
        motor.name = joint.name
        motor.target = joint.name
        motor.trntype = mujoco.mjtTrn.mjTRN_JOINT
        motor.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        motor.ctrlrange = [-limit, limit]


def _compensate_gravity(body, moving: bool) -> None:
    """gravcomp 1 on every body a joint moves (``robot.gravity_compensation``): MuJoCo
    applies the force that cancels its weight (a passive force, the same in every mode)."""
    moving = moving or bool(body.joints)
    if moving and not body.mocap:
        body.gravcomp = 1.0
    for child in body.bodies:
        _compensate_gravity(child, moving)


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
