"""COLLADA (.dae) meshes as published, made readable for MuJoCo (which reads STL, OBJ and MSH).

ROS descriptions ship COLLADA meshes, visual and collision alike (the Kinova JACO2 of
example-robot-data: every collision mesh). `stl_of_collada` converts one once, with libraries
made for it (trimesh's COLLADA import, which reads through pycollada: the scene's geometry
with its node transforms, all triangles as one mesh), to a binary STL in a cache folder
(`cache_dir`), and returns the STL's path; `psl_task.model_spec.urdf_text` puts that path in
the URDF MuJoCo compiles.

The file's ``<unit meter="...">`` is applied here (the vertices scaled to metres): trimesh
records it as metadata and leaves the vertices as they are. Its ``<up_axis>`` is not, as
trimesh does not and as the published meshes need: TIAGo's arm_4_collision.dae of
example-robot-data states Y_UP, and read as it is its bounds match those of its STL twin
arm_4.stl within 1 mm, where turning Y up to z would turn it by 90 degrees (checked with
trimesh 5.2.0; 85 of the 262 .dae files there state Y_UP, 177 Z_UP).

The cache: ``$PSL_CACHE_DIR/meshes`` (default ``${XDG_CACHE_HOME:-~/.cache}/psl/meshes``), one
file per .dae's content and converter (the sha256 of the .dae's bytes and `CONVERTER`), written
to a temporary file of the same folder and moved into place with ``os.replace`` (atomic), so
processes converting the same mesh at once each leave a whole file and read a whole file.
Imports no ROS.
"""
from __future__ import annotations

import hashlib
import io
import os
import tempfile
from pathlib import Path

import numpy as np

# what the cached file depends on besides the .dae's bytes: a change here converts anew
CONVERTER_REVISION = 1


class MeshError(ValueError):
    """A .dae that cannot be converted (damaged, no triangles): the message names the file."""


def converter() -> str:
    """The converter's identity, part of each cached file's name: the libraries' versions and
    psl's `CONVERTER_REVISION`."""
    import collada
    import trimesh

    version = getattr(collada, '__version__', '')
    return f'trimesh {trimesh.__version__} pycollada {version} psl {CONVERTER_REVISION}'


def cache_dir() -> Path:
    """The folder of converted meshes: $PSL_CACHE_DIR/meshes, else
    ${XDG_CACHE_HOME:-~/.cache}/psl/meshes."""
    root = os.environ.get('PSL_CACHE_DIR')
    if not root:
        root = str(Path(os.environ.get('XDG_CACHE_HOME') or Path.home() / '.cache') / 'psl')
    return Path(root).expanduser() / 'meshes'


def stl_of_collada(path: Path) -> Path:
    """The binary STL of the COLLADA file `path` (metres: module docstring), converted
    at its first use and cached.

    Raises:
        MeshError: the file cannot be read or converted, or holds no triangles (the message
            names the file and the cause, one line).
    """
    try:
        content = path.read_bytes()
    except OSError as exc:
        raise MeshError(f'cannot read the COLLADA mesh {path}: {exc.strerror or exc}') from None
    digest = hashlib.sha256(content + b'\0' + converter().encode()).hexdigest()
    folder = cache_dir()
    target = folder / f'{digest}.stl'
    if target.is_file():
        return target
    stl = _convert(content, path)
    tmp = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=f'.{digest}.', suffix='.tmp',
                                         delete=False) as tmp:
            tmp.write(stl)
        os.replace(tmp.name, target)        # whole or not at all: never a part at `target`
    except OSError as exc:
        if tmp is not None:
            Path(tmp.name).unlink(missing_ok=True)
        raise MeshError(f'cannot write the STL of the COLLADA mesh {path} to {folder}: '
                        f'{exc.strerror or exc} (set PSL_CACHE_DIR to a writable folder)') \
            from None
    return target


def _convert(content: bytes, path: Path) -> bytes:
    """The STL bytes of a COLLADA file's triangles, in metres."""
    import collada
    import trimesh

    try:
        document = collada.Collada(io.BytesIO(content), ignore=[
            collada.common.DaeUnsupportedError, collada.common.DaeBrokenRefError])
        mesh = trimesh.load(io.BytesIO(content), file_type='dae', force='mesh',
                            process=False)
    except Exception as exc:  # noqa: BLE001 - whatever the COLLADA libraries raise
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise MeshError(f'the COLLADA mesh {path} cannot be read: {reason}') from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshError(f'the COLLADA mesh {path} holds no triangles')
    mesh.apply_scale(_unit(document))
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f'the COLLADA mesh {path} has vertices that are not finite')
    return mesh.export(file_type='stl')


def _unit(document) -> float:
    """Metres per unit of the file's ``<unit meter="...">`` (1 when it gives none)."""
    meter = document.assetInfo.unitmeter
    return 1.0 if meter is None or not float(meter) > 0.0 else float(meter)
