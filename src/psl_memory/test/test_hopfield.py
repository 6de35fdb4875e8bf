"""Tests of the Hopfield network (eq. 2.15-2.16) on thermometer-coded patterns.

Data: (a) four patterns 0.9 * rows 1-4 of an 8 x 8 Hadamard matrix, whose codes are mutually
orthogonal, so the Hebbian network recalls them exactly (the textbook case); their first four
entries tell them apart; (b) the 20 smooth
patterns of test_associative (strongly correlated codes) for the energy property, the clamping
and the persistence; (c) test_parameterized_skill's two-skill memory for the memory file. The
test modules (b), (c) are loaded from their files.
"""
import importlib.util
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

from psl_memory.elm import RangeScaler
from psl_memory.hopfield import (Hopfield, asynchronous_sweep, decode, encode, energy,
                                 thermometer_thresholds)
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
BITS = 8
HADAMARD = scipy.linalg.hadamard(8).astype(float)[1:5]             # (4, 8)
ORTHO_SCALER = RangeScaler(-2.0 * np.ones(8), 2.0 * np.ones(8))    # unit = v / 2
ORTHO = 0.9 * 2.0 * HADAMARD                                        # unit entries +-0.9
ORTHO_KNOWN = np.arange(8) < 4


@pytest.fixture(scope='module')
def ortho() -> Hopfield:
    mem = Hopfield(ORTHO_SCALER, bits=BITS)
    mem.add(ORTHO)
    return mem


@pytest.fixture(scope='module')
def smooth() -> Hopfield:
    """The 20 correlated patterns of test_associative; tests must not add to it."""
    mem = Hopfield(assoc.SCALER, bits=BITS)
    mem.add(assoc.V_TRAIN)
    return mem


def quantised(scaler: RangeScaler, v: np.ndarray) -> np.ndarray:
    """v at the code's levels: from_unit(decode(encode(to_unit(v)))), (n, D)."""
    return scaler.from_unit(decode(encode(scaler.to_unit(np.atleast_2d(v)), BITS), BITS))


def test_code_resolution_and_levels():
    u = np.linspace(-1.0, 1.0, 401)[:, None]
    back = decode(encode(u, BITS), BITS)
    assert np.max(np.abs(back - u)) <= 1.0 / BITS + 1e-12
    assert np.all(np.diff(back[:, 0]) >= 0.0)                           # monotonic
    np.testing.assert_array_equal(decode(encode(back, BITS), BITS), back)   # levels are exact
    assert thermometer_thresholds(BITS).shape == (BITS,)
    np.testing.assert_array_equal(decode(encode(np.array([[-5.0, 5.0]]), BITS), BITS),
                                  [[-1.0, 1.0]])                        # saturates


def test_orthogonal_patterns_are_fixed_points(ortho):
    np.testing.assert_array_equal(ortho.predict(ORTHO), quantised(ORTHO_SCALER, ORTHO))


@pytest.mark.parametrize('row', range(4))
@pytest.mark.parametrize('free_start', [0.0, -0.5], ids=['centre', 'wrong_sign'])
def test_orthogonal_pattern_completed_exactly(ortho, row, free_start):
    known = ORTHO_KNOWN
    start = np.where(known, ORTHO[row], free_start * ORTHO[row])
    result = ortho.complete(start, known)
    assert result.converged and result.residual == 0.0 and result.iterations == 2, result
    np.testing.assert_array_equal(result.pattern[~known], quantised(ORTHO_SCALER,
                                                                    ORTHO[row])[0][~known])
    np.testing.assert_array_equal(result.pattern[known], ORTHO[row][known])


def test_energy_never_rises_under_asynchronous_updates(smooth):
    w = smooth.weights
    assert np.array_equal(w, w.T) and np.all(np.diag(w) == 0.0)
    rng = np.random.default_rng(3)
    n = smooth.num_neurons
    for _ in range(3):
        s = rng.choice([-1.0, 1.0], size=n)
        e = energy(w, s)
        for _sweep in range(20):
            before = s.copy()
            for i in rng.permutation(n):                  # one neuron at a time (eq. 2.15)
                one = np.zeros(n, dtype=bool)
                one[i] = True
                s = asynchronous_sweep(w, s, one)
                e_new = energy(w, s)
                assert e_new <= e + 1e-9, (e, e_new)
                e = e_new
            if np.array_equal(s, before):
                break
        else:
            pytest.fail('no fixed point within 20 sweeps')


