"""Tests of the associative skill memories AELM (eq. 2.20-2.21) and ARBF (eq. 2.22).

Data: an invertible smooth map tau -> theta (E = 1, F = 6); theta_2 = tau^2 is strictly
monotonic on [0, 1], so theta determines tau. 20 stored patterns, tau evenly spaced in [0, 1];
held-out taus are the midpoints between them. Errors are max-abs in normalised units ([-1, 1]
per entry of v).
"""

import numpy as np
import pytest

from psl_memory.aelm import AELM
from psl_memory.arbf import ARBF
from psl_memory.associative_memory import AssociativeMemory, CompletionResult, clamped_recall
from psl_memory.elm import RangeScaler

E, F = 1, 6
D = E + F
N_TRAIN = 20
# Measured with these settings (AELM seed 0 / worst of AELM seeds 0-19 / ARBF):
TOL_FIXED_POINT = 0.04  # |v_hat(v_i) - v_i| of stored patterns (0.009 / 0.025 / 0.0006)
TOL_THETA = 0.05  # theta from tau, held out (0.012 / 0.045 / 0.009)
TOL_TAU = 0.01  # tau from theta, held out (0.0005 / 0.0009 / 0.0004)
TOL_INCREMENTAL = 1e-9  # one-at-a-time vs batch add, W_out

TAU_IDX = np.arange(D) < E  # known mask for tau -> theta
THETA_IDX = ~TAU_IDX  # known mask for theta -> tau


def theta_of(tau: np.ndarray) -> np.ndarray:
    """(n,) -> (n, F)."""
    tau = np.atleast_1d(tau)
    return np.stack([np.sin(2 * tau), tau**2, np.cos(3 * tau), np.exp(-tau), tau**3 - tau,
                     0.5 * np.sin(5 * tau)], axis=-1)


def patterns_of(tau: np.ndarray) -> np.ndarray:
    """v = [tau, theta]: (n,) -> (n, D)."""
    return np.column_stack([tau, theta_of(tau)])


TAU_TRAIN = np.linspace(0.0, 1.0, N_TRAIN)
TAU_HELD_OUT = 0.5 * (TAU_TRAIN[:-1] + TAU_TRAIN[1:])
V_TRAIN = patterns_of(TAU_TRAIN)  # (N_TRAIN, D)
SCALER = RangeScaler.fit(V_TRAIN, margin=0.1)

MAKERS = {
    'aelm': lambda: AELM(SCALER, n_hidden=200, seed=0, modality_sizes=(E, F)),
    'arbf': lambda: ARBF(SCALER, modality_sizes=(E, F)),
}


@pytest.fixture(scope='module', params=sorted(MAKERS))
def kind(request) -> str:
    return request.param


@pytest.fixture(scope='module')
def memory(kind) -> AssociativeMemory:
    """A trained memory; tests must not add to it."""
    mem = MAKERS[kind]()
    mem.add(V_TRAIN)
    return mem


def unit_error(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(SCALER.to_unit(a) - SCALER.to_unit(b))))


