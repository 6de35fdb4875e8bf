"""The library baseline: the inverse-distance-weighted mean of the k nearest solved instances,
distances normalised by the tau range; an exact hit is that theta; empty is the default."""
import numpy as np
import pytest

from psl_memory.nearest_neighbour_library import NearestNeighbourLibrary

LOW, HIGH = np.array([0.0, 10.0]), np.array([1.0, 30.0])     # widths 1 and 20
DEFAULT = np.array([0.5, -0.5, 2.0])
TAUS = np.array([[0.1, 12.0], [0.9, 14.0], [0.5, 20.0], [0.2, 28.0], [0.8, 29.0]])
THETAS = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0], [4.0, 4.0, 4.0],
                   [-1.0, 5.0, 2.0]])


def library(k=3, samples=len(TAUS)):
    lib = NearestNeighbourLibrary(LOW, HIGH, DEFAULT, k=k)
    for tau, theta in zip(TAUS[:samples], THETAS[:samples]):
        lib.add(tau, theta)
    return lib


def idw(query, k):
    """The same estimate written out independently: per-axis distance over the range width."""
    dx = (query[0] - TAUS[:, 0]) / 1.0
    dy = (query[1] - TAUS[:, 1]) / 20.0
    d = np.sqrt(dx * dx + dy * dy)
    order = np.argsort(d)[:k]
    w = 1.0 / d[order]
    return (w[:, None] * THETAS[order]).sum(axis=0) / w.sum()


def test_a_two_sample_query_by_hand():
    lib = NearestNeighbourLibrary([0.0], [2.0], [0.0], k=2)
    lib.add([0.0], [4.0])
    lib.add([2.0], [8.0])
    lib.add([2.1], [100.0])           # the third nearest: k = 2 leaves it out
    # tau 0.5: distances 0.25, 0.75 and 0.8 of the range; weights 4 and 4/3 of the two
    # nearest: (4 * 4 + 4/3 * 8) / (16/3) = 5
    assert lib.query([0.5]) == pytest.approx([5.0])


@pytest.mark.parametrize('query', [[0.3, 15.0], [0.55, 22.5], [0.05, 29.9], [0.7, 11.0]])
@pytest.mark.parametrize('k', [1, 3, 5])
def test_query_equals_the_idw_formula(query, k):
    np.testing.assert_allclose(library(k).query(np.array(query)), idw(np.array(query), k),
                               rtol=1e-12)


def test_the_distance_is_normalised_by_the_range():
    """Unnormalised, tau's second entry (range 20) would decide the neighbours alone."""
    query = np.array([0.12, 18.5])
    raw = np.linalg.norm(TAUS - query, axis=1)
    assert np.argmin(raw) == 2                          # [0.5, 20]: 1.5 units away in tau
    lib = library(k=1)
    np.testing.assert_array_equal(lib.query(query), THETAS[0])   # [0.1, 12]: nearer in range


def test_only_the_k_nearest_count():
    lib, moved = library(k=3), library(k=3)
    moved._thetas[4] += 100.0                        # farthest from [0.4, 13] of the five
    query = np.array([0.4, 13.0])
    np.testing.assert_array_equal(lib.query(query), moved.query(query))
    everything, moved_all = library(k=5), library(k=5)
    moved_all._thetas[4] += 100.0                   # with k = 5 it counts
    assert not np.allclose(everything.query(query), moved_all.query(query))


def test_an_exact_hit_is_that_theta_and_empty_is_the_default():
    lib = library()
    for tau, theta in zip(TAUS, THETAS):
        np.testing.assert_array_equal(lib.query(tau), theta)
    lib.add(TAUS[0], THETAS[1])                       # the same tau twice: their mean
    np.testing.assert_allclose(lib.query(TAUS[0]), 0.5 * (THETAS[0] + THETAS[1]))
    empty = NearestNeighbourLibrary(LOW, HIGH, DEFAULT)
    np.testing.assert_array_equal(empty.query([0.5, 20.0]), DEFAULT)
    assert empty.variance([0.5, 20.0]) is None and empty.num_samples == 0


def test_fewer_samples_than_k_use_all_of_them():
    query = np.array([0.3, 15.0])
    d = np.hypot(query[0] - TAUS[:2, 0], (query[1] - TAUS[:2, 1]) / 20.0)
    expected = (THETAS[0] / d[0] + THETAS[1] / d[1]) / (1.0 / d[0] + 1.0 / d[1])
    np.testing.assert_allclose(library(k=3, samples=2).query(query), expected, rtol=1e-12)


def test_extend_equals_adding_one_by_one_and_bad_samples_change_nothing():
    lib = NearestNeighbourLibrary(LOW, HIGH, DEFAULT)
    lib.extend(TAUS, THETAS)
    np.testing.assert_array_equal(lib.taus, library().taus)
    np.testing.assert_array_equal(lib.query([0.3, 15.0]), library().query([0.3, 15.0]))
    for tau, theta in (([0.1], DEFAULT), ([0.1, np.nan], DEFAULT), ([0.1, 12.0], [1.0, 2.0])):
        with pytest.raises(ValueError):
            lib.add(tau, theta)
    assert lib.num_samples == len(TAUS)
    with pytest.raises(ValueError):
        lib.query([0.1, 12.0, 3.0])
    with pytest.raises(ValueError):
        NearestNeighbourLibrary(LOW, HIGH, DEFAULT, k=0)
    with pytest.raises(ValueError):
        NearestNeighbourLibrary(HIGH, LOW, DEFAULT)