@pytest.mark.parametrize('known', [assoc.TAU_IDX, assoc.THETA_IDX], ids=['tau', 'theta'])
def test_clamped_entries_never_move(smooth, known):
    v = assoc.patterns_of(np.array([0.1 + 0.2]))[0]
    v[known] += np.where(np.arange(assoc.D)[known] % 2 == 0, 1e-3 / 3.0, -1e-3 / 3.0)
    for max_iter in (1, 3, 200):
        result = smooth.complete(assoc.start_from(v, known), known, max_iter=max_iter)
        np.testing.assert_array_equal(result.pattern[known], v[known])
    assert result.converged


def test_adding_one_by_one_equals_batch(smooth):
    mem = Hopfield(assoc.SCALER, bits=BITS)
    for v in assoc.V_TRAIN:
        mem.add(v)
    np.testing.assert_array_equal(mem.weights, smooth.weights)


def test_state_round_trip(smooth):
    restored = Hopfield(assoc.SCALER, bits=BITS)
    restored.set_state(smooth.get_state())
    assert restored.num_patterns == assoc.N_TRAIN
    probe = np.vstack([assoc.V_TRAIN, assoc.patterns_of(assoc.TAU_HELD_OUT)])
    np.testing.assert_array_equal(restored.predict(probe), smooth.predict(probe))
    for known in (assoc.TAU_IDX, assoc.THETA_IDX):
        start = assoc.start_from(assoc.patterns_of(np.array([0.42]))[0], known)
        a, b = restored.complete(start, known), smooth.complete(start, known)
        np.testing.assert_array_equal(a.pattern, b.pattern)
        assert (a.iterations, a.residual, a.converged) == (b.iterations, b.residual, b.converged)


def test_state_from_other_code_or_broken_is_rejected(smooth):
    with pytest.raises(ValueError, match='same constructor arguments'):
        Hopfield(assoc.SCALER, bits=BITS + 1).set_state(smooth.get_state())
    state = smooth.get_state()
    with pytest.raises(ValueError, match='Hebbian sum'):
        Hopfield(assoc.SCALER, bits=BITS).set_state({**state, 'hebb': state['hebb'] + 1.0})
    with pytest.raises(ValueError, match='shape'):
        Hopfield(assoc.SCALER, bits=BITS).set_state({**state, 'hebb': np.eye(3)})
    with pytest.raises(ValueError, match='lacks'):
        Hopfield(assoc.SCALER, bits=BITS).set_state({k: v for k, v in state.items()
                                                     if k != 'patterns'})


def test_bad_input_raises_like_the_other_memories(smooth):
    mem = Hopfield(assoc.SCALER, bits=BITS)
    for bad in (np.zeros(assoc.D + 1), np.full(assoc.D, np.inf), np.zeros((0, assoc.D))):
        with pytest.raises(ValueError):
            mem.add(bad)
    assert mem.num_patterns == 0
    with pytest.raises(RuntimeError, match='empty'):
        mem.complete(assoc.V_TRAIN[0], assoc.TAU_IDX)
    with pytest.raises(ValueError, match='boolean'):
        smooth.complete(assoc.V_TRAIN[0], assoc.TAU_IDX.astype(int))
    with pytest.raises(ValueError, match='at least one'):
        smooth.complete(assoc.V_TRAIN[0], np.zeros(assoc.D, dtype=bool))
    for bits in (0, 2.5):
        with pytest.raises(ValueError):
            Hopfield(assoc.SCALER, bits=bits)


def test_memory_file_round_trip_and_corrupt_weights(tmp_path):
    memory = skills.trained_memory('bayes', 'hopfield')
    path = tmp_path / 'memory.npz'
    memory.save(path)
    loaded = SkillMemory.read(path)
    assert loaded.info()['reach']['associative'] == 'hopfield'
    assert skills.answers(loaded) == skills.answers(memory)
    skills.rewrite(path, lambda a: a.update(
        {'skill0/associative.hebb': a['skill0/associative.hebb'] * 2.0}))
    with pytest.raises(MemoryFileError, match='inconsistent content'):
        SkillMemory.read(path)
