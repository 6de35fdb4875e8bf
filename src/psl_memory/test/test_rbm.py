"""Tests of the Gaussian-Bernoulli RBM (eq. 2.17-2.19) as an associative memory.

Data: the 20 stored patterns of test_associative (E = 1, F = 6, an invertible smooth map), its
scaler and helpers, loaded from that file; the memory file through test_parameterized_skill's
small two-skill memory. Errors in normalised units ([-1, 1] per entry of v). The RBM is an
approximate memory: its mean-field recall is blurred towards the modes of the learned density,
so the tolerances are far looser than the AELM's and ARBF's.
"""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from psl_memory.rbm import RBM
from psl_memory.skill_memory import MemoryFileError, SkillMemory


def _sibling(name: str):
    """A test module next to this one, loaded by path (tests are no package)."""
    spec = importlib.util.spec_from_file_location(f'_psl_memory_{name}',
                                                  Path(__file__).with_name(f'{name}.py'))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


assoc = _sibling('test_associative')
skills = _sibling('test_parameterized_skill')
E, F, D = assoc.E, assoc.F, assoc.D

# Recall against the mean predictor: RMS error (normalised units, over the stored patterns and
# the recalled entries) over the RMS of those entries around their mean; 1 = no better than
# answering the mean. Measured over RBM seeds 0-19 (worst, median): fixed point v_hat(v_i)
# 0.15, 0.12; theta from tau 0.30, 0.19; tau from theta 0.17, 0.09. The bounds are about twice
# the worst seed's.
MAX_FIXED_POINT_RATIO = 0.3
MAX_THETA_RATIO = 0.5
MAX_TAU_RATIO = 0.35
# CD from the initial weights: reconstruction RMS 1.31 -> 0.25 (standardised units)
RECONSTRUCTION_GAIN = 3.0


def make(**kwargs) -> RBM:
    return RBM(assoc.SCALER, modality_sizes=(E, F), **kwargs)


@pytest.fixture(scope='module')
def memory() -> RBM:
    """A trained memory; tests must not add to it."""
    mem = make()
    mem.add(assoc.V_TRAIN)
    return mem


def rms_ratio_to_mean(recalled: np.ndarray, truth: np.ndarray) -> float:
    """RMS of recalled - truth over RMS of truth around its mean (normalised units)."""
    return float(np.sqrt(np.mean((recalled - truth) ** 2)
                         / np.mean((truth - truth.mean(axis=0)) ** 2)))


def test_stored_patterns_are_recalled_far_better_than_the_mean(memory):
    unit = assoc.SCALER.to_unit
    truth = unit(assoc.V_TRAIN)                                     # (N, D)
    assert rms_ratio_to_mean(unit(memory.predict(assoc.V_TRAIN)), truth) < MAX_FIXED_POINT_RATIO
    for known, bound in ((assoc.TAU_IDX, MAX_THETA_RATIO), (assoc.THETA_IDX, MAX_TAU_RATIO)):
        results = [memory.complete(assoc.start_from(v, known), known) for v in assoc.V_TRAIN]
        assert all(r.converged for r in results), results
        recalled = unit(np.array([r.pattern for r in results]))    # (N, D)
        ratio = rms_ratio_to_mean(recalled[:, ~known], truth[:, ~known])
        assert ratio < bound, (known, ratio)


def test_cd_training_lowers_reconstruction_error():
    mem = make(epochs_per_add=0)                 # stores only: the initial random weights
    mem.add(assoc.V_TRAIN)
    w0 = mem.weights[0]
    before = mem.reconstruction_error()
    mem.train(500)
    after = mem.reconstruction_error()
    assert after * RECONSTRUCTION_GAIN < before, (before, after)
    assert not np.array_equal(mem.weights[0], w0)
    # the learned density prefers the data: stored patterns have lower free energy than
    # patterns with tau and theta mismatched (theta of the pattern at the other end)
    matched = mem.free_energy(assoc.V_TRAIN)
    mismatched = mem.free_energy(np.column_stack([assoc.V_TRAIN[:, :E],
                                                  assoc.V_TRAIN[::-1, E:]]))
    assert np.mean(matched) < np.mean(mismatched)


def test_recall_is_deterministic(memory):
    start = assoc.start_from(assoc.patterns_of(np.array([0.42]))[0], assoc.TAU_IDX)
    a, b = memory.complete(start, assoc.TAU_IDX), memory.complete(start, assoc.TAU_IDX)
    np.testing.assert_array_equal(a.pattern, b.pattern)
    assert a.converged and (a.iterations, a.residual) == (b.iterations, b.residual)


@pytest.mark.parametrize('known', [assoc.TAU_IDX, assoc.THETA_IDX], ids=['tau', 'theta'])
def test_clamped_entries_never_move(memory, known):
    v = assoc.patterns_of(np.array([0.1 + 0.2]))[0]
    v[known] += np.where(np.arange(D)[known] % 2 == 0, 1e-3 / 3.0, -1e-3 / 3.0)
    for max_iter in (1, 3, 200):
        result = memory.complete(assoc.start_from(v, known), known, max_iter=max_iter)
        np.testing.assert_array_equal(result.pattern[known], v[known])