def start_from(v: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Known entries of v, unknown ones at the centre of their range (no prior knowledge)."""
    return np.where(known, v, SCALER.from_unit(np.zeros(D)))


# -- shared recall loop --------------------------------------------------------------------------
def test_clamped_recall_keeps_known_entries_in_every_step():
    seen = []

    def step(u):                       # contraction towards 3.0 in every entry
        seen.append(u.copy())
        return 0.5 * u + 1.5

    u0 = np.array([0.1 + 0.2, -7.0, 2.0])
    known = np.array([True, False, True])
    u, converged, iterations, residual = clamped_recall(step, u0, known, 1e-10, 500)
    assert converged and residual < 1e-10
    assert iterations == len(seen)
    for state in seen + [u]:
        np.testing.assert_array_equal(state[known], u0[known])
    assert u[1] == pytest.approx(3.0, abs=1e-9)


def test_clamped_recall_counts_steps_without_convergence():
    u, converged, iterations, residual = clamped_recall(
        lambda u: u + 1.0, np.zeros(2), np.array([True, False]), 1e-6, 7)
    assert not converged and iterations == 7 and residual == pytest.approx(1.0)
    np.testing.assert_array_equal(u, [0.0, 7.0])


# -- fixed points and completion -------------------------------------------------------------
def test_stored_patterns_are_near_fixed_points(memory):
    v_hat = memory.predict(V_TRAIN)
    assert v_hat.shape == V_TRAIN.shape
    assert unit_error(v_hat, V_TRAIN) < TOL_FIXED_POINT
    # one pattern (D,) gives the row of the batch (up to BLAS rounding)
    np.testing.assert_allclose(memory.predict(V_TRAIN[4]), v_hat[4], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('taus', [TAU_TRAIN, TAU_HELD_OUT], ids=['held_in', 'held_out'])
def test_complete_theta_from_tau(memory, taus):
    worst = 0.0
    for v in patterns_of(taus):
        result = memory.complete(start_from(v, TAU_IDX), TAU_IDX)
        assert isinstance(result, CompletionResult)
        assert result.converged and result.residual < 1e-6, result
        assert 1 <= result.iterations < 200
        worst = max(worst, unit_error(result.pattern, v))
    assert worst < TOL_THETA


@pytest.mark.parametrize('taus', [TAU_TRAIN, TAU_HELD_OUT], ids=['held_in', 'held_out'])
def test_complete_tau_from_theta(memory, taus):
    worst = 0.0
    for v in patterns_of(taus):
        result = memory.complete(start_from(v, THETA_IDX), THETA_IDX)
        assert result.converged, result
        worst = max(worst, unit_error(result.pattern, v))
    assert worst < TOL_TAU


def test_completion_does_not_depend_on_start(memory):
    v = patterns_of(np.array([0.37]))[0]
    rng = np.random.default_rng(0)
    results = [memory.complete(np.where(TAU_IDX, v, SCALER.from_unit(rng.uniform(-1, 1, D))),
                               TAU_IDX, tol=1e-9, max_iter=500) for _ in range(4)]
    assert all(r.converged for r in results)
    for r in results[1:]:
        assert unit_error(r.pattern, results[0].pattern) < 1e-6


@pytest.mark.parametrize('known', [TAU_IDX, THETA_IDX], ids=['tau', 'theta'])
def test_clamped_entries_never_move(memory, known):
    # 0.1 + 0.2 and 1/3 do not survive to_unit/from_unit bit for bit; the result must
    v = patterns_of(np.array([0.1 + 0.2]))[0]
    v[known] += np.where(np.arange(D)[known] % 2 == 0, 1e-3 / 3.0, -1e-3 / 3.0)
    for max_iter in (1, 3, 200):
        result = memory.complete(start_from(v, known), known, max_iter=max_iter)
        np.testing.assert_array_equal(result.pattern[known], v[known])


def test_not_converged_after_one_step_from_far_start(memory):
    v = V_TRAIN[5]
    far = np.where(TAU_IDX, v, SCALER.from_unit(np.ones(D)))  # free entries at the range edge
    result = memory.complete(far, TAU_IDX, max_iter=1)
    assert not result.converged
    assert result.iterations == 1
    assert result.residual > 0.1


def test_all_known_returns_input(memory):
    v = V_TRAIN[2]
    result = memory.complete(v, np.ones(D, dtype=bool))
    assert result.converged and result.iterations == 1 and result.residual == 0.0
    np.testing.assert_array_equal(result.pattern, v)


# -- input validation -------------------------------------------------------------------------
@pytest.mark.parametrize('pattern, known, match', [
    (np.zeros(D - 1), TAU_IDX, 'pattern must have shape'),
    (np.zeros((1, D)), TAU_IDX, 'pattern must have shape'),
    (np.r_[np.zeros(D - 1), np.nan], TAU_IDX, 'finite'),
    (np.r_[np.zeros(D - 1), np.inf], TAU_IDX, 'finite'),
    (np.zeros(D), TAU_IDX[:-1], 'mask of length'),
    (np.zeros(D), TAU_IDX.astype(int), 'boolean'),
    (np.zeros(D), np.zeros(D, dtype=bool), 'at least one'),
])
def test_complete_rejects_bad_input(memory, pattern, known, match):
    with pytest.raises(ValueError, match=match):
        memory.complete(pattern, known)


@pytest.mark.parametrize('kwargs', [{'tol': 0.0}, {'tol': np.nan}, {'max_iter': 0},
                                    {'max_iter': 2.5}, {'max_iter': np.inf}])
def test_complete_rejects_bad_settings(memory, kwargs):
    with pytest.raises(ValueError):
        memory.complete(V_TRAIN[0], TAU_IDX, **kwargs)


def test_add_and_predict_reject_bad_patterns(kind):
    mem = MAKERS[kind]()
    for bad in (np.zeros(D + 1), np.zeros((2, D - 1)), np.full(D, np.nan), np.zeros((0, D))):
        with pytest.raises(ValueError):
            mem.add(bad)
    assert mem.num_patterns == 0
    mem.add(V_TRAIN[0])
    with pytest.raises(ValueError):
        mem.predict(np.zeros(D - 1))


def test_empty_memory_cannot_recall(kind):
    mem = MAKERS[kind]()
    with pytest.raises(RuntimeError, match='empty'):
        mem.complete(V_TRAIN[0], TAU_IDX)
    with pytest.raises(RuntimeError, match='empty'):
        mem.predict(V_TRAIN[0])


@pytest.mark.parametrize('make', [
    lambda: AELM(SCALER, modality_sizes=(E, F + 1)),
    lambda: AELM(SCALER, modality_sizes=(0, D)),
    lambda: AELM(SCALER, regularization=0.0),
    lambda: AELM(SCALER, noise=-0.1),
    lambda: AELM(SCALER, n_synthetic=-1),
    lambda: ARBF(SCALER, modality_sizes=(E, F), beta=(1.0,)),
    lambda: ARBF(SCALER, modality_sizes=(E, F), beta=(1.0, -1.0)),
    lambda: ARBF(SCALER, width=0.0),
    lambda: ARBF(SCALER, regularization=-1.0),
])
def test_constructors_reject_bad_arguments(make):
    with pytest.raises(ValueError):
        make()


# -- incremental learning and persistence ------------------------------------------------------
def test_adding_one_by_one_equals_batch(kind, memory):
    mem = MAKERS[kind]()
    for v in V_TRAIN:
        mem.add(v)
    assert mem.num_patterns == memory.num_patterns == N_TRAIN
    np.testing.assert_allclose(mem.w_out, memory.w_out, rtol=0.0,
                               atol=TOL_INCREMENTAL * np.max(np.abs(memory.w_out)))


def test_state_round_trip(kind, memory):
    state = memory.get_state()
    for key, value in state.items():
        assert isinstance(value, (np.ndarray, int, float)), key
    restored = MAKERS[kind]()
    restored.set_state(state)
    assert restored.num_patterns == N_TRAIN
    probe = np.vstack([V_TRAIN, patterns_of(TAU_HELD_OUT)])
    np.testing.assert_array_equal(restored.predict(probe), memory.predict(probe))
    start = start_from(patterns_of(np.array([0.42]))[0], TAU_IDX)
    a, b = restored.complete(start, TAU_IDX), memory.complete(start, TAU_IDX)
    np.testing.assert_array_equal(a.pattern, b.pattern)
    assert (a.iterations, a.residual) == (b.iterations, b.residual)
    # the restored memory keeps learning like the original would
    extra = patterns_of(np.array([0.123]))
    restored.add(extra)
    original = MAKERS[kind]()
    original.add(np.vstack([V_TRAIN, extra]))
    np.testing.assert_allclose(restored.predict(probe), original.predict(probe), rtol=0.0,
                               atol=1e-9)


def test_state_from_other_arguments_is_rejected(kind, memory):
    other = (AELM(SCALER, n_hidden=200, seed=1, modality_sizes=(E, F)) if kind == 'aelm'
             else ARBF(SCALER, modality_sizes=(E, F), width=0.5))
    with pytest.raises(ValueError, match='same constructor arguments'):
        other.set_state(memory.get_state())
    broken = dict(memory.get_state())
    broken['w_out'] = broken['w_out'][:, :-1]
    with pytest.raises(ValueError):
        MAKERS[kind]().set_state(broken)
