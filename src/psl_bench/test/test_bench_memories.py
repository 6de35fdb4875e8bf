"""psl bench memories on a small synthetic session: the mean reference against an independent
computation, and the ranking in docs/benchmarks.md ("memories") (AELM and ARBF complete held-out [tau, theta] far better
than the mean; Hopfield's tau -> theta is no better than the mean)."""
import numpy as np
import pytest

from psl_bench import memories as bench_memories
from psl_memory.elm import RangeScaler
from psl_memory.parameterized_skill import ParameterizedSkill, scaler_around
from psl_memory.skill_config import SkillConfig

NUM_SAMPLES, THETA_DIM, STRIDE = 20, 6, 2        # 10 held-out pairs
# Bounds, as fractions of the mean reference's nRMSE on the same folds. Measured on this
# session's recipe over data seeds 0-15 x memory seeds 0 and 7 (32 sessions): AELM at most 0.17
# of the mean, ARBF at most 0.32 (either direction); Hopfield's tau -> theta 0.82-1.02 of the
# mean (even started at the held-out answer itself it drifts to 0.73). A memory that does not
# complete (answers its start, about the mean) fails the first bound; a Hopfield network that
# resolves neighbouring samples fails the second, and then the ranking in docs/benchmarks.md ("memories") is wrong.
BELOW_MEAN = 0.5             # aelm, arbf: nRMSE < BELOW_MEAN x the mean's, both directions
HOPFIELD_NOT_BELOW = 0.7     # hopfield tau -> theta: nRMSE >= this x the mean's


@pytest.fixture(scope='module')
def samples():
    """A smooth map tau (2) -> theta (6) sampled at random points: what a session's skill
    holds."""
    rng = np.random.default_rng(0)
    taus = rng.uniform(-1.0, 1.0, (NUM_SAMPLES, 2))
    mix = rng.normal(size=(2, THETA_DIM))
    thetas = 2.0 + np.tanh(taus) @ mix
    skill = ParameterizedSkill('s', RangeScaler([-1, -1], [1, 1]), scaler_around(thetas[0]),
                               SkillConfig())
    return {'taus': taus, 'thetas': thetas, 'skill': skill}


@pytest.fixture(scope='module')
def record(samples):
    return bench_memories.evaluate_seed(samples, seed=0, stride=STRIDE,
                                        kinds=('aelm', 'arbf', 'hopfield'))


def test_the_mean_reference_on_a_known_session(samples, record):
    held_out = list(range(0, NUM_SAMPLES, STRIDE))
    assert record['held_out'] == held_out and record['samples'] == NUM_SAMPLES
    v = np.hstack([samples['taus'], samples['thetas']])
    sd = v.std(axis=0)
    for part, key in ((slice(2, None), 'theta_nrmse'), (slice(0, 2), 'tau_nrmse')):
        errors = [np.delete(v, i, axis=0).mean(axis=0)[part] - v[i, part] for i in held_out]
        expected = np.sqrt(np.mean((np.array(errors) / sd[part]) ** 2))
        assert record['results']['mean'][key] == pytest.approx(expected, rel=1e-12)
    # the smooth map is learned: the readout beats the mean
    assert record['results']['readout']['theta_nrmse'] < record['results']['mean']['theta_nrmse']


def test_aelm_and_arbf_complete_far_better_than_the_mean_in_both_directions(record):
    mean = record['results']['mean']
    for kind in ('aelm', 'arbf'):
        r = record['results'][kind]
        for key in ('theta_nrmse', 'tau_nrmse'):
            assert r[key] < BELOW_MEAN * mean[key], (kind, key, r, mean)
        assert 0.0 <= r['converged'] <= 1.0 and r['add_ms'] > 0.0


def test_hopfield_is_no_better_than_the_mean_from_tau_to_theta(record):
    hopfield, mean = record['results']['hopfield'], record['results']['mean']
    assert hopfield['theta_nrmse'] >= HOPFIELD_NOT_BELOW * mean['theta_nrmse'], (hopfield, mean)
    for kind in ('aelm', 'arbf'):     # the skill memories rank above it
        assert record['results'][kind]['theta_nrmse'] < hopfield['theta_nrmse']


def test_bad_settings_are_refused(tmp_path):
    with pytest.raises(ValueError, match='memories'):
        bench_memories.run(memories=('magic',), out=tmp_path)
    with pytest.raises(ValueError, match='start'):
        bench_memories.run(start='middle', out=tmp_path)
