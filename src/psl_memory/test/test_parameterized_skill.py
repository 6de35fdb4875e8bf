"""Tests of the parameterized skill (eq. 2.1-2.14 with the associative memory of eq. 2.20-2.22
beside it) and of the skill memory with its versioned file.

Data:
- generalisation: a hidden smooth map tau -> theta, ``theta = A f(u) + offset`` with ``u`` tau
  scaled from its range to [-1, 1]^E, ``f`` smooth nonlinear features, A random (seeded), for
  (E, F) = (1, 20), (2, 40), (3, 60); 80 training taus and 200 held-out taus drawn uniformly in
  the ranges (which differ per dimension, so the normalisation matters).
- completion: the invertible map of test_associative (tau^2 is strictly monotonic on [0, 1]),
  mixed into F = 20 dimensions; 20 taus evenly spaced in [0, 1], held out at the midpoints.
- persistence: small memories with one skill created from ranges and one created ad hoc.
Every skill uses the default hyper-parameters (`SkillConfig()`) apart from the readout and the
associative memory being tested.
"""
from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import tokenize
from pathlib import Path

import numpy as np
import pytest

import psl_memory
from psl_memory.elm import RangeScaler
from psl_memory.parameterized_skill import ParameterizedSkill, scaler_around
from psl_memory.registry import ASSOCIATIVE, READOUTS
from psl_memory.skill_config import SkillConfig
from psl_memory.skill_memory import FORMAT, VERSION, MemoryFileError, SkillMemory

# -- tolerances (measured values with the data above, seeds fixed) ----------------------------
# Normalised RMS error on held-out tau: RMS(theta_hat - theta) / RMS(theta - mean theta).
# Measured for E = 1 / 2 / 3: ridge, rls, incremental_ridge (same solution) 0.021 / 0.038 /
# 0.056; bayes (evidence maximisation) 0.0003 / 0.007 / 0.046.
TOL_GENERALISATION = 0.1
# Completion tau -> theta against the readout's query, max-abs over theta in units of the theta
# range's half-width: measured 0.035 (bayes) / 0.040 (others) with aelm, 0.0015 / 0.019 with arbf.
TOL_COMPLETION_THETA = 0.08
# Completion theta -> tau, max-abs in tau units on [0, 1]: measured 0.0003 (aelm), 0.0007 (arbf).
TOL_COMPLETION_TAU = 0.005
# Bayesian variance far from the data / near it: measured > 1e8 (tau = 0.9 vs. data on [-1, 0]).
VARIANCE_RATIO_FAR_NEAR = 100.0
# Theta variance = readout variance (normalised units) * half-width^2, up to rounding.
VARIANCE_RTOL = 1e-12
SUBPROCESS_TIMEOUT = 60.0   # s, loading a memory in a fresh interpreter

GEN_LOW = np.array([0.0, -5.0, 10.0])      # tau ranges of the generalisation data (first E)
GEN_HIGH = np.array([1.0, 5.0, 30.0])
GEN_OFFSET = 50.0                          # theta lives far from 0, like a default policy
GEN_N_TRAIN, GEN_N_TEST = 80, 200
SHAPES = [(1, 20), (2, 40), (3, 60)]       # (E, F)

COMP_F = 20
COMP_MIX = np.random.default_rng(5).normal(size=(6, COMP_F)) / np.sqrt(6.0)   # (6, F)
COMP_TAU_TRAIN = np.linspace(0.0, 1.0, 20)
COMP_TAU_HELD_OUT = 0.5 * (COMP_TAU_TRAIN[:-1] + COMP_TAU_TRAIN[1:])


# -- data ---------------------------------------------------------------------------------------
def smooth_features(u: np.ndarray) -> np.ndarray:
    """(n, E) in [-1, 1]^E -> (n, 3E + 2) smooth nonlinear features."""
    cols = [np.ones(len(u))]
    for i in range(u.shape[1]):
        cols += [np.sin(u[:, i] + 0.5 * i), u[:, i]**2, np.tanh(2.0 * u[:, i])]
    cols.append(np.exp(-np.sum(u**2, axis=1)))
    return np.column_stack(cols)


class HiddenMap:
    """theta = A f(u(tau)) + GEN_OFFSET for tau in the first E of the GEN ranges."""

    def __init__(self, tau_dim: int, theta_dim: int, seed: int):
        self.low, self.high = GEN_LOW[:tau_dim], GEN_HIGH[:tau_dim]
        self.rng = np.random.default_rng(seed)
        self.a = self.rng.normal(size=(3 * tau_dim + 2, theta_dim))       # (3E + 2, F)

    def __call__(self, tau: np.ndarray) -> np.ndarray:
        """(n, E) -> (n, F)."""
        u = (tau - 0.5 * (self.low + self.high)) / (0.5 * (self.high - self.low))
        return smooth_features(u) @ self.a + GEN_OFFSET

    def uniform(self, n: int) -> np.ndarray:
        return self.rng.uniform(self.low, self.high, size=(n, self.low.size))   # (n, E)

    def new_skill(self, config: SkillConfig) -> ParameterizedSkill:
        """A skill as SkillMemory.create makes it: tau ranges, theta around the centre's."""
        centre = 0.5 * (self.low + self.high)
        return ParameterizedSkill('hidden', RangeScaler(self.low, self.high),
                                  scaler_around(self(centre[None, :])[0]), config)


