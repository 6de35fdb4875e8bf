"""The one place a task's MuJoCo model is read: `task_spec` gives a fresh, editable
`mujoco.MjSpec` of the task's model file. The simulation (`ArmModel`), the reward's sensors
(`RewardGeometry`) and batch mode's model (`batch_model`) all start from it, so whatever psl
adds to a robot as it comes (a site, motors, scene objects) is added here once and every mode
sees the same model. Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import functools
from xml.etree import ElementTree

import mujoco
import numpy as np

from psl_task.meshes import MeshError, stl_of_collada
from psl_task.package_paths import PREFIX
from psl_task.task import TaskDefinition, TaskError, package_file, rotation_xyz


GEOM_TYPES = {'box': mujoco.mjtGeom.mjGEOM_BOX, 'sphere': mujoco.mjtGeom.mjGEOM_SPHERE,
              'capsule': mujoco.mjtGeom.mjGEOM_CAPSULE,
              'cylinder': mujoco.mjtGeom.mjGEOM_CYLINDER}


def task_spec(task: TaskDefinition) -> mujoco.MjSpec:
    """A new MjSpec of the task's model (the caller may edit and compile it), with what the
    task YAML adds and takes away: the locked joints fixed (``robot.locked_joints``:
    `lock_joints`), the end-effector site on a body (``robot.end_effector: {body, offset}``)
    and the ``scene`` objects (each a mocap body with one geom of its name, no contacts unless
    ``contacts: true``).

    Raises:
        TaskError: the model file cannot be parsed, a locked joint cannot be locked, the end
            effector's body does not exist, or a scene object's name is taken.
    """
    try:
        if task.model_path.suffix.lower() == '.urdf':
            spec = mujoco.MjSpec.from_string(urdf_text(task))
            spec.option.timestep = 1.0 / task.control_rate      # a URDF has no timestep
            # MuJoCo drops a URDF's contact-free geoms at compile: psl's scene objects are such
            spec.compiler.discardvisual = False
        else:
            spec = mujoco.MjSpec.from_file(str(task.model_path))
    except TaskError:
        raise
    except ValueError as exc:
        raise TaskError(f'cannot load model {task.model_path}: {exc}') from exc
    lock_joints(task, spec)
    driven = driven_joints(task, spec)
    _set_motors(task, spec, driven)
    if task.end_effector_body:
        body = spec.body(task.end_effector_body)
        if body is None:
            bodies = [b.name for b in spec.bodies if b.name]
            raise TaskError(f'{task.path}: robot.end_effector names the body '
                            f'{task.end_effector_body!r}; {task.model_path.name} has '
                            f'{", ".join(bodies)}')
        body.add_site(name=task.end_effector_site, pos=task.end_effector_offset,
                      size=[0.01, 0.01, 0.01])
    for body in _driven_bodies(spec.worldbody, set(driven)):
        if task.reward.obstacle_geoms and not task.reward.arm_geoms:
            # the default arm_geoms are the robot's geoms; the reward's sensors need names
            for k, geom in enumerate(body.geoms):
                if not geom.name:
                    geom.name = f'psl_geom_{body.name or "body"}_{k}'
        if task.gravity_compensation:
            body.gravcomp = 1.0     # MuJoCo cancels the body's weight (a passive force)
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
    pairs = list(task.exclude_contacts)
    if task.contacts_at_rest == 'exclude':
        pairs += [(c.body1, c.body2) for c in robot_contacts_at_rest(task)]
    for body1, body2 in dict.fromkeys(pairs):
        for name in (body1, body2):
            if spec.body(name) is None:
                raise TaskError(f'{task.path}: robot.exclude_contacts names the body {name!r}; '
                                f'{task.model_path.name} has none of that name')
        spec.add_exclude(bodyname1=body1, bodyname2=body2)
    return spec


def lock_joints(task: TaskDefinition, spec: mujoco.MjSpec) -> None:
    """Compile ``robot.locked_joints: {joint: value}`` as fixed joints: each joint is removed
    from the spec and its body placed where the joint at that value puts it, so the body and
    all below it move with the body's parent (a humanoid's arm taken from its full-body
    description is then an arm: the rest of the body cannot fall).

    A hinge's body is turned by ``value - ref`` [rad] about the joint's axis through the
    joint's position (both in the body's frame; a URDF's ref is 0), a slide's moved by
    ``value - ref`` [m] along its axis: the body's new frame in its parent is F * L, F its
    frame, L the joint's transform, as MuJoCo's kinematics composes them (Todorov, MuJoCo
    documentation, "Computation": a body's joints act in their order, each in the frame the
    ones before it left). A free joint (a floating base) or a ball joint locks at 0 only: the
    body at the model's reference pose (where the model file puts it). The joints of a body
    are locked from its first on (a locked joint after a joint that stays free cannot be
    folded into the body's frame). The actuators and joint sensors of a locked joint go with
    it, and the keyframes lose its entries.

    Raises:
        TaskError: one line naming robot.locked_joints: a joint the model lacks (its joints
            listed), a value outside the joint's range, a free or ball joint at a value other
            than 0, a locked joint after a free one of the same body.
    """
    if not task.locked_joints:
        return
    key = 'robot.locked_joints'
    by_name = {j.name: j for j in spec.joints if j.name}
    for name in task.locked_joints:
        if name not in by_name:
            raise TaskError(f'{task.path}: {key} names {name!r}; {task.model_path.name} has '
                            f'the joints {", ".join(by_name)}')
    reference = _reference_model(spec, list(task.locked_joints))
    bodies: dict[int, list[str]] = {}
    for name, value in task.locked_joints.items():
        jid = reference.joint(name).id
        kind = int(reference.jnt_type[jid])
        if kind in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL):
            if value != 0.0:
                raise TaskError(f'{task.path}: {key}: {name!r} is a '
                                f'{mujoco.mjtJoint(kind).name[6:].lower()} joint, which locks '
                                f'at 0 only (the body at the model\'s reference pose), got '
                                f'{value:g}')
        elif reference.jnt_limited[jid]:
            low, high = reference.jnt_range[jid]
            if not low <= value <= high:
                raise TaskError(f'{task.path}: {key}: {name!r} at {value:g} is outside its '
                                f'range [{low:g}, {high:g}]')
        bodies.setdefault(int(reference.jnt_bodyid[jid]), []).append(name)
    locked_adr = []
    for body_id, names in bodies.items():
        order = [reference.joint(int(j)).name for j in range(reference.njnt)
                 if reference.jnt_bodyid[j] == body_id]
        if set(order[:len(names)]) != set(names):
            free = next(n for n in order if n not in names)
            raise TaskError(f'{task.path}: {key}: the body {reference.body(body_id).name!r} '
                            f'moves with {", ".join(order)} in this order; {free!r} stays '
                            'free before a locked one: lock a body\'s joints from its first')
        pos = reference.body_pos[body_id].copy()
        quat = reference.body_quat[body_id].copy()
        for name in order[:len(names)]:
            jid = reference.joint(name).id
            pos, quat = locked_frame(reference, jid, task.locked_joints[name], pos, quat)
            adr, size = reference.jnt_qposadr[jid], _QPOS_SIZE[int(reference.jnt_type[jid])]
            locked_adr.append((adr, size, reference.jnt_dofadr[jid],
                               _DOF_SIZE[int(reference.jnt_type[jid])]))
        body = by_name[names[0]].parent
        body.pos, body.quat = pos, quat
        body.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
    locked = set(task.locked_joints)
    joint_targets = (mujoco.mjtTrn.mjTRN_JOINT, mujoco.mjtTrn.mjTRN_JOINTINPARENT)
    for actuator in list(spec.actuators):
        if actuator.trntype in joint_targets and actuator.target in locked:
            spec.delete(actuator)
    for sensor in list(spec.sensors):
        if sensor.objtype == mujoco.mjtObj.mjOBJ_JOINT and sensor.objname in locked:
            spec.delete(sensor)
    for equality in list(spec.equalities):      # a URDF's <mimic>: a joint equality
        if equality.type == mujoco.mjtEq.mjEQ_JOINT and (equality.name1 in locked
                                                         or equality.name2 in locked):
            spec.delete(equality)
    _drop_tendons_of(task, spec, reference, locked)
    _drop_from_keys(spec, reference, locked_adr)
    for name in task.locked_joints:
        spec.delete(by_name[name])


def _drop_tendons_of(task: TaskDefinition, spec: mujoco.MjSpec, reference: mujoco.MjModel,
                     locked: set[str]) -> None:
    """Delete each fixed tendon all of whose joints are locked (its length is then a constant:
    gymnasium's humanoid couples hip and knee so), with the actuators, sensors and equalities
    on it. A tendon coupling a locked joint with one that stays driven is refused, naming
    both (lock all of its joints or none)."""
    tendons = list(spec.tendons)
    key = 'robot.locked_joints'
    for t in range(reference.ntendon):
        adr, num = reference.tendon_adr[t], reference.tendon_num[t]
        joints = [reference.joint(int(reference.wrap_objid[w])).name
                  for w in range(adr, adr + num)
                  if reference.wrap_type[w] == mujoco.mjtWrap.mjWRAP_JOINT]
        held = [j for j in joints if j in locked]
        if not held:
            continue
        name = reference.tendon(t).name
        if len(held) < len(joints):
            raise TaskError(f'{task.path}: {key}: the tendon {name or t!r} couples '
                            f'{", ".join(held)} (locked) with '
                            f'{", ".join(j for j in joints if j not in locked)}: lock all of '
                            'its joints or none')
        for actuator in list(spec.actuators):
            if actuator.trntype == mujoco.mjtTrn.mjTRN_TENDON and actuator.target == name:
                spec.delete(actuator)
        for sensor in list(spec.sensors):
            if sensor.objtype == mujoco.mjtObj.mjOBJ_TENDON and sensor.objname == name:
                spec.delete(sensor)
        for equality in list(spec.equalities):
            if equality.type == mujoco.mjtEq.mjEQ_TENDON and name in (equality.name1,
                                                                      equality.name2):
                spec.delete(equality)
        spec.delete(tendons[t])


_QPOS_SIZE = {int(mujoco.mjtJoint.mjJNT_FREE): 7, int(mujoco.mjtJoint.mjJNT_BALL): 4,
              int(mujoco.mjtJoint.mjJNT_SLIDE): 1, int(mujoco.mjtJoint.mjJNT_HINGE): 1}
_DOF_SIZE = {int(mujoco.mjtJoint.mjJNT_FREE): 6, int(mujoco.mjtJoint.mjJNT_BALL): 3,
             int(mujoco.mjtJoint.mjJNT_SLIDE): 1, int(mujoco.mjtJoint.mjJNT_HINGE): 1}


def locked_frame(model: mujoco.MjModel, jid: int, value: float, pos: np.ndarray,
                 quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frame (position (3,), quaternion (4,) in the parent's frame) of a body at `pos`,
    `quat` with its joint `jid` of `model` (compiled: radians, unit axis) held at `value`:
    F * L (`lock_joints`). A free or ball joint at 0 leaves the frame as it is."""
    kind = int(model.jnt_type[jid])
    if kind not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
        return pos, quat
    axis, anchor = model.jnt_axis[jid], model.jnt_pos[jid]
    turn = value - float(model.qpos0[model.jnt_qposadr[jid]])      # from the joint's ref
    if kind == mujoco.mjtJoint.mjJNT_SLIDE:
        shift = np.zeros(3)
        mujoco.mju_rotVecQuat(shift, axis * turn, quat)
        return pos + shift, quat
    local = np.zeros(4)
    mujoco.mju_axisAngle2Quat(local, axis, turn)
    turned = np.zeros(3)
    mujoco.mju_rotVecQuat(turned, anchor, local)      # the body's origin about the anchor
    shift = np.zeros(3)
    mujoco.mju_rotVecQuat(shift, anchor - turned, quat)
    new_quat = np.zeros(4)
    mujoco.mju_mulQuat(new_quat, quat, local)
    return pos + shift, new_quat


def _reference_model(spec: mujoco.MjSpec, joints: list[str]) -> mujoco.MjModel:
    """The spec compiled as it comes, on a copy, no static body fused (each body's frame
    relative to its own parent) and the <frame> elements holding the bodies of the given
    joints made neutral, so each such body's compiled frame is the one its own pos and
    orientation give: what `lock_joints` composes the locked joints onto."""
    copy = spec.copy()
    copy.compiler.fusestatic = False
    for name in joints:
        frame = copy.joint(name).parent.frame
        while frame is not None:
            frame.pos, frame.quat = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
            frame.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
            frame = frame.frame
    try:
        return copy.compile()
    except ValueError as exc:
        raise TaskError(f'cannot compile the model to lock its joints: {exc}') from exc


def _drop_from_keys(spec: mujoco.MjSpec, reference: mujoco.MjModel, locked_adr: list) -> None:
    """The keyframes without the locked joints' qpos and qvel entries."""
    qpos_keep = np.ones(reference.nq, dtype=bool)
    dof_keep = np.ones(reference.nv, dtype=bool)
    for adr, size, dof, dofs in locked_adr:
        qpos_keep[adr:adr + size] = False
        dof_keep[dof:dof + dofs] = False
    for key in spec.keys:
        if len(key.qpos) == reference.nq:
            key.qpos = np.asarray(key.qpos)[qpos_keep]
        if len(key.qvel) == reference.nv:
            key.qvel = np.asarray(key.qvel)[dof_keep]


@functools.lru_cache(maxsize=32)     # a task is hashed by identity; load_task caches tasks
def robot_contacts_at_rest(task: TaskDefinition) -> tuple[RestingContact, ...]:
    """The robot's parts in contact at the start or goal posture of the task's model as it
    comes (before any exclusion; `contacts_at_rest`): what `task_spec` excludes and `psl
    check` names. Found once per task (a compile and a collision pass: 0.15 s for robosuite's
    Panda with its visual meshes)."""
    kept = dataclasses.replace(task, contacts_at_rest='keep', exclude_contacts=())
    spec = task_spec(kept)
    return tuple(contacts_at_rest(kept, spec, driven_joints(kept, spec)))


@dataclasses.dataclass(frozen=True)
class RestingContact:
    """Two parts of the robot in contact at the start or the goal posture."""

    body1: str
    body2: str
    depth: float                    # m, the deepest penetration of the pair
    postures: tuple[str, ...]       # 'start', 'goal'


def contacts_at_rest(task: TaskDefinition, spec: mujoco.MjSpec,
                     driven: list[str]) -> list[RestingContact]:
    """The pairs of robot bodies in contact at the start or the goal posture of the spec as it
    stands (compiled here, default instance, the rest of the model at its reference pose):
    two bodies the driven joints move, or such a body and the static body its chain hangs
    from (its base, e.g. the world a URDF's fixed links are fused into), which MuJoCo's
    parent-child filter leaves in when the parent is the world.

    Such contacts are a model's artefact, not an event: no arm rests in itself. Coarse
    collision meshes of neighbouring links overlap (TALOS's left arm from its ROS URDF: four
    contacts 4.5-6.5 cm deep at every posture), MuJoCo pushes the parts apart at every step
    and the arm chatters under any gains. `task_spec` excludes them (robot.contacts_at_rest:
    exclude, the default; keep leaves them in) and `psl check` names them. A robot part
    touching anything else at rest (a table, a scene object) is not among them."""
    if len(driven) != task.n_joints:
        return []       # the arm model refuses the task, naming the joints
    model = spec.compile()
    data = mujoco.MjData(model)
    joint_ids = np.array([model.joint(name).id for name in driven], dtype=int)
    moved = robot_bodies(model, joint_ids)
    qpos_adr = model.jnt_qposadr[joint_ids]
    found: dict[tuple[str, str], RestingContact] = {}
    for label, posture in (('start', task.start_posture), ('goal', task.goal_posture)):
        mujoco.mj_resetData(model, data)
        data.qpos[qpos_adr] = posture
        mujoco.mj_forward(model, data)
        for contact in data.contact[:data.ncon]:
            b1, b2 = sorted((int(model.geom_bodyid[contact.geom1]),
                             int(model.geom_bodyid[contact.geom2])))
            robot_pair = moved[b1] and moved[b2]
            on_base = not moved[b1] and moved[b2] and model.body_parentid[b2] == b1
            if not (robot_pair or on_base):
                continue
            key = (model.body(b1).name, model.body(b2).name)
            depth = max(0.0, -float(contact.dist))
            old = found.get(key)
            found[key] = RestingContact(
                *key, depth=max(depth, old.depth if old else 0.0),
                postures=tuple(dict.fromkeys((old.postures if old else ()) + (label,))))
    return list(found.values())


def urdf_text(task: TaskDefinition) -> str:
    """The task's URDF with ``package://`` and relative mesh paths made absolute, COLLADA
    (.dae) collision meshes replaced by their STL (`psl_task.meshes`: converted once, cached;
    MuJoCo reads STL, OBJ and MSH), and Gazebo and transmission tags removed (MuJoCo ignores
    them anyway). COLLADA visual meshes are dropped unread: MuJoCo's URDF import discards a
    URDF's visual elements (its ``discardvisual``, on for URDFs: UR5's model compiles to the
    same 8 geoms with its 7 converted visual meshes in the URDF as without them), so
    converting them would cost time (1.4 s for UR5's, once) for nothing.

    Raises:
        TaskError: the URDF cannot be parsed, a mesh is not a file, or a .dae cannot be
            converted (damaged, no triangles), naming the file and the link.
    """
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
                if filename.startswith(PREFIX):
                    resolved = package_file(task, filename, f'the mesh of link '
                                                            f'{link.get("name")!r}')
                else:
                    resolved = (task.model_path.parent / filename).resolve()
                if resolved.suffix.lower() == '.dae' and kind == 'visual':
                    link.remove(element)        # discarded by MuJoCo anyway (docstring)
                    continue
                if not resolved.is_file():
                    raise TaskError(f'{task.path}: the mesh {filename} of link '
                                    f'{link.get("name")!r} is not a file ({resolved})')
                if resolved.suffix.lower() == '.dae':
                    try:
                        resolved = stl_of_collada(resolved)
                    except MeshError as exc:
                        raise TaskError(f'{task.path}: the collision mesh of link '
                                        f'{link.get("name")!r}: {exc}') from None
                mesh.set('filename', str(resolved))
    return ElementTree.tostring(root, encoding='unicode')


def urdf_velocity_limits(task: TaskDefinition, joint_names: list[str]) -> np.ndarray:
    """The URDF's ``<limit velocity="...">`` of each joint (inf where it gives none, or no
    number > 0, or the model is not a URDF): MuJoCo's URDF import drops them; psl holds the arm
    to them (`psl_task.joint_limits`)."""
    limits = np.full(len(joint_names), np.inf)
    if task.model_path.suffix.lower() != '.urdf':
        return limits
    try:
        root = ElementTree.parse(task.model_path).getroot()
    except (OSError, ElementTree.ParseError):     # MuJoCo read it: nothing to add here
        return limits
    for joint in root.iter('joint'):
        limit = joint.find('limit')
        if limit is None or joint.get('name') not in joint_names:
            continue
        try:
            velocity = float(limit.get('velocity', 'inf'))
        except ValueError:
            continue
        if velocity > 0.0:
            limits[joint_names.index(joint.get('name'))] = velocity
    return limits


ONE_DOF = (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
ONE_DOF_TYPES = tuple(int(t) for t in ONE_DOF)    # as a compiled model's jnt_type holds them


def driven_joints(task: TaskDefinition, spec: mujoco.MjSpec) -> list[str]:
    """The joints psl drives, in command order: ``robot.joints``, else the joints of the
    model's actuators (actuator order), else every hinge and slide joint of a model without
    actuators (a URDF). Every other joint stays passive; locked joints (`lock_joints`, run
    first) are gone from the spec with their actuators, so they are never among them.

    Raises:
        TaskError: robot.joints names a joint the model lacks, or one that is not a hinge or
            slide (psl commands one torque per joint).
    """
    if not task.joints:
        if len(spec.actuators):
            return [a.target for a in spec.actuators]
        return [j.name for j in spec.joints if j.type in ONE_DOF]
    by_name = {j.name: j for j in spec.joints if j.name}
    for name in task.joints:
        if name not in by_name:
            raise TaskError(f'{task.path}: robot.joints names {name!r}; '
                            f'{task.model_path.name} has the joints {", ".join(by_name)}')
        if by_name[name].type not in ONE_DOF:
            raise TaskError(f'{task.path}: robot.joints names {name!r}, a '
                            f'{by_name[name].type.name[6:].lower()} joint: psl drives hinge '
                            'and slide joints only; leave it out (it stays passive)')
    return list(task.joints)


def _set_motors(task: TaskDefinition, spec: mujoco.MjSpec, driven: list[str]) -> None:
    """With ``robot.joints``: remove the actuators of the joints that are not driven (they
    stay passive); then a plain motor on every driven joint without an actuator, its torque
    limit from ``robot.torque_limits``, else the joint's ``actuatorfrcrange`` (a URDF's effort
    limit)."""
    if task.joints:
        for actuator in list(spec.actuators):
            if actuator.trntype != mujoco.mjtTrn.mjTRN_JOINT or actuator.target not in driven:
                spec.delete(actuator)
    for actuator in spec.actuators:
        _torque_motor(actuator)
    actuated = {a.target for a in spec.actuators if a.trntype == mujoco.mjtTrn.mjTRN_JOINT}
    for i, name in enumerate(driven):
        if name in actuated:
            continue
        joint = spec.joint(name)
        if task.torque_limits is not None:
            limit = float(task.torque_limits[i])
        elif joint.actfrclimited == mujoco.mjtLimited.mjLIMITED_TRUE or joint.actfrcrange[1] > 0:
            limit = float(max(abs(joint.actfrcrange[0]), abs(joint.actfrcrange[1])))
        else:
            raise TaskError(f'{task.path}: joint {joint.name!r} of {task.model_path.name} has no '
                            'motor and no torque limit: give robot.torque_limits (N m per joint)')
        motor = spec.add_actuator()
        motor.name = joint.name if spec.actuator(joint.name) is None else f'psl_{joint.name}'
        motor.target = joint.name
        motor.trntype = mujoco.mjtTrn.mjTRN_JOINT
        motor.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        motor.ctrlrange = [-limit, limit]


def _torque_motor(actuator) -> None:
    """A joint motor with a gear or gain other than 1 (gymnasium's humanoid: gear 25,
    ctrlrange +-0.4) made one whose ctrl is the joint torque: gear and gain 1, the ctrlrange
    scaled by their product (torque = gear * gain * ctrl, MuJoCo documentation, "Actuation
    model"), so the torque limits are unchanged. Other actuators are left as they are
    (`ArmModel` names them)."""
    plain = (actuator.trntype == mujoco.mjtTrn.mjTRN_JOINT
             and actuator.dyntype == mujoco.mjtDyn.mjDYN_NONE
             and actuator.gaintype == mujoco.mjtGain.mjGAIN_FIXED
             and actuator.biastype == mujoco.mjtBias.mjBIAS_NONE
             and not np.any(actuator.gear[1:]))
    scale = float(actuator.gear[0] * actuator.gainprm[0])
    if not plain or scale == 1.0 or scale == 0.0:
        return
    actuator.ctrlrange = np.sort(np.asarray(actuator.ctrlrange, dtype=float) * scale)
    actuator.gear[0] = 1.0
    actuator.gainprm[0] = 1.0


def _driven_bodies(body, driven: set[str], moving: bool = False):
    """The bodies a driven joint moves (the body of a driven joint and all below it), but
    not mocap bodies: the robot."""
    moving = moving or any(j.name in driven for j in body.joints)
    if moving and not body.mocap:
        yield body
    for child in body.bodies:
        yield from _driven_bodies(child, driven, moving)


def robot_bodies(model: mujoco.MjModel, joint_ids: np.ndarray) -> np.ndarray:
    """(nbody,) True for the bodies the driven joints (ids) move (not mocap): the robot."""
    driven = set(model.jnt_bodyid[joint_ids].tolist())
    moved = np.zeros(model.nbody, dtype=bool)
    for b in range(1, model.nbody):         # parents come before their children
        moved[b] = b in driven or moved[model.body_parentid[b]]
    return moved & (model.body_mocapid < 0)


def visual_only(model: mujoco.MjModel) -> np.ndarray:
    """(ngeom,) True for geoms that are there to be seen: no contacts (contype = conaffinity =
    0) and a geom group above 0. MuJoCo's URDF import puts a link's <visual> there (group 1,
    no contacts) and model collections do likewise (robosuite: visual meshes in group 1,
    collision geoms in group 0; MuJoCo Menagerie: classes visual (group 2) and collision
    (group 3, contacts on)). A contact-free geom of group 0 (gymnasium's pusher arm) is the
    robot's shape, not decoration."""
    return (model.geom_contype == 0) & (model.geom_conaffinity == 0) & (model.geom_group > 0)


def robot_geoms(model: mujoco.MjModel, joint_ids: np.ndarray) -> tuple[str, ...]:
    """Names of the geoms on the bodies the driven joints (ids) move, visual-only ones left
    out (`visual_only`): the arm geoms the reward and the safety check measure when
    ``reward.arm_geoms`` is omitted (a passive object's geoms are not the arm's). Measuring
    the visual meshes too cost robosuite's Panda 45 geoms (38 of them visual mesh pieces)
    against an obstacle at every step instead of its 7 collision meshes
    (docs/benchmarks.md)."""
    moved = robot_bodies(model, joint_ids)
    seen_only = visual_only(model)
    return tuple(model.geom(int(g)).name for g in range(model.ngeom)
                 if moved[model.geom_bodyid[g]] and not seen_only[g]
                 and model.geom(int(g)).name)


def _geom_size(size: np.ndarray) -> list[float]:
    return list(size) + [0.0] * (3 - len(size))


def task_model(task: TaskDefinition) -> mujoco.MjModel:
    """The task's model, compiled from `task_spec`.

    Raises:
        TaskError: the model file cannot be parsed or compiled.
    """
    try:
        return task_spec(task).compile()
    except TaskError:
        raise
    except ValueError as exc:
        raise TaskError(f'cannot compile model {task.model_path}: {exc}') from exc
