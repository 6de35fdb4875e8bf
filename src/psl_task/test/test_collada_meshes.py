"""COLLADA (.dae) collision meshes as published (`psl_task.meshes`, `psl_task.model_spec`):
converted once by trimesh + pycollada to STL, cached by content, written atomically. A box
exported by trimesh as .dae and as .stl collides alike (the same signed distances and
contacts against a probe within 1e-6 m), also from a file in centimetres (<unit meter=0.01>);
a damaged .dae is refused in one line naming it; the Kinova JACO2 of example-robot-data,
whose collision meshes are all COLLADA, compiles (refused before)."""
import concurrent.futures
import multiprocessing
import re
import textwrap

import mujoco
import numpy as np
import pytest
import trimesh
import yaml

from psl_task import meshes
from psl_task.arm_model import ArmModel
from psl_task.model_spec import task_model
from psl_task.package_paths import find_package
from psl_task.task import TaskError, load_task

EXTENTS = (0.3, 0.08, 0.05)         # m, the box link's size
CM = '<unit name="centimeter" meter="0.01"/>'


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    """Each test converts into a cache folder of its own."""
    monkeypatch.setenv('PSL_CACHE_DIR', str(tmp_path / 'cache'))
    return tmp_path / 'cache' / 'meshes'


def box(scale: float = 1.0) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=[e * scale for e in EXTENTS])
    mesh.apply_translation(np.array([EXTENTS[0] / 2, 0.01, 0.0]) * scale)   # off its origin
    return mesh


def collada(mesh: trimesh.Trimesh, unit: str = '') -> bytes:
    text = trimesh.exchange.dae.export_collada(mesh).decode()
    return text.replace('<asset>', '<asset>' + unit, 1).encode()


def write_task(folder, mesh_file: str, name: str = 'task'):
    """A one-link URDF whose collision mesh is `mesh_file`, and a task on it with a probe
    sphere that collides."""
    (folder / f'{name}.urdf').write_text(textwrap.dedent(f"""\
        <?xml version="1.0"?>
        <robot name="box_arm">
          <link name="base"/>
          <link name="box">
            <inertial><mass value="1.0"/>
              <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>
            <collision><geometry><mesh filename="{mesh_file}"/></geometry></collision>
          </link>
          <joint name="hinge" type="revolute"><parent link="base"/><child link="box"/>
            <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="10" velocity="3"/></joint>
        </robot>
        """))
    data = {'name': name, 'robot': {'model': f'{name}.urdf',
                                    'end_effector': {'body': 'box', 'offset': [0.3, 0, 0]}},
            'scene': [{'name': 'probe', 'type': 'sphere', 'size': [0.02],
                       'position': [0.5, 0.0, 0.0], 'contacts': True}],
            'control_rate': 500.0, 'duration': 1.0, 'start_posture': [0.0],
            'goal_posture': [0.1],
            'task_parameters': [{'name': 'x', 'low': 0.0, 'high': 1.0,
                                 'binds': {'kind': 'mocap_position', 'body': 'probe',
                                           'axis': 0}}],
            'controller': {'kp': [10.0], 'kd': [1.0]}, 'policy': {'n_basis': 3},
            'demonstration': {'times': [0.0, 1.0], 'positions': [[0.0], [0.1]]},
            'reward': {'weights': {'goal_error': 1.0}, 'success_threshold': -1.0}}
    (folder / f'{name}.yaml').write_text(yaml.safe_dump(data))
    return load_task(str(folder / f'{name}.yaml'))


# probe centres in the box link's frame (the box: x 0..0.3, y -0.03..0.05, z -0.025..0.025):
# two outside, then five 1-1.5 cm deep in a face (the probe's radius is 2 cm)
PROBES = [(0.5, 0.0, 0.0), (0.15, 0.0, 0.1), (0.31, 0.0, 0.0), (0.15, 0.06, 0.0),
          (0.1, 0.0, 0.03), (-0.01, 0.02, 0.01), (0.2, -0.04, 0.02)]
ANGLE = 0.4         # rad, the arm's hinge (about z)


def collisions(task) -> list[tuple[float, int, float]]:
    """At each probe position: the signed distance of box and probe (mj_geomDistance), the
    number of contacts and their deepest penetration, the arm at ANGLE."""
    model = task_model(task)
    data = mujoco.MjData(model)
    box_geom = next(g for g in range(model.ngeom)
                    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH)
    probe = model.geom('probe').id
    out = []
    turn = np.array([[np.cos(ANGLE), -np.sin(ANGLE), 0], [np.sin(ANGLE), np.cos(ANGLE), 0],
                     [0, 0, 1]])
    for position in PROBES:
        data.qpos[0] = ANGLE
        data.mocap_pos[0] = turn @ position
        mujoco.mj_forward(model, data)
        distance = mujoco.mj_geomDistance(model, data, box_geom, probe, 1.0, None)
        depth = min((c.dist for c in data.contact[:data.ncon]), default=0.0)
        out.append((distance, data.ncon, depth))
    return out


def test_a_collada_mesh_collides_as_its_stl_twin(tmp_path, cache):
    mesh = box()
    (tmp_path / 'box.stl').write_bytes(mesh.export(file_type='stl'))
    (tmp_path / 'box.dae').write_bytes(collada(mesh))
    (tmp_path / 'box_cm.dae').write_bytes(collada(box(100.0), CM))
    stl = collisions(write_task(tmp_path, 'box.stl', 'stl'))
    assert [n for _, n, _ in stl] == [0, 0, 1, 1, 1, 1, 1]
    for name in ('box.dae', 'box_cm.dae'):
        dae = collisions(write_task(tmp_path, name, name[:-4]))
        assert [n for _, n, _ in dae] == [n for _, n, _ in stl]
        np.testing.assert_allclose(np.array(dae)[:, [0, 2]], np.array(stl)[:, [0, 2]],
                                   rtol=0, atol=1e-6)
    assert len(list(cache.glob('*.stl'))) == 2 and not list(cache.glob('.*'))