def comp_theta(tau) -> np.ndarray:
    """Invertible smooth map [0, 1] -> R^COMP_F: (n,) -> (n, F), scalar -> (F,)."""
    tau = np.asarray(tau, dtype=float)
    basis = np.stack([np.sin(2 * tau), tau**2, np.cos(3 * tau), np.exp(-tau), tau**3 - tau,
                      0.5 * np.sin(5 * tau)], axis=-1)
    return basis @ COMP_MIX


def trained_skill(config: SkillConfig, name: str = 'reach', n: int = 12) -> ParameterizedSkill:
    """A small skill (E = 2, F = 8) from ranges, n samples of a smooth map."""
    rng = np.random.default_rng(11)
    low, high = np.array([-1.0, 0.0]), np.array([1.0, 4.0])
    mix = rng.normal(size=(3, 8))
    skill = ParameterizedSkill(name, RangeScaler(low, high), scaler_around(np.full(8, 2.0)),
                               config)
    for tau in rng.uniform(low, high, size=(n, 2)):
        skill.add(tau, 2.0 + np.array([np.sin(tau[0]), np.cos(tau[1]), tau[0] * tau[1]]) @ mix)
    return skill


def trained_memory(readout: str = 'bayes', associative: str = 'aelm') -> SkillMemory:
    """'reach' created from ranges (12 samples) and 'throw' created by its first sample (4)."""
    memory = SkillMemory(SkillConfig(readout=readout, associative=associative))
    memory.create('reach', [-1.0, 0.0], [1.0, 4.0], np.full(8, 2.0))
    reference = trained_skill(memory.config)
    for tau, theta in zip(reference.taus, reference.thetas):
        memory.add('reach', tau, theta)
    for i in range(4):
        memory.add('throw', [0.5 + 0.1 * i], np.linspace(-1.0, 1.0, 5) * (1.0 + 0.2 * i))
    return memory


# -- exact answers, comparable across processes --------------------------------------------------
def hex_list(values) -> list[str]:
    return [float(x).hex() for x in np.ravel(values)]


def skill_answers(skill: ParameterizedSkill) -> dict:
    """Query, variance and completions at fixed points of the skill's ranges, floats as exact
    hex strings (JSON-able, so a second process can report the same)."""
    out = {'num_samples': skill.num_samples}
    lo, hi = skill.tau_scaler.low, skill.tau_scaler.high
    tau_known = np.arange(skill.tau_dim + skill.theta_dim) < skill.tau_dim
    for i, frac in enumerate((0.1, 0.5, 0.93)):
        tau = lo + frac * (hi - lo)
        theta, var = skill.query(tau)
        out[f'query{i}'] = hex_list(theta)
        out[f'variance{i}'] = None if var is None else hex_list(var)
        if skill.num_samples:
            centre_theta = 0.5 * (skill.theta_scaler.low + skill.theta_scaler.high)
            centre_tau = 0.5 * (lo + hi)
            for mask, start in ((tau_known, np.r_[tau, centre_theta]),
                                (~tau_known, np.r_[centre_tau, theta])):
                r = skill.complete(start, mask)
                key = f'complete{i}_{"tau" if mask[0] else "theta"}'
                out[key] = [hex_list(r.pattern), r.converged, r.iterations,
                            float(r.residual).hex()]
    return out


def answers(memory: SkillMemory) -> dict:
    return {name: skill_answers(skill) for name, skill in sorted(memory.skills.items())}


def skill_snapshot(skill: ParameterizedSkill) -> dict:
    """Answers plus every count and stored sample, to check that nothing changed."""
    return {**skill_answers(skill), 'readout_n': skill.readout.num_samples,
            'patterns': skill.associative.num_patterns,
            'taus': hex_list(skill.taus), 'thetas': hex_list(skill.thetas)}


# -- generalisation ----------------------------------------------------------------------------
@pytest.mark.parametrize('readout', READOUTS)
@pytest.mark.parametrize('tau_dim, theta_dim', SHAPES)
def test_generalises_to_held_out_tau(readout, tau_dim, theta_dim):
    hidden = HiddenMap(tau_dim, theta_dim, seed=tau_dim)
    train, test = hidden.uniform(GEN_N_TRAIN), hidden.uniform(GEN_N_TEST)
    skill = hidden.new_skill(SkillConfig(readout=readout))
    for tau, theta in zip(train, hidden(train)):       # one sample at a time
        skill.add(tau, theta)
    assert skill.num_samples == skill.readout.num_samples == GEN_N_TRAIN
    truth = hidden(test)                                                      # (n, F)
    predicted = np.array([skill.query(tau)[0] for tau in test])              # (n, F)
    assert predicted.shape == truth.shape
    rms_error = np.sqrt(np.mean((predicted - truth)**2))
    rms_spread = np.sqrt(np.mean((truth - truth.mean(axis=0))**2))
    assert rms_error / rms_spread < TOL_GENERALISATION, rms_error / rms_spread


