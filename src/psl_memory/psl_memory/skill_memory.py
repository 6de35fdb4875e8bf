"""The skill memory: named parameterized skills, saved and loaded as one versioned file.

Skills are created with known ranges (a task's tau ranges, theta around the task's default
policy: whoever knows the task passes them, the memory knows no tasks) or by their first sample, whose sizes then fix the skill's
dimensions. `save` writes atomically (temporary file + rename); `load` checks the file's format
and version and every array before it replaces anything, so a corrupt, truncated or
other-version file is refused with a clear error and the memory in use stays as it was.
Imports no ROS.
"""
from __future__ import annotations

import json
import os
import stat
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from psl_memory.elm import RangeScaler
from psl_memory.parameterized_skill import ParameterizedSkill, scaler_around
from psl_memory.skill_config import SkillConfig

FORMAT = 'psl-skill-memory'
VERSION = 1
MAX_FILE_BYTES = 256 * 2**20     # a memory file, and the arrays it declares, at most this big
MAX_MEMBERS = 100_000            # arrays in one file


class MemoryFileError(ValueError):
    """A memory file that cannot be read: missing, corrupt, truncated or another version."""


class SkillMemory:
    """Named skills with one configuration (hyper-parameters) for all of them."""

    def __init__(self, config: SkillConfig = SkillConfig()):
        self.config = config
        self.skills: dict[str, ParameterizedSkill] = {}

    def create(self, name: str, tau_low, tau_high, theta_reference,
               exist_ok: bool = False, replace: bool = False) -> ParameterizedSkill:
        """A skill with known tau ranges (e.g. a task's) and a theta reference (its default
        policy, which theta is normalised around); with `replace` an existing skill of that
        name is replaced by the new, empty one.

        Raises:
            ValueError: no name, bad ranges or reference, or a skill of that name exists (with
                ``exist_ok``: only if its sizes differ; otherwise it is returned as it is).
        """
        if not name or not name.strip():
            raise ValueError('a skill needs a name')
        tau_scaler = RangeScaler(tau_low, tau_high)
        theta_scaler = scaler_around(theta_reference)
        if tau_scaler.dim == 0 or theta_scaler.dim == 0:
            raise ValueError('a skill needs at least one task and one policy parameter')
        if name in self.skills and not replace:
            skill = self.skills[name]
            if not exist_ok:
                raise ValueError(f'skill {name!r} exists already')
            if (skill.tau_dim, skill.theta_dim) != (tau_scaler.dim, theta_scaler.dim):
                raise ValueError(f'skill {name!r} exists with {skill.tau_dim} task and '
                                 f'{skill.theta_dim} policy parameters, not {tau_scaler.dim} '
                                 f'and {theta_scaler.dim}')
            return skill
        skill = ParameterizedSkill(name, tau_scaler, theta_scaler, self.config, bounded=True)
        self.skills[name] = skill
        return skill

    def get(self, name: str) -> ParameterizedSkill:
        if name not in self.skills:
            known = ', '.join(sorted(self.skills)) or 'none yet'
            raise KeyError(f'unknown skill {name!r}; known skills: {known}')
        return self.skills[name]

    def add(self, name: str, tau, theta) -> int:
        """Add a sample; an unknown skill is created by it (ranges around this sample)."""
        if name not in self.skills:
            if not name or not name.strip():
                raise ValueError('a skill needs a name')
            tau = np.asarray(tau, dtype=float)
            theta = np.asarray(theta, dtype=float)
            if tau.ndim != 1 or theta.ndim != 1 or tau.size == 0 or theta.size == 0:
                raise ValueError('the first sample of a skill needs non-empty tau and theta')
            if not (np.all(np.isfinite(tau)) and np.all(np.isfinite(theta))):
                raise ValueError('tau and theta must be finite')
            skill = ParameterizedSkill(name, scaler_around(tau), scaler_around(theta),
                                       self.config)
            count = skill.add(tau, theta)
            self.skills[name] = skill
            return count
        return self.skills[name].add(tau, theta)

    def info(self) -> dict:
        return {name: {'tau_dim': s.tau_dim, 'theta_dim': s.theta_dim,
                       'num_samples': s.num_samples, 'readout': s.config.readout,
                       'associative': s.config.associative}
                for name, s in sorted(self.skills.items())}

    # -- persistence --------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write every skill to one file, atomically (temp file in the same folder + rename)."""
        path = Path(path)
        meta = {'format': FORMAT, 'version': VERSION,
                'config': dataclass_dict(self.config), 'skills': sorted(self.skills)}
        arrays = {'__meta__': np.array(json.dumps(meta))}
        for index, name in enumerate(meta['skills']):      # by index: any name is safe
            for key, value in self.skills[name].get_state().items():
                arrays[f'skill{index}/{key}'] = np.asarray(value)
        write_npz_atomically(path, arrays)

    @classmethod
    def read(cls, path: str | Path, max_bytes: int = MAX_FILE_BYTES) -> 'SkillMemory':
        """A new memory from a file; raises MemoryFileError saying what is wrong with it.

        The file is opened without following a symbolic link and must be a regular file; its
        size and the sizes its archive declares for the arrays are checked against
        `max_bytes` before any array is read, so a crafted file (a zip of gigabytes of zeros)
        is refused at once, at a bounded memory cost."""
        path = Path(path)
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)   # a FIFO: no wait
        except FileNotFoundError:
            raise MemoryFileError(f'{path}: no such file') from None
        except OSError as exc:
            raise MemoryFileError(f'{path}: cannot be opened as a file ({exc.strerror})') from exc
        status = os.fstat(fd)
        if not stat.S_ISREG(status.st_mode):
            os.close(fd)
            raise MemoryFileError(f'{path}: is a directory, not a memory file'
                                  if stat.S_ISDIR(status.st_mode) else
                                  f'{path}: not a regular file (a device, FIFO or socket)')
        with os.fdopen(fd, 'rb') as f:
            if status.st_size > max_bytes:
                raise MemoryFileError(f'{path}: {status.st_size} bytes, more than the limit of '
                                      f'{max_bytes}')
            try:
                with zipfile.ZipFile(f) as archive:
                    members = archive.infolist()
                    declared = sum(m.file_size for m in members)
                    if len(members) > MAX_MEMBERS or declared > max_bytes:
                        raise MemoryFileError(
                            f'{path}: declares {len(members)} arrays of {declared} bytes in '
                            f'all, more than the limit of {max_bytes} bytes; not read')
                    archive.testzip()                      # every member's CRC
                f.seek(0)
                with np.load(f, allow_pickle=False) as data:
                    arrays = {key: data[key] for key in data.files}
            except MemoryFileError:
                raise
            except Exception as exc:  # noqa: BLE001 - numpy/zipfile raise many kinds
                raise MemoryFileError(f'{path}: not a readable psl memory file '
                                      f'({type(exc).__name__}: {exc})') from exc
        if '__meta__' not in arrays:
            raise MemoryFileError(f'{path}: not a psl memory file (no header)')
        try:
            meta = json.loads(str(arrays.pop('__meta__')))
        except json.JSONDecodeError as exc:
            raise MemoryFileError(f'{path}: corrupt header ({exc})') from exc
        if not isinstance(meta, dict):
            raise MemoryFileError(f'{path}: corrupt header (not a JSON object)')
        if meta.get('format') != FORMAT:
            raise MemoryFileError(f'{path}: format {meta.get("format")!r} is not {FORMAT!r}')
        if meta.get('version') != VERSION:
            raise MemoryFileError(f'{path}: version {meta.get("version")!r}; this psl reads '
                                  f'version {VERSION}')
        try:
            memory = cls(SkillConfig(**meta['config']))
            for index, name in enumerate(meta['skills']):
                prefix = f'skill{index}/'
                state = {k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}
                memory.skills[str(name)] = ParameterizedSkill.from_state(str(name),
                                                                         memory.config, state)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
            raise MemoryFileError(f'{path}: inconsistent content ({exc})') from exc
        return memory


def write_npz_atomically(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """Write arrays as an npz file: a temporary file in the same folder, synced, then
    renamed over `path`, which is never a link, directory, device or FIFO that gets replaced.

    Raises:
        OSError: the folder does not exist, or `path` is not a regular file.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise OSError(f'cannot save to {path}: folder {path.parent} does not exist')
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        with os.fdopen(fd, 'wb') as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        if path.is_symlink() or (path.exists() and not path.is_file()):
            raise OSError(f'cannot save to {path}: not a regular file (a link, directory, '
                          'device or FIFO); it is not replaced')
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def dataclass_dict(config: SkillConfig) -> dict:
    import dataclasses
    return dataclasses.asdict(config)
