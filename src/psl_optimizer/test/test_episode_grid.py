"""episode_grid: a robot's measurements onto the control grid, against closed forms: a
linear function of time is reproduced exactly (up to rounding) from any stamps, samples on
the grid come back as they are, and a gap is found where it is."""

import numpy as np
import pytest

from psl_optimizer.episode_grid import EpisodeGap, grid, on_grid

PERIOD = 2_000_000          # ns, 500 Hz
T0 = 1_764_000_000_123_456_789   # a wall-clock stamp (2025), ns


def test_on_the_grid_the_samples_come_back_exactly():
    times = grid(T0, PERIOD, 50)
    rows = np.random.default_rng(1).normal(size=(51, 3))
    assert np.array_equal(on_grid(times, rows, times, 3 * PERIOD), rows)


def test_a_linear_motion_from_jittered_stamps():
    rng = np.random.default_rng(2)
    stamps = T0 - 2 * PERIOD + np.cumsum(rng.integers(PERIOD // 2, 3 * PERIOD // 2, 80))
    slope, offset = np.array([0.7, -1.3]), np.array([0.1, 2.0])
    seconds = (stamps - T0) * 1e-9
    rows = offset + slope * seconds[:, None]
    times = grid(T0, PERIOD, 60)
    expected = offset + slope * ((times - T0) * 1e-9)[:, None]
    assert np.allclose(on_grid(stamps, rows, times, 3 * PERIOD), expected, rtol=0, atol=1e-12)


def test_a_gap_is_found_where_it_is():
    stamps = np.concatenate([grid(T0, PERIOD, 20), grid(T0 + 40 * PERIOD, PERIOD, 30)])
    rows = np.zeros((len(stamps), 1))
    with pytest.raises(EpisodeGap, match=r'no joint state for 0\.040 s from 0\.040 s'):
        on_grid(stamps, rows, grid(T0, PERIOD, 60), 3 * PERIOD)
    # the end not reached: the states stopped before it
    with pytest.raises(EpisodeGap, match='no joint state for'):
        on_grid(grid(T0, PERIOD, 20), np.zeros((21, 1)), grid(T0, PERIOD, 60), 3 * PERIOD)
    with pytest.raises(EpisodeGap, match='no measurement'):
        on_grid(np.array([], dtype=np.int64), np.zeros((0, 1)), grid(T0, PERIOD, 5), PERIOD)