# -- predictive variance -------------------------------------------------------------------------
def variance_skill(readout: str, **options) -> ParameterizedSkill:
    """E = 1 on [-1, 1], 15 noise-free samples on [-1, 0] only; F = 20, theta half-width 34.6."""
    mix = np.random.default_rng(5).normal(size=(3, COMP_F))

    def theta_of(t):
        return 10.0 * np.array([1.0, np.sin(2 * t), t**2]) @ mix
    skill = ParameterizedSkill('v', RangeScaler([-1.0], [1.0]), scaler_around(theta_of(0.0)),
                               SkillConfig(readout=readout, **options))
    for t in np.linspace(-1.0, 0.0, 15):
        skill.add([t], theta_of(t))
    return skill


@pytest.mark.parametrize('estimate', [True, False])
def test_bayes_query_gives_variance_in_theta_units_growing_away_from_data(estimate):
    """With the noise precision estimated (noise-free data: tiny noise floor) the variance far
    from the data is orders of magnitude above the variance near it; with the fixed default
    (noise variance 1 in normalised units) it still grows monotonically away from the data."""
    skill = variance_skill('bayes', estimate_precisions=estimate)
    half = 0.5 * (skill.theta_scaler.high - skill.theta_scaler.low)          # (F,)
    assert half[0] > 10.0     # so that a variance in normalised units would be far off
    variances = {}
    for t in (-0.9, -0.5, -0.03, 0.2, 0.5, 0.9):
        theta, var = skill.query([t])
        assert theta.shape == var.shape == (COMP_F,)
        assert np.all(np.isfinite(var)) and np.all(var > 0.0)
        unit_var = skill.readout.predict_variance(skill.features.transform(np.array([t])))
        np.testing.assert_allclose(var, unit_var * half**2, rtol=VARIANCE_RTOL, atol=0.0)
        variances[t] = var[0]
    near = max(variances[t] for t in (-0.9, -0.5, -0.03))
    assert near < variances[0.2] < variances[0.5] < variances[0.9], variances
    assert variances[0.9] > (VARIANCE_RATIO_FAR_NEAR if estimate else 10.0) * near, variances


@pytest.mark.parametrize('readout', [r for r in READOUTS if r != 'bayes'])
def test_other_readouts_give_no_variance(readout):
    skill = variance_skill(readout)
    theta, var = skill.query([0.3])
    assert theta.shape == (COMP_F,) and var is None


def test_query_before_any_sample_gives_the_reference():
    reference = np.linspace(-3.0, 3.0, 7)
    skill = ParameterizedSkill('s', RangeScaler([0.0], [1.0]), scaler_around(reference),
                               SkillConfig())
    theta, var = skill.query([0.5])
    np.testing.assert_allclose(theta, reference, rtol=0.0, atol=1e-12)
    assert var.shape == (7,) and np.all(var > 0.0)


# -- bad input -----------------------------------------------------------------------------------
E_BAD, F_BAD = 2, 8            # sizes of trained_skill
BAD_SAMPLES = {                # case: (tau, theta, fragment of the message)
    'tau too long': (np.zeros(E_BAD + 1), np.zeros(F_BAD), 'tau with 2 entries, got 3'),
    'tau too short': (np.zeros(E_BAD - 1), np.zeros(F_BAD), 'tau with 2 entries, got 1'),
    'tau 2-D': (np.zeros((1, E_BAD)), np.zeros(F_BAD), 'tau with 2 entries'),
    'tau empty': ([], np.zeros(F_BAD), 'tau with 2 entries, got 0'),
    'tau scalar': (0.5, np.zeros(F_BAD), 'tau with 2 entries'),
    'theta too long': (np.zeros(E_BAD), np.zeros(F_BAD + 1), 'theta with 8 entries, got 9'),
    'theta too short': (np.zeros(E_BAD), np.zeros(F_BAD - 1), 'theta with 8 entries, got 7'),
    'theta 2-D': (np.zeros(E_BAD), np.zeros((F_BAD, 1)), 'theta with 8 entries'),
    'tau nan': (np.array([0.0, np.nan]), np.zeros(F_BAD), 'tau contains NaN or inf'),
    'tau inf': (np.array([np.inf, 0.0]), np.zeros(F_BAD), 'tau contains NaN or inf'),
    'theta nan': (np.zeros(E_BAD), np.r_[np.zeros(F_BAD - 1), np.nan], 'theta contains NaN'),
    'theta -inf': (np.zeros(E_BAD), np.r_[-np.inf, np.zeros(F_BAD - 1)], 'theta contains NaN'),
    'theta text': (np.zeros(E_BAD), ['a'] * F_BAD, 'float'),
}


