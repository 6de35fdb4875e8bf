"""What a task's scene looks like: the visible geoms of its MuJoCo model as drawable shapes.

`Scene` reads, once per model, which geoms are drawn, their kind, size and colour, and gives
their poses for any `mujoco.MjData` of that model (`poses`; `forward` first when data comes
straight from ``mj_step``, whose geom poses are those of the state before the step). Two
levels:

- `SceneGeom`: one per visible geom, MuJoCo's own description (type, ``size``, rgba) and its
  pose (``data.geom_xpos``, ``data.geom_xmat``) — what a stick figure or a check needs;
- `Shape`: the primitives of the ROS ``visualization_msgs/Marker`` conventions that draw a
  geom (``SPHERE``, ``CYLINDER``, ``CUBE``, ``TRIANGLE_LIST``; the marker's ``scale`` is the
  full extent, a cylinder's axis is its local z like MuJoCo's), each with a marker namespace
  and an id that stay the same for the model, so that RViz and Foxglove update a marker in
  place from one message to the next. The simulator node turns them into Marker messages;
  this module imports no ROS.

How each MuJoCo geom type is drawn (MuJoCo ``size`` semantics, mjModel.geom_size):

- sphere (radius r): SPHERE of diameter 2r;
- capsule (radius r, half-length h of the cylinder part): a CYLINDER of diameter 2r and height
  2h plus two SPHEREs of diameter 2r at +-h along the geom's z axis (exact, three markers);
- cylinder (r, h): CYLINDER (2r, 2r, 2h); ellipsoid (semi-axes a, b, c): SPHERE (2a, 2b, 2c);
- box (half-sizes): CUBE of twice the half-sizes;
- plane (half-sizes x, y; 0 = infinite): a CUBE ``PLANE_THICKNESS`` thick whose top face is
  the plane, an infinite side drawn ``INFINITE_PLANE_EXTENTS`` model extents long;
- mesh: TRIANGLE_LIST of its faces, vertices in the geom frame (``mesh_vert``, ``mesh_face``);
- height field and SDF geoms are not drawn.

A geom is visible when MuJoCo's viewer shows it by default (geom group 0, 1 or 2:
``mjvOption.geomgroup``) and it is not fully transparent. Its colour is the material's when
it has one and its own rgba is MuJoCo's default, else its rgba (as MuJoCo's renderer does).

Namespaces: geoms of mocap bodies — the bodies the task parameters place (obstacles, posts) —
are ``obstacles``; geoms fixed to the world ``static`` (table, floor); all others, the bodies
the joints move, ``arm``. Marker ids: ``PARTS_PER_GEOM * geom id + part``.
"""
from __future__ import annotations

import dataclasses
import enum

import mujoco
import numpy as np

ARM, OBSTACLES, STATIC = 'arm', 'obstacles', 'static'      # marker namespaces of the geoms
END_EFFECTOR_PATH = 'end_effector_path'                     # namespace of the executed path
VISIBLE_GROUPS = 3          # MuJoCo's viewer shows geom groups 0..2 by default
PARTS_PER_GEOM = 3          # at most three markers per geom (a capsule: cylinder and two caps)
PLANE_THICKNESS = 0.002     # m, a plane is drawn as a box this thick below its surface
INFINITE_PLANE_EXTENTS = 2.0    # an infinite plane is drawn this many model extents long
PATH_WIDTH = 0.005          # m, line width of the end-effector path
PATH_RGBA = np.array([1.0, 0.75, 0.1, 1.0])
_DEFAULT_GEOM_RGBA = np.array([0.5, 0.5, 0.5, 1.0], dtype=np.float32)    # MuJoCo's default


class ShapeKind(enum.Enum):
    """Drawing primitives, named as visualization_msgs/Marker's types."""

    SPHERE = 'sphere'
    CYLINDER = 'cylinder'
    CUBE = 'cube'
    TRIANGLE_LIST = 'triangle_list'
    LINE_STRIP = 'line_strip'


