"""Readouts of the parameterized skill (eq. 2.5-2.14) against closed-form solutions.

Data: smooth targets of a 2-D task parameter through a random ELM hidden layer (eq. 2.2). Every
incremental readout is held against the batch ridge solution (eq. 2.8) on the same data.
"""
from __future__ import annotations

import numpy as np
import pytest

from psl_memory.bayesian_linear_regression import BayesianLinearRegression
from psl_memory.elm import ELMFeatures, RangeScaler
from psl_memory.incremental_ridge import IncrementalRidge
from psl_memory.readout import Readout
from psl_memory.registry import make_readout
from psl_memory.recursive_least_squares import RecursiveLeastSquares
from psl_memory.ridge_regression import RidgeReadout

N_HIDDEN, N_OUT, N_SAMPLES = 40, 25, 60
# ELM features are strongly correlated (cond(H^T H) ~ 1e17), so the regulariser sets the
# conditioning of every solve: with g = 1e-4, cond(H^T H + g I) ~ 1e7 and the recursions agree
# with the batch solve to ~1e-10 of the weight scale.
REGULARIZATION = 1e-4
WEIGHT_RTOL = 1e-7          # max |W - W_batch| relative to max |W_batch|
VARIANCE_RTOL = 1e-9        # predictive variance vs. explicit S_N
NOISE_STD = 0.1             # for evidence maximisation
BETA_RTOL = 0.2             # beta recovered within 20 % of 1 / NOISE_STD^2
INCREMENTAL = ['rls', 'incremental_ridge', 'bayes']
ALL_NAMES = ['ridge', 'rls', 'incremental_ridge', 'bayes']


def smooth_targets(tau: np.ndarray, n_out: int, rng: np.random.Generator) -> np.ndarray:
    """(n, n_out) random mixtures of smooth functions of tau (n, 2)."""
    basis = np.column_stack([np.ones(len(tau)), tau, tau**2, np.sin(2.0 * tau),
                             tau[:, 0] * tau[:, 1]])                      # (n, 8)
    return basis @ rng.normal(size=(basis.shape[1], n_out))


@pytest.fixture(scope='module')
def features() -> ELMFeatures:
    return ELMFeatures(RangeScaler([-1.0, -1.0], [1.0, 1.0]), N_HIDDEN, seed=3)


@pytest.fixture(scope='module')
def data(features):
    """Hidden states H (N, N_H), targets Y (N, F), query hidden states (20, N_H)."""
    rng = np.random.default_rng(7)
    tau = rng.uniform(-1.0, 1.0, size=(N_SAMPLES, 2))
    queries = features.transform(rng.uniform(-1.0, 1.0, size=(20, 2)))
    return features.transform(tau), smooth_targets(tau, N_OUT, rng), queries


def readout(name: str, **options) -> Readout:
    """Readout `name` whose solution is ridge with REGULARIZATION (bayes: alpha / beta = g)."""
    if name == 'bayes':
        return make_readout(name, N_HIDDEN, N_OUT, prior_precision=REGULARIZATION,
                            noise_precision=1.0, **options)
    return make_readout(name, N_HIDDEN, N_OUT, regularization=REGULARIZATION, **options)


def random_chunks(n: int, rng: np.random.Generator) -> list[slice]:
    """Consecutive slices of random lengths 1..15 covering range(n)."""
    bounds = [0]
    while bounds[-1] < n:
        bounds.append(min(n, bounds[-1] + int(rng.integers(1, 16))))
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]


def assert_weights_close(w: np.ndarray, w_ref: np.ndarray, rtol: float = WEIGHT_RTOL) -> None:
    scale = np.max(np.abs(w_ref))
    assert np.max(np.abs(w - w_ref)) <= rtol * scale, np.max(np.abs(w - w_ref)) / scale


# ---------------------------------------------------------------------- agreement with batch ridge
@pytest.mark.parametrize('name', INCREMENTAL)
def test_one_by_one_equals_batch_ridge(name, data):
    hs, ys, queries = data
    batch = readout('ridge')
    batch.update(hs, ys)
    model = readout(name)
    for h, y in zip(hs, ys):
        model.update(h, y)
    assert model.num_samples == batch.num_samples == N_SAMPLES
    assert_weights_close(model.weights, batch.weights)
    assert_weights_close(model.predict(queries), batch.predict(queries))


