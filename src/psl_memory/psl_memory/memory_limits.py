"""What one request may make the skill memory hold: the bounds, defaults written once.

Without them one request could exhaust the node (measured before: an 8 MB add_sample creating
a skill of 10^6 policy parameters held the service lock 20.9 s and grew the node to 4.1 GB; a
1 MB skill name made every info answer 1 MB; ranges of +-1e308 made a skill that answered 0
for every tau), and a memory could be saved into a file the node then refused to read. Each
bound is a parameter of the skill_memory node (`psl_memory.skill_memory_node`). Imports no ROS.
"""
from __future__ import annotations

import dataclasses
from dataclasses import field

MAX_FILE_BYTES = 256 * 2**20     # a memory file, and the arrays it declares, at most this big
ARRAYS_PER_SKILL = 40            # a skill's state is 33 arrays in a memory file


@dataclasses.dataclass(frozen=True)
class MemoryLimits:
    """Bounds of a skill memory (`SkillMemory.check_*` refuse what exceeds them)."""

    max_name_length: int = field(default=256, metadata={'doc': 'characters of a skill name'})
    max_skills: int = field(default=200, metadata={'doc': 'skills in one memory'})
    max_tau_dim: int = field(default=64, metadata={'doc': 'task parameters of a skill'})
    max_theta_dim: int = field(default=20_000, metadata={'doc': 'policy parameters of a skill'})
    max_samples: int = field(default=100_000, metadata={'doc': 'samples of one skill'})
    max_magnitude: float = field(default=1e9, metadata={'doc': (
        "|a range's end|, |a theta reference entry|")})
    max_file_bytes: int = field(default=MAX_FILE_BYTES, metadata={'doc': (
        'bytes of a memory file read or written (and of its arrays)')})

    def __post_init__(self):
        for bound in dataclasses.fields(self):
            value = getattr(self, bound.name)
            if not value > 0:
                raise ValueError(f'{bound.name} must be > 0, got {value!r}')

    @property
    def max_file_arrays(self) -> int:
        """Arrays a memory file may hold: the header and max_skills skills' states (a file
        of 99,000 junk arrays took 37.8 s to load before this bound)."""
        return 1 + ARRAYS_PER_SKILL * self.max_skills
