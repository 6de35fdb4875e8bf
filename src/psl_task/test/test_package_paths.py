"""package:// URLs resolve to the file a robot description names (psl_task.package_paths)."""
import pytest

from psl_task.package_paths import PackageNotFound, find_package, resolve


def test_a_package_url_resolves_below_the_packages_folder(tmp_path):
    (tmp_path / 'my_robot' / 'meshes').mkdir(parents=True)
    (tmp_path / 'my_robot' / 'meshes' / 'link.stl').write_text('solid x\nendsolid x\n')
    paths = {'my_robot': tmp_path / 'my_robot'}
    want = tmp_path / 'my_robot' / 'meshes' / 'link.stl'
    assert resolve('package://my_robot/meshes/link.stl', paths) == want
    # an empty package name (package:///NAME/...), as TALOS's URDFs write their meshes
    assert resolve('package:///my_robot/meshes/link.stl', paths) == want


def test_talos_full_body_meshes_as_published_are_files():
    """example-robot-data's talos_full_v2.urdf names its meshes package:///example-robot-data/..."""
    from xml.etree import ElementTree

    root = find_package('example-robot-data')
    urdf = root / 'robots' / 'talos_data' / 'robots' / 'talos_full_v2.urdf'
    urls = {m.get('filename') for m in ElementTree.parse(urdf).getroot().iter('mesh')}
    triple = sorted(u for u in urls if u.startswith('package:///'))
    assert triple, 'the URDF no longer writes package:///'
    missing = [u for u in triple if not resolve(u).is_file()]
    assert not missing, missing


def test_an_unknown_package_names_where_it_looked(tmp_path):
    with pytest.raises(PackageNotFound) as caught:
        find_package('no_such_package_here')
    assert caught.value.searched