@pytest.mark.parametrize('name', INCREMENTAL)
def test_random_chunks_equal_batch_ridge_after_every_chunk(name, data):
    hs, ys, queries = data
    batch, model = readout('ridge'), readout(name)
    for part in random_chunks(N_SAMPLES, np.random.default_rng(11)):
        batch.update(hs[part], ys[part])
        model.update(hs[part], ys[part])
        assert model.num_samples == batch.num_samples
        assert_weights_close(model.weights, batch.weights)
    assert batch.num_samples == N_SAMPLES
    assert_weights_close(model.predict(queries), batch.predict(queries))


def test_ridge_is_the_regularised_normal_equation(data):
    """Eq. 2.8 checked against numpy's dense solve of (H^T H + g I) W = H^T Y."""
    hs, ys, _ = data
    batch = readout('ridge')
    for part in random_chunks(N_SAMPLES, np.random.default_rng(2)):
        batch.update(hs[part], ys[part])
    expected = np.linalg.solve(hs.T @ hs + REGULARIZATION * np.eye(N_HIDDEN), hs.T @ ys)
    assert_weights_close(batch.weights, expected)


def test_rls_with_forgetting_equals_exponentially_weighted_ridge(data):
    """RLS with P(0) = I/g and forgetting lam (eq. 2.5-2.6) keeps
    P(N)^{-1} = lam P(N-1)^{-1} + h_N h_N^T, hence
        P(N)^{-1} = lam^N g I + sum_i lam^(N-i) h_i h_i^T,
    and its weights solve
        W = (sum_i lam^(N-i) h_i h_i^T + lam^N g I)^{-1} sum_i lam^(N-i) h_i y_i^T,
    the minimiser of sum_i lam^(N-i) ||y_i - W^T h_i||^2 + lam^N g ||W||^2."""
    hs, ys, _ = data
    lam, g = 0.95, 1e-2
    weights = lam ** (N_SAMPLES - 1 - np.arange(N_SAMPLES))              # (N,) lam^(N-i)
    gram = (hs * weights[:, None]).T @ hs + lam**N_SAMPLES * g * np.eye(N_HIDDEN)
    expected = np.linalg.solve(gram, (hs * weights[:, None]).T @ ys)     # (N_H, F)

    one_by_one = make_readout('rls', N_HIDDEN, N_OUT, forgetting=lam, regularization=g)
    for h, y in zip(hs, ys):
        one_by_one.update(h, y)
    chunked = make_readout('rls', N_HIDDEN, N_OUT, forgetting=lam, regularization=g)
    for part in random_chunks(N_SAMPLES, np.random.default_rng(5)):
        chunked.update(hs[part], ys[part])
    assert_weights_close(one_by_one.weights, expected)
    assert_weights_close(chunked.weights, expected)
    # forgetting matters here: the unweighted ridge solution is far from it
    plain = make_readout('ridge', N_HIDDEN, N_OUT, regularization=g)
    plain.update(hs, ys)
    assert np.max(np.abs(plain.weights - expected)) > 1e-2 * np.max(np.abs(expected))


# ---------------------------------------------------------------------- Bayesian linear regression
def test_bayes_mean_is_ridge_with_alpha_over_beta(data):
    hs, ys, queries = data
    alpha, beta = 0.05, 20.0
    bayes = BayesianLinearRegression(N_HIDDEN, N_OUT, prior_precision=alpha, noise_precision=beta)
    bayes.update(hs, ys)
    ridge = RidgeReadout(N_HIDDEN, N_OUT, regularization=alpha / beta)
    ridge.update(hs, ys)
    assert_weights_close(bayes.weights, ridge.weights)
    assert_weights_close(bayes.predict(queries), ridge.predict(queries))