@pytest.mark.parametrize('readout', READOUTS)
def test_bad_samples_raise_and_change_nothing(readout):
    skill = trained_skill(SkillConfig(readout=readout), n=6)
    before = skill_snapshot(skill)
    for case, (tau, theta, fragment) in BAD_SAMPLES.items():
        with pytest.raises(ValueError) as excinfo:
            skill.add(tau, theta)
        assert fragment in str(excinfo.value), (case, str(excinfo.value))
        assert skill_snapshot(skill) == before, case
    # and the skill still learns
    assert skill.add(np.zeros(E_BAD), np.zeros(F_BAD)) == 7


@pytest.mark.parametrize('tau', [np.zeros(E_BAD + 1), np.zeros((1, E_BAD)), [],
                                 np.array([0.0, np.nan]), np.array([np.inf, 0.0])])
def test_bad_query_raises(tau):
    skill = trained_skill(SkillConfig(), n=3)
    with pytest.raises(ValueError):
        skill.query(tau)


@pytest.mark.parametrize('pattern_size, mask_size', [
    (E_BAD + F_BAD, E_BAD + F_BAD - 1), (E_BAD + F_BAD, E_BAD + F_BAD + 1),
    (E_BAD + F_BAD - 1, E_BAD + F_BAD), (E_BAD + F_BAD + 1, E_BAD + F_BAD + 1)])
def test_completion_with_wrong_sizes_raises(pattern_size, mask_size):
    skill = trained_skill(SkillConfig(), n=3)
    before = skill_snapshot(skill)
    with pytest.raises(ValueError):
        skill.complete(np.zeros(pattern_size), np.arange(mask_size) < E_BAD)
    assert skill_snapshot(skill) == before


def test_completion_rejects_nan_pattern_and_empty_mask():
    skill = trained_skill(SkillConfig(), n=3)
    known = np.arange(E_BAD + F_BAD) < E_BAD
    with pytest.raises(ValueError):
        skill.complete(np.r_[np.nan, np.zeros(E_BAD + F_BAD - 1)], known)
    with pytest.raises(ValueError):
        skill.complete(np.zeros(E_BAD + F_BAD), np.zeros(E_BAD + F_BAD, dtype=bool))


def test_completion_of_an_empty_skill_raises():
    skill = ParameterizedSkill('empty', RangeScaler([0.0], [1.0]), scaler_around(np.zeros(3)))
    with pytest.raises(ValueError, match='no samples'):
        skill.complete(np.zeros(4), np.array([True, False, False, False]))


# -- completion through the skill ---------------------------------------------------------------
@pytest.mark.parametrize('associative', ASSOCIATIVE)
@pytest.mark.parametrize('readout', READOUTS)
def test_completion_both_ways(readout, associative):
    skill = ParameterizedSkill('c', RangeScaler([0.0], [1.0]), scaler_around(comp_theta(0.5)),
                               SkillConfig(readout=readout, associative=associative))
    for tau in COMP_TAU_TRAIN:
        skill.add([tau], comp_theta(tau))
    half = 0.5 * (skill.theta_scaler.high - skill.theta_scaler.low)          # (F,)
    centre = 0.5 * (skill.theta_scaler.high + skill.theta_scaler.low)        # (F,)
    tau_known = np.r_[True, np.zeros(COMP_F, dtype=bool)]
    worst_theta = worst_tau = 0.0
    for tau in np.r_[COMP_TAU_TRAIN[::4], COMP_TAU_HELD_OUT]:
        # tau -> theta, starting from the centre of the theta range
        start = np.r_[tau, centre]
        result = skill.complete(start, tau_known)
        assert result.converged, result
        assert result.pattern[0] == tau                                       # clamped, exact
        query = skill.query([tau])[0]
        worst_theta = max(worst_theta, float(np.max(np.abs(result.pattern[1:] - query) / half)))
        # theta -> tau, starting from the centre of the tau range
        theta = comp_theta(tau)
        result = skill.complete(np.r_[0.5, theta], ~tau_known)
        assert result.converged, result
        np.testing.assert_array_equal(result.pattern[1:], theta)             # clamped, exact
        worst_tau = max(worst_tau, abs(result.pattern[0] - tau))
    assert worst_theta < TOL_COMPLETION_THETA, worst_theta
    assert worst_tau < TOL_COMPLETION_TAU, worst_tau


