"""The skill memory: named parameterized skills, saved and loaded as one versioned file.

Skills are created with known ranges (a task's tau ranges, theta around the task's default
policy: whoever knows the task passes them, the memory knows no tasks) or by their first sample, whose sizes then fix the skill's
dimensions. `save` writes atomically (temporary file + rename); `load` checks the file's format
and version and every array before it replaces anything, so a corrupt, truncated or
other-version file is refused with a clear error and the memory in use stays as it was.
What a memory may hold is bounded (`psl_memory.memory_limits`): names, skills, dimensions,
samples, magnitudes; a file is written only if it can be read back within the same bounds.
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
from psl_memory.memory_limits import MAX_FILE_BYTES, MemoryLimits
from psl_memory.parameterized_skill import ParameterizedSkill, scaler_around
from psl_memory.skill_config import SkillConfig

FORMAT = 'psl-skill-memory'
VERSION = 1
FULL = 0.9      # share of max_file_bytes a memory's state may take before it takes no sample


class MemoryFileError(ValueError):
    """A memory file that cannot be read: missing, corrupt, truncated or another version."""


class SkillMemory:
    """Named skills with one configuration (hyper-parameters) for all of them."""

    def __init__(self, config: SkillConfig = SkillConfig(),
                 limits: MemoryLimits = MemoryLimits()):
        self.config, self.limits = config, limits
        self.skills: dict[str, ParameterizedSkill] = {}
        self._bytes: dict[str, int] = {}     # skill -> bytes of its state (after its last add)

    # -- bounds -------------------------------------------------------------------------------
    def check_new_skill(self, name: str, tau_dim: int, theta_dim: int) -> None:
        """ValueError when a skill of this name and these sizes may not be made."""
        limits = self.limits
        if not isinstance(name, str) or not name.strip():
            raise ValueError('a skill needs a name')
        if len(name) > limits.max_name_length:
            raise ValueError(f'a skill name of {len(name)} characters: at most '
                             f'{limits.max_name_length} (max_name_length)')
        if name not in self.skills and len(self.skills) >= limits.max_skills:
            raise ValueError(f'the memory holds {len(self.skills)} skills, the most it may '
                             f'(max_skills)')
        if tau_dim > limits.max_tau_dim:
            raise ValueError(f'{tau_dim} task parameters: at most {limits.max_tau_dim} '
                             '(max_tau_dim)')
        if theta_dim > limits.max_theta_dim:
            raise ValueError(f'{theta_dim} policy parameters: at most {limits.max_theta_dim} '
                             '(max_theta_dim)')

    def check_magnitudes(self, what: str, values: np.ndarray) -> None:
        """ValueError when an entry's magnitude exceeds max_magnitude (or is not finite)."""
        values = np.asarray(values, dtype=float)
        if not np.all(np.isfinite(values)):
            raise ValueError(f'{what} must be finite')
        if values.size and np.abs(values).max() > self.limits.max_magnitude:
            raise ValueError(f'{what} holds {np.abs(values).max():g}, more than '
                             f'{self.limits.max_magnitude:g} (max_magnitude): a units or '
                             'scaling error')

    def check_room(self, name: str) -> None:
        """ValueError when skill `name` may take no further sample: max_samples, or the
        memory's state near max_file_bytes (its file must stay readable)."""
        skill = self.skills.get(name)
        if skill is not None and skill.num_samples >= self.limits.max_samples:
            raise ValueError(f'skill {name!r} holds {skill.num_samples} samples, the most it '
                             'may (max_samples)')
        held = sum(self._bytes.values())
        if held > FULL * self.limits.max_file_bytes:
            raise ValueError(f'the memory holds {held} bytes, {100 * FULL:.0f} % of what its '
                             f'file may hold ({self.limits.max_file_bytes} bytes, '
                             'max_file_bytes): it takes no further sample')

    def _measure(self, name: str) -> None:
        """Note the bytes of a skill's state (as saved)."""
        if name in self.skills:
            self._bytes[name] = sum(np.asarray(v).nbytes
                                    for v in self.skills[name].get_state().values())
        else:
            self._bytes.pop(name, None)

    def create(self, name: str, tau_low, tau_high, theta_reference,
               exist_ok: bool = False, replace: bool = False) -> ParameterizedSkill:
        """A skill with known tau ranges (e.g. a task's) and a theta reference (its default
        policy, which theta is normalised around); with `replace` an existing skill of that
        name is replaced by the new, empty one.

        Raises:
            ValueError: no name, bad ranges or reference, or a skill of that name exists (with
                ``exist_ok``: only if its sizes differ; otherwise it is returned as it is).
        """
        self.check_new_skill(name, np.size(tau_low), np.size(theta_reference))
        for what, values in (('tau_low', tau_low), ('tau_high', tau_high),
                             ('theta_reference', theta_reference)):
            self.check_magnitudes(what, values)
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
        self._measure(name)
        return skill

    def get(self, name: str) -> ParameterizedSkill:
        if name not in self.skills:
            known = ', '.join(sorted(self.skills)) or 'none yet'
            raise KeyError(f'unknown skill {name!r}; known skills: {known}')
        return self.skills[name]

    def add(self, name: str, tau, theta) -> int:
        """Add a sample; an unknown skill is created by it (ranges around this sample).
        Raises ValueError, changing nothing, for a bad sample or one beyond the limits."""
        self.check_room(name)
        if name not in self.skills:
            tau = np.asarray(tau, dtype=float)
            theta = np.asarray(theta, dtype=float)
            self.check_new_skill(name, tau.size, theta.size)
            if tau.ndim != 1 or theta.ndim != 1 or tau.size == 0 or theta.size == 0:
                raise ValueError('the first sample of a skill needs non-empty tau and theta')
            self.check_magnitudes('tau', tau)
            self.check_magnitudes('theta', theta)
            skill = ParameterizedSkill(name, scaler_around(tau), scaler_around(theta),
                                       self.config)
            count = skill.add(tau, theta)
            self.skills[name] = skill
        else:
            count = self.skills[name].add(tau, theta)
        self._measure(name)
        return count

    def merge(self, other: 'SkillMemory', replace: bool = False) -> list[str]:
        """Take the skills of `other` (a memory read from a file); skills only this memory
        holds are kept. Returns the names taken.

        Raises:
            ValueError, changing nothing: a name this memory holds already (unless
            `replace`), or more skills than max_skills.
        """
        clash = sorted(set(other.skills) & set(self.skills))
        if clash and not replace:
            raise ValueError(f'the memory holds skill(s) {", ".join(map(repr, clash))} '
                             'already; load with replace to replace them (psl memory load --replace)')
        if len(set(self.skills) | set(other.skills)) > self.limits.max_skills:
            raise ValueError(f'the memory would hold more than {self.limits.max_skills} skills '
                             '(max_skills)')
        for name, skill in other.skills.items():
            self.check_new_skill(name, skill.tau_dim, skill.theta_dim)
        for name, skill in other.skills.items():
            self.skills[name] = skill
            self._bytes[name] = other._bytes.get(name, 0)
        return sorted(other.skills)

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
        write_npz_atomically(path, arrays, self.limits.max_file_bytes)

    @classmethod
    def read(cls, path: str | Path, max_bytes: int = MAX_FILE_BYTES,
             limits: MemoryLimits | None = None) -> 'SkillMemory':
        """A new memory from a file; raises MemoryFileError saying what is wrong with it.

        The file is opened without following a symbolic link and must be a regular file; its
        size and the sizes its archive declares for the arrays are checked against
        `max_bytes` before any array is read, so a crafted file (a zip of gigabytes of zeros)
        is refused at once, at a bounded memory cost. With `limits`, the number of arrays,
        of skills and their sizes are held to them too (and `max_bytes` is theirs)."""
        path = Path(path)
        limits = limits or MemoryLimits(max_file_bytes=max_bytes)
        max_bytes = limits.max_file_bytes
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
                    if len(members) > limits.max_file_arrays or declared > max_bytes:
                        raise MemoryFileError(
                            f'{path}: declares {len(members)} arrays of {declared} bytes in '
                            f'all, more than the limits of {limits.max_file_arrays} arrays '
                            f'and {max_bytes} bytes; not read')
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
            memory = cls(SkillConfig(**meta['config']), limits)
            for index, name in enumerate(meta['skills']):
                prefix = f'skill{index}/'
                state = {k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}
                skill = ParameterizedSkill.from_state(str(name), memory.config, state)
                memory.check_new_skill(str(name), skill.tau_dim, skill.theta_dim)
                memory.skills[str(name)] = skill
                memory._measure(str(name))
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
            raise MemoryFileError(f'{path}: inconsistent content ({exc})') from exc
        return memory


def write_npz_atomically(path: str | Path, arrays: dict[str, np.ndarray],
                         max_bytes: int | None = None) -> None:
    """Write arrays as an npz file: a temporary file in the same folder, synced, then
    renamed over `path`, which is never a link, directory, device or FIFO that gets replaced.
    With `max_bytes`, a file larger than that (one that would not be read back) is not
    written.

    Raises:
        OSError: the folder does not exist, `path` is not a regular file, or the file would
        be larger than `max_bytes`.
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
            size = f.tell()
        if max_bytes is not None and size > max_bytes:
            raise OSError(f'cannot save to {path}: the file would hold {size} bytes, more '
                          f'than a memory file may ({max_bytes}, max_file_bytes): it could '
                          'not be loaded again')
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