def test_adding_one_by_one_equals_batch(memory):
    mem = make()
    for v in assoc.V_TRAIN:
        mem.add(v)
    for a, b in zip(mem.weights, memory.weights):
        np.testing.assert_array_equal(a, b)


def test_state_round_trip(memory):
    state = memory.get_state()
    restored = make()
    restored.set_state(state)
    assert restored.num_patterns == assoc.N_TRAIN
    probe = np.vstack([assoc.V_TRAIN, assoc.patterns_of(assoc.TAU_HELD_OUT)])
    np.testing.assert_array_equal(restored.predict(probe), memory.predict(probe))
    for known in (assoc.TAU_IDX, assoc.THETA_IDX):
        start = assoc.start_from(assoc.patterns_of(np.array([0.42]))[0], known)
        a, b = restored.complete(start, known), memory.complete(start, known)
        np.testing.assert_array_equal(a.pattern, b.pattern)
        assert (a.iterations, a.residual) == (b.iterations, b.residual)
    # the restored memory keeps learning exactly like the original would
    extra = assoc.patterns_of(np.array([0.123]))
    restored.add(extra)
    original = make()
    original.add(np.vstack([assoc.V_TRAIN, extra]))
    np.testing.assert_array_equal(restored.predict(probe), original.predict(probe))


def test_state_from_other_arguments_or_broken_is_rejected(memory):
    with pytest.raises(ValueError, match='same constructor arguments'):
        make(n_hidden=32).set_state(memory.get_state())
    with pytest.raises(ValueError, match='same constructor arguments'):
        RBM(assoc.SCALER).set_state(memory.get_state())          # other modality split
    for key, bad in (('w', memory.get_state()['w'][:, :-1]),
                     ('b_v', np.full(D, np.nan)), ('std', np.zeros(D)), ('updates', -1)):
        broken = {**memory.get_state(), key: bad}
        with pytest.raises(ValueError):
            make().set_state(broken)
    missing = dict(memory.get_state())
    missing.pop('b_h')
    with pytest.raises(ValueError, match='lacks'):
        make().set_state(missing)


def test_bad_input_raises_like_the_other_memories(memory):
    mem = make()
    for bad in (np.zeros(D + 1), np.zeros((2, D - 1)), np.full(D, np.nan), np.zeros((0, D))):
        with pytest.raises(ValueError):
            mem.add(bad)
    assert mem.num_patterns == 0
    with pytest.raises(RuntimeError, match='empty'):
        mem.complete(assoc.V_TRAIN[0], assoc.TAU_IDX)
    with pytest.raises(RuntimeError, match='empty'):
        mem.train(1)
    with pytest.raises(ValueError):
        memory.complete(np.zeros(D - 1), assoc.TAU_IDX)
    with pytest.raises(ValueError, match='at least one'):
        memory.complete(assoc.V_TRAIN[0], np.zeros(D, dtype=bool))
    with pytest.raises(ValueError):
        memory.train(-1)


@pytest.mark.parametrize('kwargs', [{'n_hidden': 0}, {'cd_steps': 0}, {'epochs_per_add': -1},
                                    {'rate': 0.0}, {'weight_decay': -1.0}, {'batch_size': 0},
                                    {'min_std': 0.0}, {'modality_sizes': (E, F + 1)}])
def test_constructor_rejects_bad_arguments(kwargs):
    with pytest.raises(ValueError):
        RBM(assoc.SCALER, **{'modality_sizes': (E, F), **kwargs})


def test_diverging_training_raises_and_changes_nothing():
    mem = make(rate=5.0, epochs_per_add=0)
    mem.add(assoc.V_TRAIN[:5])
    state = mem.get_state()
    with pytest.raises(RuntimeError, match='diverged'):
        mem.train(200)
    for key, value in mem.get_state().items():
        np.testing.assert_array_equal(value, state[key])
    diverging = make(rate=5.0)
    with pytest.raises(RuntimeError, match='diverged'):
        diverging.add(assoc.V_TRAIN[:5])
    assert diverging.num_patterns == 0


def test_memory_file_round_trip_and_corrupt_weights(tmp_path):
    memory = skills.trained_memory('bayes', 'rbm')
    path = tmp_path / 'memory.npz'
    memory.save(path)
    loaded = SkillMemory.read(path)
    assert loaded.info()['reach']['associative'] == 'rbm'
    assert skills.answers(loaded) == skills.answers(memory)
    skills.rewrite(path, lambda a: a.update({'skill0/associative.w': np.eye(3)}))
    with pytest.raises(MemoryFileError, match='inconsistent content'):
        SkillMemory.read(path)