# -- SkillMemory ---------------------------------------------------------------------------------
def test_create_from_ranges():
    memory = SkillMemory()
    skill = memory.create('reach', [0.0, -1.0], [2.0, 1.0], np.arange(5.0))
    assert memory.get('reach') is skill
    assert (skill.tau_dim, skill.theta_dim, skill.num_samples) == (2, 5, 0)
    np.testing.assert_array_equal(skill.tau_scaler.low, [0.0, -1.0])
    np.testing.assert_array_equal(skill.tau_scaler.high, [2.0, 1.0])
    with pytest.raises(ValueError, match='exists'):
        memory.create('reach', [0.0], [1.0], np.zeros(3))
    assert memory.get('reach') is skill and skill.tau_dim == 2
    for low, high in (([1.0], [1.0]), ([0.0, 0.0], [1.0]), ([0.0], [np.inf])):
        with pytest.raises(ValueError):
            memory.create('bad', low, high, np.zeros(3))
    assert sorted(memory.skills) == ['reach']
    assert memory.add('reach', [1.0, 0.0], np.arange(5.0) + 0.1) == 1


def test_first_sample_creates_a_skill_and_fixes_its_sizes():
    memory = SkillMemory()
    assert memory.add('throw', [0.3, 0.7], np.arange(6.0)) == 1
    skill = memory.get('throw')
    assert (skill.tau_dim, skill.theta_dim) == (2, 6)
    before = skill_snapshot(skill)
    for tau, theta in (([0.3], np.arange(6.0)), ([0.3, 0.7, 0.1], np.arange(6.0)),
                       ([0.3, 0.7], np.arange(5.0)), ([0.3, 0.7], np.arange(7.0))):
        with pytest.raises(ValueError, match='entries'):
            memory.add('throw', tau, theta)
    assert skill_snapshot(skill) == before
    assert memory.add('throw', [0.4, 0.6], np.arange(6.0) + 0.5) == 2


@pytest.mark.parametrize('name, tau, theta', [
    ('s', [], np.zeros(3)), ('s', [0.1], []), ('s', [[0.1]], np.zeros(3)),
    ('s', [np.nan], np.zeros(3)), ('s', [0.1], [0.0, np.inf]), ('', [0.1], np.zeros(3)),
    ('  ', [0.1], np.zeros(3))])
def test_bad_first_sample_creates_nothing(name, tau, theta):
    memory = SkillMemory()
    with pytest.raises(ValueError):
        memory.add(name, tau, theta)
    assert memory.skills == {} and memory.info() == {}


def test_unknown_skill_names_the_known_ones():
    memory = SkillMemory()
    with pytest.raises(KeyError, match='none yet'):
        memory.get('reach')
    memory.create('reach', [0.0], [1.0], np.zeros(3))
    memory.add('throw', [0.0], np.zeros(2))
    with pytest.raises(KeyError) as excinfo:
        memory.get('grasp')
    message = str(excinfo.value)
    assert 'grasp' in message and 'reach' in message and 'throw' in message


def test_info():
    memory = SkillMemory(SkillConfig(readout='rls', associative='arbf'))
    memory.create('reach', [0.0, 0.0], [1.0, 1.0], np.zeros(4))
    memory.add('throw', [0.0], np.zeros(3))
    memory.add('throw', [0.5], np.ones(3))
    assert memory.info() == {
        'reach': {'tau_dim': 2, 'theta_dim': 4, 'num_samples': 0, 'readout': 'rls',
                  'associative': 'arbf'},
        'throw': {'tau_dim': 1, 'theta_dim': 3, 'num_samples': 2, 'readout': 'rls',
                  'associative': 'arbf'}}
    json.dumps(memory.info())          # JSON-able, for `psl memory info --json`


# -- persistence ---------------------------------------------------------------------------------
@pytest.mark.parametrize('associative', ASSOCIATIVE)
@pytest.mark.parametrize('readout', READOUTS)
def test_save_read_gives_identical_answers(readout, associative, tmp_path):
    memory = trained_memory(readout, associative)
    path = tmp_path / 'memory.npz'
    memory.save(path)
    loaded = SkillMemory.read(path)
    assert loaded.config == memory.config
    assert loaded.info() == memory.info()
    assert answers(loaded) == answers(memory)
    for name, skill in memory.skills.items():
        np.testing.assert_array_equal(loaded.get(name).taus, skill.taus)
        np.testing.assert_array_equal(loaded.get(name).thetas, skill.thetas)
    # learning goes on identically
    for m in (memory, loaded):
        m.add('reach', [0.2, 3.0], np.linspace(1.0, 3.0, 8))
        m.add('throw', [0.9], np.linspace(-2.0, 2.0, 5))
    assert answers(loaded) == answers(memory)


CHILD = """
import json, runpy, sys
from psl_memory.skill_memory import SkillMemory
answers = runpy.run_path(sys.argv[1], run_name='psl_child')['answers']
print(json.dumps({path: answers(SkillMemory.read(path)) for path in sys.argv[2:]}))
"""


def test_save_read_in_a_new_process_gives_identical_answers(tmp_path):
    expected = {}
    for readout in READOUTS:
        memory = trained_memory(readout)
        path = str(tmp_path / f'{readout}.npz')
        memory.save(path)
        expected[path] = answers(memory)
    package_root = str(Path(psl_memory.__file__).parent.parent)
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (package_root, env.get('PYTHONPATH')) if p)
    done = subprocess.run([sys.executable, '-c', CHILD, __file__, *expected], env=env,
                          capture_output=True, text=True, timeout=SUBPROCESS_TIMEOUT)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == expected