def test_bayes_predictive_variance_matches_explicit_posterior(data):
    hs, ys, queries = data
    alpha, beta = 0.05, 20.0
    bayes = BayesianLinearRegression(N_HIDDEN, N_OUT, prior_precision=alpha, noise_precision=beta)
    for part in random_chunks(N_SAMPLES, np.random.default_rng(3)):
        bayes.update(hs[part], ys[part])
    s_n = np.linalg.inv(alpha * np.eye(N_HIDDEN) + beta * hs.T @ hs)     # (N_H, N_H) eq. 2.12
    expected = 1.0 / beta + np.einsum('ni,ij,nj->n', queries, s_n, queries)   # (n,) eq. 2.14
    var = bayes.predict_variance(queries)
    assert var.shape == (len(queries), N_OUT)
    np.testing.assert_allclose(var, np.repeat(expected[:, None], N_OUT, axis=1),
                               rtol=VARIANCE_RTOL)
    single = bayes.predict_variance(queries[0])
    assert single.shape == (N_OUT,)
    np.testing.assert_allclose(single, expected[0], rtol=VARIANCE_RTOL)
    # the mean too: m_N = beta S_N H^T Y
    assert_weights_close(bayes.weights, beta * s_n @ hs.T @ ys)


def test_bayes_variance_is_smallest_near_training_inputs():
    """1-D task parameter in [-2, 2], trained on tau in [-0.5, 0.5]."""
    feats = ELMFeatures(RangeScaler([-2.0], [2.0]), N_HIDDEN, seed=5)
    tau = np.linspace(-0.5, 0.5, 30)[:, None]                            # (30, 1)
    bayes = BayesianLinearRegression(N_HIDDEN, 1, prior_precision=1e-2, noise_precision=100.0)
    bayes.update(feats.transform(tau), np.sin(3.0 * tau))
    on_data = bayes.predict_variance(feats.transform(tau))[:, 0]        # (30,)
    outward = np.linspace(0.5, 2.0, 16)
    right = bayes.predict_variance(feats.transform(outward[:, None]))[:, 0]
    left = bayes.predict_variance(feats.transform(-outward[:, None]))[:, 0]
    assert np.all(np.diff(right) > 0) and np.all(np.diff(left) > 0)
    assert on_data.max() < 0.5 * min(right[5], left[5])                  # |tau| = 1.0
    assert on_data.min() >= 1.0 / bayes.beta


@pytest.mark.parametrize('feed', ['one_by_one', 'chunks'])
def test_evidence_maximisation_recovers_noise_precision(features, feed):
    rng = np.random.default_rng(21)
    n = 300
    tau = rng.uniform(-1.0, 1.0, size=(n, 2))
    clean = np.column_stack([np.sin(2.0 * tau[:, 0]), tau[:, 1]**2, tau[:, 0] * tau[:, 1]])
    ys = clean + NOISE_STD * rng.normal(size=clean.shape)                # (n, 3)
    hs = features.transform(tau)
    bayes = BayesianLinearRegression(N_HIDDEN, 3, prior_precision=1e-6, noise_precision=1.0, estimate=True)
    parts = ([slice(i, i + 1) for i in range(n)] if feed == 'one_by_one'
             else random_chunks(n, np.random.default_rng(4)))
    for part in parts:
        bayes.update(hs[part], ys[part])
        assert np.isfinite(bayes.alpha) and bayes.alpha > 0
        assert np.isfinite(bayes.beta) and bayes.beta > 0
    true_beta = 1.0 / NOISE_STD**2
    assert abs(bayes.beta - true_beta) <= BETA_RTOL * true_beta, bayes.beta
    assert bayes.alpha != 1e-6
    # the estimate is a fixed point: the mean is ridge with alpha / beta
    ridge = RidgeReadout(N_HIDDEN, 3, regularization=bayes.alpha / bayes.beta)
    ridge.update(hs, ys)
    assert_weights_close(bayes.weights, ridge.weights)


def test_evidence_estimate_is_a_fixed_point_of_the_reestimation(features):
    """After an update, alpha and beta satisfy Bishop's eq. 3.92 and 3.95 (F outputs), with
    gamma, ||M||_F and the residuals computed here directly from H and Y."""
    rng = np.random.default_rng(8)
    tau = rng.uniform(-1.0, 1.0, size=(120, 2))
    ys = smooth_targets(tau, 4, rng) + NOISE_STD * rng.normal(size=(120, 4))    # (N, F)
    hs = features.transform(tau)
    bayes = BayesianLinearRegression(N_HIDDEN, 4, estimate=True, tolerance=1e-10)
    bayes.update(hs[:70], ys[:70])
    bayes.update(hs[70:], ys[70:])
    alpha, beta, m = bayes.alpha, bayes.beta, bayes.weights
    lam = beta * np.linalg.eigvalsh(hs.T @ hs)
    gamma = np.sum(lam / (alpha + lam))
    residual = np.sum((ys - hs @ m) ** 2)
    np.testing.assert_allclose(alpha, 4 * gamma / np.sum(m * m), rtol=1e-6)
    np.testing.assert_allclose(beta, (120 * 4 - 4 * gamma) / residual, rtol=1e-6)