@dataclasses.dataclass(frozen=True)
class SceneGeom:
    """One visible geom of the model."""

    geom: int                   # geom id
    name: str                   # geom name ('' when unnamed)
    namespace: str              # ARM, OBSTACLES or STATIC
    type: mujoco.mjtGeom
    size: np.ndarray            # (3,) mjModel.geom_size
    rgba: np.ndarray            # (4,) as drawn


@dataclasses.dataclass(frozen=True)
class Shape:
    """One primitive that draws (part of) a geom: a Marker without its pose."""

    namespace: str
    marker_id: int
    kind: ShapeKind
    geom: int                   # geom id of the geom it draws
    scale: np.ndarray           # (3,) full extents [m] (Marker.scale)
    rgba: np.ndarray            # (4,)
    axial_offset: float = 0.0   # m along the geom's z axis: capsule caps, plane boxes
    points: np.ndarray | None = None    # (3 T, 3) triangle vertices in the geom frame


@dataclasses.dataclass(frozen=True)
class Poses:
    """Poses of the shapes, in the order of `Scene.shapes`."""

    position: np.ndarray        # (S, 3) in the world frame [m]
    orientation: np.ndarray     # (S, 4) quaternion w, x, y, z


def _namespace(model: mujoco.MjModel, body: int) -> str:
    if model.body_mocapid[model.body_rootid[body]] >= 0:
        return OBSTACLES
    if model.body_weldid[body] == 0:
        return STATIC
    return ARM


def _rgba(model: mujoco.MjModel, geom: int) -> np.ndarray:
    material = model.geom_matid[geom]
    if material >= 0 and np.array_equal(model.geom_rgba[geom], _DEFAULT_GEOM_RGBA):
        return model.mat_rgba[material].astype(float)
    return model.geom_rgba[geom].astype(float)


def _visible(model: mujoco.MjModel, geom: int) -> bool:
    return (0 <= model.geom_group[geom] < VISIBLE_GROUPS and _rgba(model, geom)[3] > 0.0
            and model.geom_type[geom] not in (mujoco.mjtGeom.mjGEOM_HFIELD,
                                              mujoco.mjtGeom.mjGEOM_SDF))


def _mesh_triangles(model: mujoco.MjModel, geom: int) -> np.ndarray:
    """(3 F, 3) the mesh's faces as a triangle list, in the geom frame."""
    mesh = model.geom_dataid[geom]
    first, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
    vertices = model.mesh_vert[first:first + count].astype(float)
    face_first, face_count = model.mesh_faceadr[mesh], model.mesh_facenum[mesh]
    faces = model.mesh_face[face_first:face_first + face_count]          # (F, 3) indices
    return vertices[faces].reshape(-1, 3)


def shapes_of(model: mujoco.MjModel, geom: SceneGeom) -> list[Shape]:
    """The primitives that draw one geom (see the module docstring)."""
    g, r = geom.type, geom.size

    def shape(part: int, kind: ShapeKind, scale, offset: float = 0.0, points=None) -> Shape:
        return Shape(namespace=geom.namespace, marker_id=PARTS_PER_GEOM * geom.geom + part,
                     kind=kind, geom=geom.geom, scale=np.asarray(scale, dtype=float),
                     rgba=geom.rgba, axial_offset=offset, points=points)

    if g == mujoco.mjtGeom.mjGEOM_SPHERE:
        return [shape(0, ShapeKind.SPHERE, [2 * r[0]] * 3)]
    if g == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return [shape(0, ShapeKind.CYLINDER, [2 * r[0], 2 * r[0], 2 * r[1]]),
                shape(1, ShapeKind.SPHERE, [2 * r[0]] * 3, -r[1]),
                shape(2, ShapeKind.SPHERE, [2 * r[0]] * 3, r[1])]
    if g == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return [shape(0, ShapeKind.CYLINDER, [2 * r[0], 2 * r[0], 2 * r[1]])]
    if g == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        return [shape(0, ShapeKind.SPHERE, 2 * r)]
    if g == mujoco.mjtGeom.mjGEOM_BOX:
        return [shape(0, ShapeKind.CUBE, 2 * r)]
    if g == mujoco.mjtGeom.mjGEOM_PLANE:
        infinite = INFINITE_PLANE_EXTENTS * model.stat.extent
        sides = [2 * s if s > 0 else infinite for s in r[:2]]
        return [shape(0, ShapeKind.CUBE, sides + [PLANE_THICKNESS], -PLANE_THICKNESS / 2)]
    if g == mujoco.mjtGeom.mjGEOM_MESH:
        return [shape(0, ShapeKind.TRIANGLE_LIST, [1.0, 1.0, 1.0],
                      points=_mesh_triangles(model, geom.geom))]
    raise ValueError(f'geom {geom.name or geom.geom} of type {g.name} is not drawn')