ODD_NAMES = ('ur5', 'ur5/reach', 'reach over obstacle', 'grasp.v2', 'ünïcode', '__meta__',
             '../x', '.npy')


def test_odd_skill_names_survive_save_and_read(tmp_path):
    memory = SkillMemory()
    for i, name in enumerate(ODD_NAMES):
        memory.add(name, [0.1], np.arange(3.0) + i)
        memory.add(name, [0.4], np.arange(3.0) - i)
    memory.save(tmp_path / 'memory.npz')
    assert os.listdir(tmp_path) == ['memory.npz']          # '../x' wrote nothing elsewhere
    loaded = SkillMemory.read(tmp_path / 'memory.npz')
    assert sorted(loaded.skills) == sorted(ODD_NAMES)
    assert answers(loaded) == answers(memory)


def test_skill_names_with_slashes_do_not_mix(tmp_path):
    memory = SkillMemory()
    for name in ('ur5', 'ur5/readout.v2'):
        memory.add(name, [0.1], np.arange(3.0))
    memory.save(tmp_path / 'memory.npz')
    loaded = SkillMemory.read(tmp_path / 'memory.npz')
    assert answers(loaded) == answers(memory)


def test_save_is_atomic_and_replaces_the_file(tmp_path):
    memory = trained_memory()
    path = tmp_path / 'memory.npz'
    memory.save(path)
    assert sorted(os.listdir(tmp_path)) == ['memory.npz']      # no temporary file left
    inode = path.stat().st_ino
    memory.add('throw', [0.05], np.zeros(5))
    memory.save(path)
    assert sorted(os.listdir(tmp_path)) == ['memory.npz']
    assert path.stat().st_ino != inode        # a new file renamed over the old, not rewritten
    assert SkillMemory.read(path).info() == memory.info()


def test_failed_save_keeps_the_old_file(tmp_path, monkeypatch):
    memory = trained_memory()
    path = tmp_path / 'memory.npz'
    memory.save(path)
    old = path.read_bytes()

    def savez_then_fail(file, **arrays):
        file.write(b'PK\x03\x04 half a zip')
        raise RuntimeError('disk full')

    monkeypatch.setattr(np, 'savez', savez_then_fail)
    memory.add('throw', [0.05], np.zeros(5))
    with pytest.raises(RuntimeError, match='disk full'):
        memory.save(path)
    assert sorted(os.listdir(tmp_path)) == ['memory.npz']
    assert path.read_bytes() == old


def test_save_to_a_missing_folder_raises_and_leaves_nothing(tmp_path):
    memory = trained_memory()
    missing = tmp_path / 'no' / 'such'
    with pytest.raises(OSError, match='does not exist'):
        memory.save(missing / 'memory.npz')
    assert not (tmp_path / 'no').exists()
    assert os.listdir(tmp_path) == []


# -- corrupt files are refused -------------------------------------------------------------------
def good_arrays(path: Path) -> dict:
    with np.load(path) as data:
        return {key: data[key] for key in data.files}


def header(fmt=FORMAT, version=VERSION, **extra) -> np.ndarray:
    meta = {'format': fmt, 'version': version, 'config': {}, 'skills': [], **extra}
    return np.array(json.dumps(meta))


def savez(path: Path, **arrays) -> None:
    """np.savez to exactly `path` (np.savez would append .npz to a name without it)."""
    with open(path, 'wb') as f:
        np.savez(f, **arrays)


def rewrite(path: Path, change) -> None:
    """The good file's arrays, changed by ``change(arrays)``, saved back with np.savez."""
    arrays = good_arrays(path)
    change(arrays)
    savez(path, **arrays)