def test_each_mesh_is_converted_once(tmp_path, cache, monkeypatch):
    (tmp_path / 'box.dae').write_bytes(collada(box()))
    first = meshes.stl_of_collada(tmp_path / 'box.dae')
    assert first.parent == cache and len(first.stem) == 64          # a sha256
    monkeypatch.setattr(meshes, '_convert', lambda *a: pytest.fail('converted again'))
    assert meshes.stl_of_collada(tmp_path / 'box.dae') == first
    monkeypatch.setattr(meshes, 'CONVERTER_REVISION', meshes.CONVERTER_REVISION + 1)
    with pytest.raises(pytest.fail.Exception, match='converted again'):
        meshes.stl_of_collada(tmp_path / 'box.dae')       # another converter: another file


def test_a_write_that_fails_leaves_nothing_behind(tmp_path, cache, monkeypatch):
    """The STL reaches its name whole (os.replace) or not at all, and the temporary file
    goes: a later run converts anew instead of reading a part."""
    (tmp_path / 'box.dae').write_bytes(collada(box()))

    def disk_full(*args):
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(meshes.os, 'replace', disk_full)
    with pytest.raises(meshes.MeshError, match='No space left on device'):
        meshes.stl_of_collada(tmp_path / 'box.dae')
    assert list(cache.iterdir()) == []


def _convert_in_a_process(path):
    return str(meshes.stl_of_collada(path)), meshes.stl_of_collada(path).read_bytes()


def test_processes_converting_at_once_each_get_a_whole_file(tmp_path, cache):
    (tmp_path / 'box.dae').write_bytes(collada(box()))
    context = multiprocessing.get_context('fork')
    with concurrent.futures.ProcessPoolExecutor(4, mp_context=context) as pool:
        results = list(pool.map(_convert_in_a_process, [tmp_path / 'box.dae'] * 4))
    assert len({path for path, _ in results}) == 1
    expected = box().export(file_type='stl')
    for _, content in results:
        loaded = trimesh.load(trimesh.util.wrap_as_stream(content), file_type='stl')
        np.testing.assert_allclose(loaded.bounds, trimesh.load(
            trimesh.util.wrap_as_stream(expected), file_type='stl').bounds, atol=1e-7)
    assert [p.name for p in cache.iterdir()] == [results[0][0].rsplit('/', 1)[1]]


def _without_geometry() -> bytes:
    """A well-formed COLLADA file whose scene instances no geometry."""
    text = collada(box()).decode()
    return re.sub(r'<instance_geometry.*?</instance_geometry>', '', text, flags=re.S).encode()


@pytest.mark.parametrize('content, words', [
    (b'<COLLADA/>', 'cannot be read'), (b'not xml at all', 'cannot be read'),
    (b'', 'cannot be read'), (_without_geometry(), 'holds no triangles')])
def test_a_damaged_collada_mesh_is_refused_naming_it(tmp_path, content, words):
    (tmp_path / 'broken.dae').write_bytes(content)
    with pytest.raises(TaskError, match=r"the collision mesh of link 'box': the COLLADA "
                                        rf'mesh .*broken\.dae {words}') as error:
        task_model(write_task(tmp_path, 'broken.dae'))
    assert '\n' not in str(error.value)


def test_a_stated_up_axis_is_left_as_published():
    """TIAGo's arm_4_collision.dae states Y_UP; read as it is it lies where its STL twin
    arm_4.stl lies (turning Y up to z would not)."""
    arm = find_package('example-robot-data') / 'robots' / 'tiago_description' / 'meshes' / 'arm'
    assert b'<up_axis>Y_UP</up_axis>' in (arm / 'arm_4_collision.dae').read_bytes()
    converted = trimesh.load(meshes.stl_of_collada(arm / 'arm_4_collision.dae'))
    twin = trimesh.load(arm / 'arm_4.stl')
    np.testing.assert_allclose(converted.bounds, twin.bounds, atol=1e-3)


def test_the_kinova_jaco2_as_published_compiles(tmp_path):
    joints = [f'j2s6s200_joint_{k}' for k in range(1, 7)]
    posture = [0.0, 2.9, 1.3, 0.0, 2.0, 0.0]
    data = {'name': 'jaco2',
            'robot': {'model': 'package://example-robot-data/robots/kinova_description/'
                               'robots/kinova.urdf',
                      'end_effector': {'body': 'j2s6s200_link_6'}, 'joints': joints},
            'control_rate': 500.0, 'duration': 1.0, 'start_posture': posture,
            'goal_posture': posture,
            'task_parameters': [{'name': 'x', 'low': 0.0, 'high': 1.0,
                                 'binds': {'kind': 'target_position', 'axis': 0}}],
            'target': {'position': [0.0, 0.0, 0.0]},
            'controller': {'kp': [10.0] * 6, 'kd': [1.0] * 6}, 'policy': {'n_basis': 3},
            'demonstration': {'times': [0.0, 1.0], 'positions': [posture, posture]},
            'reward': {'weights': {'goal_error': 1.0}, 'success_threshold': -1.0}}
    (tmp_path / 'jaco2.yaml').write_text(yaml.safe_dump(data))
    arm = ArmModel(load_task(str(tmp_path / 'jaco2.yaml')))
    m = arm.model
    assert arm.joint_names == joints
    colliding = [g for g in range(m.ngeom) if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
                 and m.geom_contype[g]]
    assert len(colliding) >= 10          # the links' and fingers' COLLADA collision meshes
