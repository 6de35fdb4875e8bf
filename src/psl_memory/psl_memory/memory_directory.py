"""The one folder a skill memory node reads and writes its memory files in.

A request names a file by a name or a path inside the folder (relative to it, or absolute).
Refused, with a message saying why and nothing created, replaced or read: a path that leads
outside the folder (``..``, an absolute path elsewhere), one with a symbolic link anywhere
below the folder (a link could lead out, or its target be replaced), and a file that is not a
regular file (a directory, device, FIFO or socket). Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import os
import stat
from dataclasses import field
from pathlib import Path


@dataclasses.dataclass(frozen=True)
class MemoryFiles:
    """Where the skill_memory node keeps its files (its parameters beside `SkillConfig` and
    `MemoryLimits`)."""

    memory_dir: str = field(default='', metadata={'doc': (
        "the folder of the memory files ('' = the working directory); save, load and "
        'autosave stay inside it')})
    autosave_path: str = field(default='', metadata={'doc': (
        'memory file (inside memory_dir) loaded at start and written after every sample; '
        'empty = no autosave')})


class MemoryPathError(ValueError):
    """A memory file path a memory node does not read or write."""


class MemoryDirectory:
    """Resolve names of memory files inside `root` (created if missing)."""

    def __init__(self, root: str | Path):
        self.root = Path(os.path.realpath(Path(root).expanduser()))
        self.root.mkdir(parents=True, exist_ok=True)
        self._aliases = {Path(os.path.abspath(Path(root).expanduser())), self.root}

    def resolve(self, name: str) -> Path:
        """The path of `name` inside the folder (which need not exist yet).

        Raises:
            MemoryPathError: no name, a path outside the folder, or a symbolic link on the way.
        """
        if not name or not str(name).strip():
            raise MemoryPathError(f'give a file name (files live in {self.root})')
        given = Path(os.path.normpath(name))
        relative = None
        if not given.is_absolute():
            relative = given
        else:
            for alias in self._aliases:
                if given == alias or alias in given.parents:
                    relative = given.relative_to(alias)
                    break
        if relative is None or relative.parts[:1] == ('..',) or relative == Path('.'):
            raise MemoryPathError(f'{name}: outside the memory folder {self.root}; give a file '
                                  'name or a path inside it')
        path = self.root
        for part in relative.parts:
            path = path / part
            if path.is_symlink():
                raise MemoryPathError(f'{name}: {path} is a symbolic link; memory files are '
                                      'read and written without following links')
        return path

    def for_reading(self, name: str) -> Path:
        """An existing regular file inside the folder. Raises MemoryPathError."""
        path = self.resolve(name)
        try:
            mode = os.lstat(path).st_mode
        except FileNotFoundError:
            raise MemoryPathError(f'{name}: no such file in {self.root}') from None
        if stat.S_ISDIR(mode):
            raise MemoryPathError(f'{name}: is a directory, not a memory file')
        if not stat.S_ISREG(mode):
            raise MemoryPathError(f'{name}: not a regular file (a device, FIFO or socket)')
        return path

    def for_writing(self, name: str) -> Path:
        """A path inside the folder that is absent or a regular file; its folder is created
        (inside this one). Raises MemoryPathError."""
        path = self.resolve(name)
        if path.exists() or path.is_symlink():
            mode = os.lstat(path).st_mode
            if stat.S_ISDIR(mode):
                raise MemoryPathError(f'{name}: is a directory; give a file name')
            if not stat.S_ISREG(mode):
                raise MemoryPathError(f'{name}: not a regular file (a device, FIFO or socket); '
                                      'it is not replaced')
        path.parent.mkdir(parents=True, exist_ok=True)
        return path