def flip_byte_at_middle(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF            # inside the data of a large array: CRC mismatch
    path.write_bytes(bytes(data))


def set_meta(arrays: dict, **changes) -> None:
    meta = json.loads(str(arrays['__meta__']))
    meta.update(changes)
    arrays['__meta__'] = np.array(json.dumps(meta))


def wrong_config(arrays: dict) -> None:
    meta = json.loads(str(arrays['__meta__']))
    set_meta(arrays, config={**meta['config'], 'readout': 'magic'})


CORRUPT = {   # case: (make the bad file at `path` (a good file is there), fragment of the message)
    'missing path': (lambda p: p.unlink(), 'no such file'),
    'a folder': (lambda p: (p.unlink(), p.mkdir()), 'is a directory'),
    'empty file': (lambda p: p.write_bytes(b''), 'not a readable'),
    'truncated to half': (lambda p: p.write_bytes(p.read_bytes()[:p.stat().st_size // 2]),
                          'not a readable'),
    'last bytes cut': (lambda p: p.write_bytes(p.read_bytes()[:-10]), 'not a readable'),
    'random bytes': (lambda p: p.write_bytes(np.random.default_rng(0).bytes(5000)),
                     'not a readable'),
    'flipped byte': (flip_byte_at_middle, 'not a readable'),
    'text file': (lambda p: p.write_text('format: psl-skill-memory\nversion: 1\n'),
                  'not a readable'),
    'npz without header': (lambda p: savez(p, weights=np.zeros(3)), 'no header'),
    'other version': (lambda p: rewrite(p, lambda a: set_meta(a, version=VERSION + 1)),
                      f'version {VERSION + 1}'),
    'no version': (lambda p: rewrite(p, lambda a: a.update(__meta__=header(version=None))),
                   'version None'),
    'other format': (lambda p: savez(p, __meta__=header(fmt='other-memory')),
                     "format 'other-memory'"),
    'header not JSON': (lambda p: rewrite(p, lambda a: a.update(__meta__=np.array('{oops'))),
                        'corrupt header'),
    'pickled object array': (lambda p: rewrite(p, lambda a: a.update(
        extra=np.array([{'x': 1}], dtype=object))), 'not a readable'),
    'skill arrays missing': (lambda p: rewrite(p, lambda a: [a.pop(k) for k in list(a)
                                                             if k.startswith('skill0/')]),
                             'inconsistent content'),
    'array of wrong shape': (lambda p: rewrite(p, lambda a: a.update(
        {'skill0/readout.hth': np.eye(3)})), 'inconsistent content'),
    'non-finite array': (lambda p: rewrite(p, lambda a: a.update(
        {'skill0/readout.hty': np.full_like(a['skill0/readout.hty'], np.nan)})),
        'inconsistent content'),
    'other random weights': (lambda p: rewrite(p, lambda a: a.update(
        {'skill1/w_inp': a['skill1/w_inp'] + 1.0})), 'random weights'),
    'unknown readout in config': (lambda p: rewrite(p, wrong_config), 'inconsistent content'),
    'skill listed but absent': (lambda p: rewrite(p, lambda a: set_meta(
        a, skills=['reach', 'throw', 'grasp'])), 'inconsistent content'),
}


@pytest.fixture(scope='module')
def memory_in_use() -> SkillMemory:
    return trained_memory()


@pytest.mark.parametrize('case', CORRUPT)
def test_corrupt_file_is_refused_and_memory_in_use_kept(case, memory_in_use, tmp_path):
    make_bad, fragment = CORRUPT[case]
    path = tmp_path / 'memory.npz'
    memory_in_use.save(path)
    make_bad(path)
    m = memory_in_use
    before = answers(m)
    with pytest.raises(MemoryFileError) as excinfo:
        m = SkillMemory.read(path)                 # the caller's pattern: m only on success
    message = str(excinfo.value)
    assert fragment in message, message
    assert str(path) in message, message
    assert m is memory_in_use and answers(m) == before
    assert isinstance(excinfo.value, ValueError)   # callers that catch ValueError see it too


# -- known bugs (see the reasons) ---------------------------------------------------------------
def npy_instead_of_npz(path: Path) -> None:
    with open(path, 'wb') as f:
        np.save(f, np.arange(3.0))


def header_json_list(path: Path) -> None:
    savez(path, __meta__=np.array(json.dumps([FORMAT, VERSION])))


def unsupported_compression(path: Path) -> None:
    data = bytearray(path.read_bytes())
    entry = data.index(b'PK\x01\x02')                # first central directory entry
    data[entry + 10:entry + 12] = struct.pack('<H', 99)     # compression method
    path.write_bytes(bytes(data))


def garbled_array_header(path: Path) -> None:
    data = bytearray(path.read_bytes())
    member = data.index(b'skill0/readout.hth.npy')     # a large member: header parsed before CRC
    data[data.index(b"{'descr'", member)] = ord('x')
    path.write_bytes(bytes(data))


@pytest.mark.parametrize('make_bad, error', [
    pytest.param(npy_instead_of_npz, TypeError, id='npy file'),
    pytest.param(header_json_list, AttributeError, id='header a JSON list'),
    pytest.param(unsupported_compression, NotImplementedError, id='unknown zip compression'),
    pytest.param(garbled_array_header, tokenize.TokenError, id='garbled npy header'),
])
def test_other_corrupt_files_are_refused(make_bad, error, memory_in_use, tmp_path, request):
    path = tmp_path / 'memory.npz'
    memory_in_use.save(path)
    make_bad(path)
    with pytest.raises(MemoryFileError):
        SkillMemory.read(path)


@pytest.mark.filterwarnings('ignore:overflow:RuntimeWarning')
def test_every_accepted_sample_survives_save_and_read(tmp_path):
    memory = SkillMemory()                                  # default: bayes readout
    memory.create('reach', [0.0], [1.0], np.zeros(4))
    memory.add('reach', [0.1], np.zeros(4))
    try:
        memory.add('reach', [0.5], np.full(4, 1e156))
    except ValueError:
        return                                             # refusing it is fine too
    memory.save(tmp_path / 'memory.npz')
    loaded = SkillMemory.read(tmp_path / 'memory.npz')
    assert answers(loaded) == answers(memory)


# -- the registries and create --------------------------------------------------------------------
def test_every_registered_part_is_built_from_the_config():
    from psl_memory.registry import ASSOCIATIVE_MEMORIES
    config = SkillConfig(regularization=0.25, forgetting=0.9, noise_precision=3.0, seed=7,
                         n_hidden=120)
    for name, cls in READOUTS.items():
        readout = cls.from_config(config.n_hidden, 5, config)
        assert isinstance(readout, cls) and readout.name == name
        assert (readout.n_hidden, readout.n_out) == (120, 5)
    bayes = READOUTS['bayes'].from_config(10, 2, config)
    assert (bayes.alpha, bayes.beta) == (0.25, 3.0)          # prior precision = regularization
    scaler = RangeScaler(-np.ones(4), np.ones(4))
    for name, cls in ASSOCIATIVE_MEMORIES.items():
        memory = cls.from_config(scaler, (1, 3), config)
        assert isinstance(memory, cls) and memory.num_patterns == 0
    assert ASSOCIATIVE_MEMORIES['aelm'].from_config(scaler, (1, 3), config).features.n_hidden == 120
    small = SkillConfig(n_hidden=20)
    assert ASSOCIATIVE_MEMORIES['aelm'].from_config(scaler, (1, 3), small).features.n_hidden \
        == 100


def test_create_keeps_a_skill_of_the_same_sizes_and_refuses_others():
    memory = SkillMemory(SkillConfig())
    skill = memory.create('reach', [0.0, 0.0], [1.0, 1.0], np.ones(6))
    skill.add([0.5, 0.5], np.ones(6))
    with pytest.raises(ValueError, match='exists already'):
        memory.create('reach', [0.0, 0.0], [1.0, 1.0], np.ones(6))
    assert memory.create('reach', [0.0, 0.0], [1.0, 1.0], np.ones(6), exist_ok=True) is skill
    assert memory.get('reach').num_samples == 1
    with pytest.raises(ValueError, match='exists with 2 task and 6 policy parameters'):
        memory.create('reach', [0.0], [1.0], np.ones(6), exist_ok=True)
    for bad in (('', [0.0], [1.0], [0.0]), ('x', [], [], [0.0]), ('x', [0.0], [1.0], [])):
        with pytest.raises(ValueError):
            memory.create(*bad)
    assert list(memory.skills) == ['reach']


# -- the range policy -----------------------------------------------------------------------------
def test_a_task_skill_refuses_tau_beyond_its_margin_everywhere():
    from psl_memory.parameterized_skill import TAU_MARGIN
    memory = SkillMemory(SkillConfig())
    skill = memory.create('task', [0.5, 0.1], [0.8, 0.2], np.ones(4))
    inside = [0.8 + 0.99 * TAU_MARGIN * 0.3, 0.1 - 0.99 * TAU_MARGIN * 0.1]    # just inside
    outside = [0.8 + 1.01 * TAU_MARGIN * 0.3, 0.15]                          # just beyond
    skill.add(inside, np.ones(4))
    skill.query(inside)
    for call in (lambda: skill.query(outside), lambda: skill.add(outside, np.ones(4)),
                 lambda: skill.complete(np.r_[outside, np.ones(4)], [True, True] + [False] * 4)):
        with pytest.raises(ValueError, match=r'tau\[0\] = .* outside the range \[0.5, 0.8\]'):
            call()
    assert skill.num_samples == 1
    # a free entry of a completion is a guess, not a request: no range applies to it
    skill.complete(np.r_[0.0, 0.15, np.ones(4)], [False, True] + [True] * 4)


def test_absurd_magnitudes_are_refused_by_any_skill():
    memory = SkillMemory(SkillConfig())
    memory.add('adhoc', [0.0], [1.0, 2.0])                    # ranges around the first sample
    skill = memory.get('adhoc')
    skill.add([25.0], [1.0, 2.0])                           # far for a task, fine ad hoc
    for call in (lambda: skill.query([-1e308]), lambda: skill.add([1e300], [1.0, 2.0]),
                 lambda: skill.add([0.5], [1e308, 2.0])):
        with pytest.raises(ValueError, match='a units or scaling error'):
            call()
    assert skill.num_samples == 2


def test_a_memory_file_keeps_whether_a_skill_has_a_tasks_ranges(tmp_path):
    memory = SkillMemory(SkillConfig())
    memory.create('task', [0.0], [1.0], np.zeros(2))
    memory.add('adhoc', [0.0], [1.0, 2.0])
    memory.save(tmp_path / 'm.npz')
    again = SkillMemory.read(tmp_path / 'm.npz')
    assert again.get('task').bounded and not again.get('adhoc').bounded
