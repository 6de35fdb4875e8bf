"""Tests of the scene extraction (psl_sim.scene) against the task models and MuJoCo's own
geom poses: which geoms are drawn, capsules as a cylinder and two caps, obstacles placed by
tau, stable marker ids, and every geom type on a small model of its own."""

import textwrap

import mujoco
import numpy as np
import pytest

from psl_task.arm_model import ArmModel
from psl_sim.scene import (ARM, OBSTACLES, PARTS_PER_GEOM, PLANE_THICKNESS, STATIC, Scene,
                           ShapeKind)
from psl_task.task import load_task

# reach_over_obstacle.xml, copied by hand
ARM_GEOMS = ['link1', 'link2', 'link3']
OBSTACLE_GEOMS = ['obstacle']
STATIC_GEOMS = ['table']
ARM_RADIUS = 0.025                  # m
LINK2_HALF_LENGTH = 0.25            # m, fromto 0 -> 0.5
OBSTACLE_TOP_OFFSET = -0.04         # m, obstacle_height binds the body z with this offset
OBSTACLE_HALF_LENGTH = 0.2          # m, capsule fromto z - 0.4 -> z
TABLE_HALF_SIZES = np.array([1.2, 0.3, 0.01])

TOL = 1e-12                         # m, poses computed from MuJoCo's own data
TOL_QUAT = 1e-12


@pytest.fixture(scope='module')
def arm():
    arm = ArmModel(load_task('reach_over_obstacle'))
    arm.reset(arm.task.tau_default)
    return arm


@pytest.fixture(scope='module')
def scene(arm):
    return Scene(arm.model)


def names_in(scene, namespace):
    return [g.name for g in scene.geoms_in(namespace)]


def shapes_of_geom(scene, arm, name):
    return [(k, s) for k, s in enumerate(scene.shapes) if s.geom == arm.geom(name)]


def test_every_visible_geom_is_drawn_once_in_its_namespace(scene):
    assert names_in(scene, ARM) == ARM_GEOMS
    assert names_in(scene, OBSTACLES) == OBSTACLE_GEOMS
    assert names_in(scene, STATIC) == STATIC_GEOMS
    assert len(scene.geoms) == len(ARM_GEOMS + OBSTACLE_GEOMS + STATIC_GEOMS)
    # a capsule is three markers (cylinder + two caps), the table one
    assert len(scene.shapes) == 3 * len(ARM_GEOMS + OBSTACLE_GEOMS) + len(STATIC_GEOMS)


def test_marker_ids_are_unique_and_stable(arm, scene):
    keys = [(s.namespace, s.marker_id) for s in scene.shapes]
    assert len(set(keys)) == len(keys)
    assert keys == [(s.namespace, s.marker_id) for s in Scene(arm.model).shapes]
    for shape in scene.shapes:
        assert shape.marker_id // PARTS_PER_GEOM == shape.geom


def test_a_capsule_is_a_cylinder_and_two_caps_at_mujocos_pose(arm, scene):
    q = np.array([0.4, -0.7, 0.9])
    data = mujoco.MjData(arm.model)
    data.qpos[arm.qpos_adr] = q
    mujoco.mj_forward(arm.model, data)
    geom = arm.geom('link2')
    np.testing.assert_allclose(arm.model.geom_size[geom][:2], [ARM_RADIUS, LINK2_HALF_LENGTH])
    poses = scene.poses(data)
    (k_cyl, cyl), (k_a, cap_a), (k_b, cap_b) = shapes_of_geom(scene, arm, 'link2')
    assert [cyl.kind, cap_a.kind, cap_b.kind] == [ShapeKind.CYLINDER, ShapeKind.SPHERE,
                                                  ShapeKind.SPHERE]
    diameter, length = 2 * ARM_RADIUS, 2 * LINK2_HALF_LENGTH
    np.testing.assert_allclose(cyl.scale, [diameter, diameter, length], atol=TOL)
    np.testing.assert_allclose(cap_a.scale, [diameter] * 3, atol=TOL)
    # the cylinder sits where MuJoCo has the geom; the caps at the ends of its segment, which
    # for link2 (fromto 0 -> 0.5 along the body x) start at the elbow joint: body_xpos
    np.testing.assert_allclose(poses.position[k_cyl], data.geom_xpos[geom], atol=TOL)
    axis = data.geom_xmat[geom].reshape(3, 3)[:, 2]
    ends = sorted([poses.position[k_a], poses.position[k_b]], key=lambda p: np.dot(p, axis))
    np.testing.assert_allclose(ends[1] - ends[0], length * axis, atol=TOL)
    link2_start = data.xpos[arm.model.geom_bodyid[geom]]
    assert min(np.linalg.norm(e - link2_start) for e in ends) < TOL
    # the orientation is the geom's: its z axis along the segment
    rotation = np.empty(9)
    mujoco.mju_quat2Mat(rotation, poses.orientation[k_cyl])
    np.testing.assert_allclose(rotation, data.geom_xmat[geom], atol=TOL_QUAT)
    np.testing.assert_allclose(cyl.rgba, arm.model.geom_rgba[geom], atol=1e-7)


