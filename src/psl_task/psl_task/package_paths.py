"""Where ``package://NAME/...`` points: the folder of a robot description package.

ROS robot descriptions name their meshes (and psl task YAMLs may name their model) as
``package://NAME/path``. `find_package` looks for NAME, in this order, in

1. the task's ``robot.package_paths`` (``{NAME: folder}``),
2. ``ROS_PACKAGE_PATH`` (a folder named NAME, or one holding a folder NAME),
3. ``AMENT_PREFIX_PATH`` (``PREFIX/share/NAME``, where colcon and apt install packages),
4. Python's installed packages: an importable package NAME (``-`` read as ``_``, e.g.
   ``gymnasium``'s MuJoCo assets) and cmeel's prefix ``site-packages/cmeel.prefix/share/NAME``
   (where pip installs ROS-style packages such as ``example-robot-data``).

Imports no ROS.
"""
from __future__ import annotations

import importlib.util
import os
import sysconfig
from pathlib import Path

PREFIX = 'package://'


class PackageNotFound(LookupError):
    """NAME is in none of the places searched (`searched` lists them)."""

    def __init__(self, name: str, searched: list[str]):
        self.name, self.searched = name, searched
        super().__init__(f'package {name!r} not found')


def find_package(name: str, package_paths: dict[str, Path] | None = None) -> Path:
    """The folder of package `name` (see the module docstring for the search order).

    Raises:
        PackageNotFound: nowhere; ``searched`` names every place looked at.
    """
    if package_paths and name in package_paths:
        return Path(package_paths[name])
    searched = []
    for root in filter(None, os.environ.get('ROS_PACKAGE_PATH', '').split(':')):
        for candidate in (Path(root), Path(root) / name):
            searched.append(str(candidate))
            if candidate.name == name and candidate.is_dir():
                return candidate
    for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(':')):
        candidate = Path(prefix) / 'share' / name
        searched.append(str(candidate))
        if candidate.is_dir():
            return candidate
    try:
        spec = importlib.util.find_spec(name.replace('-', '_'))
    except (ImportError, ValueError):
        spec = None
    searched.append(f'the Python package {name.replace("-", "_")}')
    if spec is not None and spec.submodule_search_locations:
        return Path(list(spec.submodule_search_locations)[0])
    for key in ('purelib', 'platlib'):
        candidate = Path(sysconfig.get_paths()[key]) / 'cmeel.prefix' / 'share' / name
        if str(candidate) not in searched:
            searched.append(str(candidate))
        if candidate.is_dir():
            return candidate
    raise PackageNotFound(name, searched)


def resolve(url: str, package_paths: dict[str, Path] | None = None) -> Path:
    """``package://NAME/rest`` -> find_package(NAME) / rest (PackageNotFound otherwise).
    ``package:///NAME/rest`` (an empty package name, as TALOS's and others' URDFs in
    example-robot-data write it for a path below a folder of packages, pinocchio's reading)
    is read the same."""
    name, _, rest = url[len(PREFIX):].lstrip('/').partition('/')
    return find_package(name, package_paths) / rest