class Scene:
    """The visible geoms of a model and the shapes that draw them (module docstring)."""

    def __init__(self, model: mujoco.MjModel):
        self.model = model
        self.geoms: tuple[SceneGeom, ...] = tuple(
            SceneGeom(geom=i, name=model.geom(i).name,
                      namespace=_namespace(model, model.geom_bodyid[i]),
                      type=mujoco.mjtGeom(model.geom_type[i]),
                      size=model.geom_size[i].copy(), rgba=_rgba(model, i))
            for i in range(model.ngeom) if _visible(model, i))
        self.shapes: tuple[Shape, ...] = tuple(
            s for geom in self.geoms for s in shapes_of(model, geom))
        self._shape_geoms = np.array([s.geom for s in self.shapes], dtype=int)      # (S,)
        self._offsets = np.array([s.axial_offset for s in self.shapes])             # (S,)
        self._data = mujoco.MjData(model)

    def forward(self, data: mujoco.MjData) -> mujoco.MjData:
        """The kinematics of data's current state (joint positions, mocap poses) on the
        scene's own MjData, which it returns: after ``mj_step`` data's own geom and site poses
        are still those of the state before the step. data is not changed."""
        own = self._data
        own.qpos[:], own.mocap_pos[:], own.mocap_quat[:] = (data.qpos, data.mocap_pos,
                                                            data.mocap_quat)
        mujoco.mj_kinematics(self.model, own)
        return own

    def geoms_in(self, namespace: str) -> list[SceneGeom]:
        return [g for g in self.geoms if g.namespace == namespace]

    def geom_poses(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """Positions (G, 3) and rotation matrices (G, 3, 3) of `geoms` in the world frame,
        as of the last kinematics pass on data (mj_forward, mj_step, mj_kinematics)."""
        ids = [g.geom for g in self.geoms]
        return data.geom_xpos[ids].copy(), data.geom_xmat[ids].reshape(-1, 3, 3).copy()

    def poses(self, data: mujoco.MjData) -> Poses:
        """The world poses of `shapes`: a geom's pose, moved by the shape's axial offset
        along the geom's z axis."""
        rotation = data.geom_xmat[self._shape_geoms].reshape(-1, 3, 3)        # (S, 3, 3)
        position = data.geom_xpos[self._shape_geoms] + self._offsets[:, None] * rotation[:, :, 2]
        orientation = np.empty((len(self.shapes), 4))
        for k, geom in enumerate(self._shape_geoms):
            mujoco.mju_mat2Quat(orientation[k], data.geom_xmat[geom])
        return Poses(position=position, orientation=orientation)


# the end-effector path executed in an episode (a LINE_STRIP: scale.x is the line width)
PATH_SHAPE = Shape(namespace=END_EFFECTOR_PATH, marker_id=0, kind=ShapeKind.LINE_STRIP,
                   geom=-1, scale=np.array([PATH_WIDTH, 0.0, 0.0]), rgba=PATH_RGBA)
