"""A measured episode on the control grid: a robot's stamps are its own.

psl's simulator stamps every state exactly on the control grid (``t0 + k * period``). A robot
stamps with its wall clock: jitter, a state late or missing, another rate. The reward, ILC and
the recorded evaluation all work on the grid, so an episode measured off it is interpolated
onto it, per joint, linearly between the two measurements around each grid time (on the grid
the measurement itself: interpolation at a sample point returns the sample). A gap of more
than `max_gap_ns` between measurements inside the episode means the robot's states stopped:
`EpisodeGap`, with where. Imports no ROS.
"""
from __future__ import annotations

import numpy as np


class EpisodeGap(ValueError):
    """The measurements do not cover the episode: a gap, or no measurement at its ends."""


def grid(t0_ns: int, period_ns: int, num_steps: int) -> np.ndarray:
    """The control grid of an episode, int64 (num_steps + 1,)."""
    return t0_ns + period_ns * np.arange(num_steps + 1, dtype=np.int64)


def on_grid(stamps_ns: np.ndarray, rows: np.ndarray, times_ns: np.ndarray,
            max_gap_ns: int) -> np.ndarray:
    """`rows` (M, n) measured at `stamps_ns` (M,), increasing, interpolated at `times_ns` (T,):
    (T, n). EpisodeGap when the measurements leave a stretch of more than `max_gap_ns` of
    [times_ns[0], times_ns[-1]] uncovered (at either end too)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    rows = np.asarray(rows, dtype=float)
    if stamps.size == 0:
        raise EpisodeGap('no measurement in the episode')
    if np.any(np.diff(stamps) <= 0):
        raise ValueError('measurement stamps must increase')
    start, end = int(times_ns[0]), int(times_ns[-1])
    inside = stamps[(stamps >= start) & (stamps <= end)]
    edges = np.concatenate([[start], inside, [end]])
    # a measurement just outside an end covers it as far as the interpolation reaches
    if stamps[0] <= start:
        edges[0] = stamps[stamps <= start][-1]
    if stamps[-1] >= end:
        edges[-1] = stamps[stamps >= end][0]
    gaps = np.diff(edges)
    worst = int(np.argmax(gaps))
    if gaps[worst] > max_gap_ns:
        at = (max(int(edges[worst]), start) - start) * 1e-9
        raise EpisodeGap(f'no joint state for {gaps[worst] * 1e-9:.3f} s from {at:.3f} s into '
                         f'the episode (at most {max_gap_ns * 1e-9:.3f} s allowed)')
    # relative to the start in float seconds: int64 ns do not fit a float's 53 bits exactly
    x = (times_ns - start) * 1e-9
    xp = (stamps - start) * 1e-9
    return np.stack([np.interp(x, xp, rows[:, j]) for j in range(rows.shape[1])], axis=1) \
        if rows.shape[1] else np.empty((len(x), 0))
