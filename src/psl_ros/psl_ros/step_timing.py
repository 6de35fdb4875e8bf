"""Where a control step's time goes: per-phase durations of a loop, summarised per episode.

The simulator times the phases of each lockstep step with `time.perf_counter_ns` (a few
hundred nanoseconds per step in all) and reports their medians with each episode's end on
``/diagnostics`` (keys ``step_<phase>_us``); ``psl bench graph`` prints them beside the bare
round trip of the same run. Imports no ROS.
"""
from __future__ import annotations

import statistics


class StepTiming:
    """Durations [ns] of named phases, one sample per step and phase, until `clear`."""

    def __init__(self, phases: tuple[str, ...]):
        self.phases = phases
        self._samples: dict[str, list[int]] = {phase: [] for phase in phases}

    def add(self, phase: str, nanoseconds: int) -> None:
        """One sample of `phase` (KeyError for a phase not named at construction)."""
        self._samples[phase].append(nanoseconds)

    def medians_us(self) -> dict[str, float]:
        """Median [us] of each phase with samples (phases without any are left out)."""
        return {phase: 1e-3 * statistics.median(samples)
                for phase, samples in self._samples.items() if samples}

    def clear(self) -> None:
        for samples in self._samples.values():
            samples.clear()