def test_obstacle_markers_move_with_tau(arm, scene):
    data = mujoco.MjData(arm.model)
    tops = []
    for tau in (arm.task.tau_low, arm.task.tau_high):
        arm.move_bodies(tau, data)
        mujoco.mj_forward(arm.model, data)
        poses = scene.poses(data)
        (k_cyl, _), *caps = shapes_of_geom(scene, arm, 'obstacle')
        top = max((poses.position[k] for k, _ in caps), key=lambda p: p[2])
        np.testing.assert_allclose(top, [tau[0], 0.0, tau[1] + OBSTACLE_TOP_OFFSET], atol=TOL)
        np.testing.assert_allclose(poses.position[k_cyl],
                                   top - [0.0, 0.0, OBSTACLE_HALF_LENGTH], atol=TOL)
        tops.append(top)
    assert np.linalg.norm(tops[1] - tops[0]) > 0.1


def test_the_table_is_a_cube_of_its_size(arm, scene):
    (k, table), = shapes_of_geom(scene, arm, 'table')
    assert table.kind == ShapeKind.CUBE and table.namespace == STATIC
    np.testing.assert_allclose(table.scale, 2 * TABLE_HALF_SIZES)


def test_every_geom_type_on_a_model_of_its_own():
    """Spheres, ellipsoids, cylinders, boxes, planes and meshes; invisible geoms (group 3,
    alpha 0) are not drawn; a material's colour; a mesh's triangles land where its vertices
    were put in the MJCF (MuJoCo recentres mesh vertices and moves the geom frame instead)."""
    vertices = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.1]])
    model = mujoco.MjModel.from_xml_string(textwrap.dedent(f"""
        <mujoco>
          <asset>
            <mesh name="tetra" vertex="{' '.join(map(str, vertices.ravel()))}"/>
            <material name="green" rgba="0 1 0 1"/>
          </asset>
          <worldbody>
            <geom name="floor" type="plane" size="0 2 0.1"/>
            <geom name="hidden" type="sphere" size="0.1" group="3"/>
            <geom name="clear" type="sphere" size="0.1" rgba="1 1 1 0"/>
            <body name="b" pos="1 2 3">
              <joint type="hinge"/>
              <geom name="ball" type="sphere" size="0.1" material="green"/>
              <geom name="egg" type="ellipsoid" size="0.1 0.2 0.3"/>
              <geom name="can" type="cylinder" size="0.1 0.4"/>
              <geom name="box" type="box" size="0.1 0.2 0.3"/>
              <geom name="tetra" type="mesh" mesh="tetra"/>
            </body>
          </worldbody>
        </mujoco>"""))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    scene = Scene(model)
    assert [g.name for g in scene.geoms] == ['floor', 'ball', 'egg', 'can', 'box', 'tetra']
    shapes = {model.geom(s.geom).name: s for s in scene.shapes}
    assert len(shapes) == len(scene.shapes)                     # one shape each
    expected = {'ball': (ShapeKind.SPHERE, [0.2, 0.2, 0.2]),
                'egg': (ShapeKind.SPHERE, [0.2, 0.4, 0.6]),
                'can': (ShapeKind.CYLINDER, [0.2, 0.2, 0.8]),
                'box': (ShapeKind.CUBE, [0.2, 0.4, 0.6]),
                'tetra': (ShapeKind.TRIANGLE_LIST, [1.0, 1.0, 1.0])}
    for name, (kind, scale) in expected.items():
        assert shapes[name].kind == kind and shapes[name].namespace == ARM
        np.testing.assert_allclose(shapes[name].scale, scale, atol=1e-7)
    np.testing.assert_allclose(shapes['ball'].rgba, [0, 1, 0, 1])
    floor = shapes['floor']
    assert floor.kind == ShapeKind.CUBE and floor.namespace == STATIC
    assert floor.scale[0] > 1.0 and floor.scale[1] == pytest.approx(4.0)     # x infinite
    assert floor.scale[2] == PLANE_THICKNESS
    poses = scene.poses(data)
    k_floor = scene.shapes.index(floor)
    assert poses.position[k_floor][2] + PLANE_THICKNESS / 2 == pytest.approx(0.0)
    k_tetra = scene.shapes.index(shapes['tetra'])
    rotation = np.empty(9)
    mujoco.mju_quat2Mat(rotation, poses.orientation[k_tetra])
    world = poses.position[k_tetra] + shapes['tetra'].points @ rotation.reshape(3, 3).T
    assert world.shape == (3 * 4, 3)                            # four faces
    expected_vertices = vertices + [1.0, 2.0, 3.0]
    for corner in expected_vertices:
        assert np.min(np.linalg.norm(world - corner, axis=1)) < 1e-6
    for point in world:
        assert np.min(np.linalg.norm(expected_vertices - point, axis=1)) < 1e-6


def test_forward_gives_the_poses_of_the_state_after_a_step():
    """After mj_step the data's geom poses are those of the state before it; `forward`
    computes those of the current state (what the simulator publishes) and leaves data be."""
    arm = ArmModel(load_task('reach_over_obstacle'))
    arm.reset(arm.task.tau_default)
    scene = Scene(arm.model)
    for _ in range(20):
        arm.step(np.array([30.0, -20.0, 10.0]))
    stale = scene.poses(arm.data).position
    reference = mujoco.MjData(arm.model)
    reference.qpos[:], reference.mocap_pos[:] = arm.data.qpos, arm.data.mocap_pos
    mujoco.mj_forward(arm.model, reference)
    current = scene.poses(scene.forward(arm.data)).position
    np.testing.assert_allclose(current, scene.poses(reference).position, atol=TOL)
    assert np.abs(current - stale).max() > 1e-3                 # the arm moved in the step
    np.testing.assert_array_equal(scene.poses(arm.data).position, stale)
