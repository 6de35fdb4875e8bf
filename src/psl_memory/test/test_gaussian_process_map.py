"""The Gaussian-process baseline: a smooth function from few samples (better than the library),
the default theta as prior mean, a variance that grows away from the data, and a map that is a
function of its samples (rebuilt from them, it predicts the same bits)."""
import numpy as np
import pytest

from psl_memory.gaussian_process_map import GaussianProcessMap
from psl_memory.nearest_neighbour_library import NearestNeighbourLibrary

LOW, HIGH = np.array([-1.0]), np.array([2.0])
DEFAULT = np.array([0.3, -0.2])


def smooth(tau):
    """A smooth map tau (n, 1) -> theta (n, 2)."""
    t = tau[:, 0]
    return np.c_[np.sin(2.0 * t) + 0.3, 0.5 * t ** 2 - 0.2]


TRAIN = np.linspace(-1.0, 2.0, 10)[:, None]
TEST = np.linspace(-0.95, 1.95, 117)[:, None]


@pytest.fixture(scope='module')
def fitted():
    gp = GaussianProcessMap(LOW, HIGH, DEFAULT)
    gp.extend(TRAIN, smooth(TRAIN))
    return gp


def rms_error(model):
    return np.sqrt(np.mean((np.array([model.query(t) for t in TEST]) - smooth(TEST)) ** 2))


def test_a_smooth_function_from_ten_samples_beats_the_library(fitted):
    library = NearestNeighbourLibrary(LOW, HIGH, DEFAULT)
    library.extend(TRAIN, smooth(TRAIN))
    gp_error, library_error = rms_error(fitted), rms_error(library)
    assert gp_error < 0.2 * library_error
    assert gp_error < 0.01          # of values of size 1: interpolates, not just averages


def test_empty_predicts_the_default_and_far_away_reverts_to_it(fitted):
    empty = GaussianProcessMap(LOW, HIGH, DEFAULT)
    for tau in ([-1.0], [0.5], [2.0]):
        np.testing.assert_array_equal(empty.query(tau), DEFAULT)
    assert empty.kernel is None and np.all(empty.variance([0.5]) > 0)
    np.testing.assert_allclose(fitted.query([40.0]), DEFAULT, atol=1e-6)   # prior mean


def test_the_variance_grows_away_from_the_data(fitted):
    assert fitted.variance(TRAIN[4]).shape == (2,)
    assert np.all(fitted.variance(TRAIN[4]) < fitted.variance([3.5]))
    sparse = GaussianProcessMap(LOW, HIGH, DEFAULT)
    taus = np.array([[-1.0], [-0.5], [0.0], [0.5]])
    sparse.extend(taus, DEFAULT + np.c_[0.4 * taus, 0.1 * taus])   # a line, sampled sparsely
    away = [sparse.variance([t]) for t in (0.5, 1.0, 1.5, 2.0, 3.0)]   # from the last sample
    assert all(np.all(near < far) for near, far in zip(away, away[1:]))
    assert np.all(sparse.variance([-0.25]) < away[1])
    one_sided = GaussianProcessMap(LOW, HIGH, DEFAULT)
    one_sided.extend(TRAIN[:3], smooth(TRAIN[:3]))           # samples at the low end only
    steps = [np.mean(one_sided.variance([t])) for t in (-1.0, 0.0, 1.0, 2.0)]
    assert steps == sorted(steps) and steps[0] < steps[-1]


def test_rebuilt_from_its_samples_it_predicts_the_same_bits():
    one_by_one = GaussianProcessMap(LOW, HIGH, DEFAULT)
    for tau, theta in zip(TRAIN[:6], smooth(TRAIN[:6])):
        one_by_one.add(tau, theta)
    rebuilt = GaussianProcessMap(LOW, HIGH, DEFAULT)
    rebuilt.extend(one_by_one.taus, one_by_one.thetas)
    for tau in TEST[::10]:
        np.testing.assert_array_equal(rebuilt.query(tau), one_by_one.query(tau))
        np.testing.assert_array_equal(rebuilt.variance(tau), one_by_one.variance(tau))


def test_bad_samples_change_nothing(fitted):
    before = fitted.query([0.3])
    for tau, theta in (([0.1, 0.2], DEFAULT), ([np.inf], DEFAULT), ([0.1], [1.0])):
        with pytest.raises(ValueError):
            fitted.add(tau, theta)
    assert fitted.num_samples == len(TRAIN)
    np.testing.assert_array_equal(fitted.query([0.3]), before)
    with pytest.raises(ValueError):
        fitted.query([np.nan])