def test_evidence_maximisation_keeps_priors_for_a_single_sample(features):
    bayes = BayesianLinearRegression(N_HIDDEN, 3, prior_precision=0.5, noise_precision=2.0, estimate=True)
    bayes.update(features.transform(np.array([0.1, 0.2])), np.array([1.0, -1.0, 0.5]))
    assert (bayes.alpha, bayes.beta) == (0.5, 2.0)


# ---------------------------------------------------------------------- interface and validation
def trained(name: str, data, **options) -> Readout:
    hs, ys, _ = data
    model = readout(name, **options)
    model.update(hs[:30], ys[:30])
    return model


@pytest.mark.parametrize('name', ALL_NAMES)
def test_prediction_shapes(name, data):
    _, _, queries = data
    model = trained(name, data)
    assert model.predict(queries[0]).shape == (N_OUT,)
    assert model.predict(queries).shape == (len(queries), N_OUT)
    var = model.predict_variance(queries)
    assert (var is None) == (name != 'bayes')


BAD_UPDATES = {   # case: (h, y, fragment of the error message)
    'h too long': (np.zeros(N_HIDDEN + 1), np.zeros(N_OUT), 'h must have shape'),
    'y too short': (np.zeros(N_HIDDEN), np.zeros(N_OUT - 1), 'y must have shape'),
    'chunk h, single y': (np.zeros((3, N_HIDDEN)), np.zeros(N_OUT), 'y must have shape'),
    'single h, chunk y': (np.zeros(N_HIDDEN), np.zeros((1, N_OUT)), 'y must have shape'),
    'row counts differ': (np.zeros((3, N_HIDDEN)), np.zeros((2, N_OUT)), 'y must have shape'),
    'h 3-D': (np.zeros((1, 3, N_HIDDEN)), np.zeros((3, N_OUT)), 'h must have shape'),
    'empty chunk': (np.zeros((0, N_HIDDEN)), np.zeros((0, N_OUT)), 'at least one sample'),
    'NaN in h': (np.r_[np.nan, np.zeros(N_HIDDEN - 1)], np.zeros(N_OUT), 'h contains NaN'),
    'inf in y': (np.zeros((2, N_HIDDEN)), np.full((2, N_OUT), np.inf), 'y contains NaN or inf'),
    'NaN in last chunk row': (np.zeros((4, N_HIDDEN)),
                              np.vstack([np.ones((3, N_OUT)), np.full((1, N_OUT), np.nan)]),
                              'y contains NaN'),
    'not numeric': (np.array(['a'] * N_HIDDEN), np.zeros(N_OUT), 'h must be numeric'),
}


@pytest.mark.parametrize('case', list(BAD_UPDATES))
@pytest.mark.parametrize('name', ALL_NAMES)
def test_bad_update_raises_and_leaves_state_unchanged(name, case, data):
    _, _, queries = data
    model = trained(name, data, **({'estimate': True} if name == 'bayes' else {}))
    before, state = model.predict(queries), model.get_state()
    h, y, message = BAD_UPDATES[case]
    with pytest.raises(ValueError, match=message):
        model.update(h, y)
    np.testing.assert_array_equal(model.predict(queries), before)
    assert model.num_samples == 30
    after = model.get_state()
    for key, value in state.items():
        np.testing.assert_array_equal(after[key], value)


@pytest.mark.parametrize('name', ALL_NAMES)
def test_bad_prediction_inputs_raise(name, data):
    model = trained(name, data)
    for h in (np.zeros(N_HIDDEN - 1), np.zeros((2, N_HIDDEN + 1)), np.full(N_HIDDEN, np.nan),
              np.zeros((1, 1, N_HIDDEN))):
        with pytest.raises(ValueError):
            model.predict(h)
        with pytest.raises(ValueError):
            model.predict_variance(h)


