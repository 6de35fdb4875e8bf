"""psl bench memories: the leave-out numbers on a small synthetic session, checked against
an independent computation of the references."""
import numpy as np
import pytest

from psl_bench import memories as bench_memories
from psl_memory.elm import RangeScaler
from psl_memory.parameterized_skill import ParameterizedSkill, scaler_around
from psl_memory.skill_config import SkillConfig


@pytest.fixture(scope='module')
def samples():
    rng = np.random.default_rng(0)
    taus = rng.uniform(-1.0, 1.0, (9, 2))
    mix = rng.normal(size=(2, 4))
    thetas = 2.0 + np.tanh(taus) @ mix
    skill = ParameterizedSkill('s', RangeScaler([-1, -1], [1, 1]), scaler_around(thetas[0]),
                               SkillConfig())
    return {'taus': taus, 'thetas': thetas, 'skill': skill}


def test_the_references_and_the_memories_on_a_known_session(samples):
    record = bench_memories.evaluate_seed(samples, seed=0, stride=3, kinds=('aelm', 'hopfield'))
    assert record['held_out'] == [0, 3, 6] and record['samples'] == 9
    v = np.hstack([samples['taus'], samples['thetas']])
    sd = v.std(axis=0)
    errors = [np.delete(samples['thetas'], i, axis=0).mean(axis=0) - samples['thetas'][i]
              for i in (0, 3, 6)]
    expected = np.sqrt(np.mean((np.array(errors) / sd[2:]) ** 2))
    assert record['results']['mean']['theta_nrmse'] == pytest.approx(expected, rel=1e-12)
    for kind in ('aelm', 'hopfield'):
        r = record['results'][kind]
        assert np.isfinite(r['theta_nrmse']) and np.isfinite(r['tau_nrmse'])
        assert 0.0 <= r['converged'] <= 1.0 and r['add_ms'] > 0.0
    # the smooth map is learned: the readout beats the mean
    assert record['results']['readout']['theta_nrmse'] < expected


def test_bad_settings_are_refused(tmp_path):
    with pytest.raises(ValueError, match='memories'):
        bench_memories.run(memories=('magic',), out=tmp_path)
    with pytest.raises(ValueError, match='start'):
        bench_memories.run(start='middle', out=tmp_path)