@pytest.mark.parametrize('name', ALL_NAMES)
def test_state_round_trip_is_exact(name, data, tmp_path):
    hs, ys, queries = data
    options = {'estimate': True} if name == 'bayes' else {}
    model = trained(name, data, **options)
    state = model.get_state()
    for key, value in state.items():
        assert isinstance(value, (np.ndarray, int, float, bool)), (key, type(value))
    # through a fresh object with default options, and through numpy's file format
    np.savez(tmp_path / 'state.npz', **state)
    with np.load(tmp_path / 'state.npz') as stored:
        from_file = {key: stored[key] for key in stored.files}
    for restored_state in (state, from_file):
        fresh = make_readout(name, N_HIDDEN, N_OUT)
        fresh.set_state(restored_state)
        assert fresh.num_samples == model.num_samples
        np.testing.assert_array_equal(fresh.predict(queries), model.predict(queries))
        if name == 'bayes':
            np.testing.assert_array_equal(fresh.predict_variance(queries),
                                          model.predict_variance(queries))
        # learning goes on identically
        fresh.update(hs[30:], ys[30:])
        twin = make_readout(name, N_HIDDEN, N_OUT)
        twin.set_state(state)
        twin.update(hs[30:], ys[30:])
        np.testing.assert_array_equal(fresh.predict(queries), twin.predict(queries))
    # the state is a copy: changing it changes nothing
    before = model.predict(queries)
    for value in state.values():
        if isinstance(value, np.ndarray):
            value[...] = 0.0
    np.testing.assert_array_equal(model.predict(queries), before)


@pytest.mark.parametrize('name', ALL_NAMES)
def test_bad_state_is_rejected_and_changes_nothing(name, data):
    _, _, queries = data
    model = trained(name, data)
    before = model.predict(queries)
    good = model.get_state()
    array_key = next(k for k, v in good.items() if isinstance(v, np.ndarray) and v.ndim == 2)
    bad_states = [
        {k: v for k, v in good.items() if k != array_key},                 # missing key
        {**good, 'extra': 1.0},                                            # unknown key
        {**good, array_key: good[array_key][:-1]},                         # wrong shape
        {**good, array_key: np.full_like(good[array_key], np.nan)},        # not finite
        {**good, 'n_hidden': N_HIDDEN + 1},                                # other size
    ]
    for bad in bad_states:
        with pytest.raises(ValueError):
            model.set_state(bad)
        np.testing.assert_array_equal(model.predict(queries), before)


def test_factory_names_and_classes():
    expected = {'ridge': RidgeReadout, 'rls': RecursiveLeastSquares,
                'incremental_ridge': IncrementalRidge, 'bayes': BayesianLinearRegression}
    for name, cls in expected.items():
        model = make_readout(name, 4, 2)
        assert type(model) is cls and model.name == name and isinstance(model, Readout)
        assert (model.n_hidden, model.n_out, model.num_samples) == (4, 2, 0)
        np.testing.assert_array_equal(model.predict(np.ones(4)), np.zeros(2))
    with pytest.raises(ValueError, match='bayes.*incremental_ridge.*ridge.*rls'):
        make_readout('lasso', 4, 2)


@pytest.mark.parametrize('name, options', [
    ('ridge', {'forgetting': 0.9}),
    ('incremental_ridge', {'alpha': 1.0}),
    ('rls', {'estimate': True}),
    ('bayes', {'regularization': 1e-3}),
    ('bayes', {'alpha': 1e-3}),          # the precisions have their names, not the symbols
])
def test_factory_rejects_unknown_options(name, options):
    with pytest.raises(TypeError):
        make_readout(name, 4, 2, **options)


@pytest.mark.parametrize('name, options', [
    ('ridge', {'regularization': 0.0}),
    ('ridge', {'regularization': -1.0}),
    ('incremental_ridge', {'regularization': np.nan}),
    ('rls', {'forgetting': 0.0}),
    ('rls', {'forgetting': 1.01}),
    ('rls', {'regularization': np.inf}),
    ('bayes', {'prior_precision': 0.0}),
    ('bayes', {'noise_precision': -2.0}),
    ('bayes', {'estimate': 'yes'}),
    ('bayes', {'max_iterations': 0}),
])
def test_invalid_option_values_raise(name, options):
    with pytest.raises(ValueError):
        make_readout(name, 4, 2, **options)


@pytest.mark.parametrize('sizes', [(0, 2), (4, 0), (2.5, 2), (True, 2)])
def test_invalid_sizes_raise(sizes):
    with pytest.raises(ValueError):
        make_readout('ridge', *sizes)
