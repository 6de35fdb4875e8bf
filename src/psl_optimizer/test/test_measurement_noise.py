"""A noisy robot in batch mode: the PD law acts on the noisy measurement (the noise enters as
extra control), the reward is computed on the measured angles; a success is confirmed before
its sample enters the skill."""
import numpy as np
import pytest

from psl_controller.pd_law import law_for
from psl_controller.policy import policy_for
from psl_memory.skill_memory import SkillMemory
from psl_optimizer.batch_rollout import BatchRollouts, MeasurementNoise, rollout_key
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_optimizer.rollout_modes import make_rollouts
from psl_task.arm_model import ArmModel
from psl_task.task import load_task

NOISE = MeasurementNoise(position=2e-4, velocity=0.02, seed=5)


@pytest.fixture(scope='module')
def task():
    return load_task('reach_over_obstacle')


def test_no_noise_is_bit_identical_to_no_option(task):
    theta = policy_for(task).default_theta
    plain = BatchRollouts(task).run(theta[None], task.tau_default)[0]
    off = BatchRollouts(task, measurement_noise=MeasurementNoise(seed=3)).run(
        theta[None], task.tau_default)[0]
    assert np.array_equal(plain.q, off.q) and plain.evaluation.reward == off.evaluation.reward


def test_the_law_acts_on_the_noisy_measurement_as_stepped_in_python(task):
    """The same noise samples (`MeasurementNoise.sample` of the rollout) fed to the law step
    by step: the true trajectory (measured minus noise) and the torques agree."""
    theta = policy_for(task).default_theta
    tau = task.tau_default
    rollouts = BatchRollouts(task, measurement_noise=NOISE)
    result = rollouts.run(theta[None], tau)[0]
    ref = policy_for(task).reference(theta)
    n_q, n_qd = NOISE.sample(rollout_key(ref, tau), 0, ref.q.shape)
    n_steps, n = result.q.shape
    law, arm = law_for(task), ArmModel(task)
    # the same rollout again: other noise
    again = rollouts.run(theta[None], tau)[0]
    assert not np.array_equal(again.q, result.q)
    arm.reset(tau)
    q, torque = [arm.q.copy()], [np.zeros(n)]
    for k in range(n_steps - 1):
        u = law.torque(arm.q + n_q[k], arm.qd + n_qd[k], ref.q[k], ref.qd[k], ref.u_ffwd[k])
        torque.append(arm.step(u))
        q.append(arm.q.copy())
    assert np.abs(result.q - n_q - np.array(q)).max() < 1e-10
    assert np.abs(result.torque - np.array(torque)).max() < 1e-7
    # the reward of the measured angles, the geometry replayed from them
    rollouts = BatchRollouts(task)
    replayed = rollouts.reward.evaluate_replayed(result.q[None], result.torque[None],
                                                 ref.q[None], tau[None])[0]
    assert result.evaluation.reward == pytest.approx(replayed.reward, rel=1e-12)
    clean = rollouts.run(theta[None], tau)[0]
    assert result.evaluation.components['smoothness'] > 10 * clean.evaluation.components[
        'smoothness']


def test_noise_parses_and_is_batch_mode_only(task):
    assert MeasurementNoise.parse('position=0.001,velocity=0.01,seed=2') == MeasurementNoise(
        0.001, 0.01, 2)
    for text, words in (('position=-1', '>= 0'), ('seed=1.5', 'whole number'),
                        ('angle=1', 'KEY=VALUE')):
        with pytest.raises(ValueError, match=words):
            MeasurementNoise.parse(text)
    with pytest.raises(ValueError, match='batch mode'):
        make_rollouts('graph', task, workers=[object()], measurement_noise='velocity=0.1')
    with pytest.raises(ValueError, match='the settings say'):
        Learner(task, LearnSettings(), '/nonexistent', make_rollouts(
            'batch', task, measurement_noise='velocity=0.1'))
    for confirm in ((0, 1), (3, 2), (1.5, 2)):
        with pytest.raises(ValueError, match='confirm'):
            LearnSettings(confirm=confirm)


def test_a_success_enters_the_skill_only_if_it_confirms(task, tmp_path):
    noise = 'position=0.00022,velocity=0.02'
    settings = LearnSettings(seed=21, num_tasks=6, num_test=2, measurement_noise=noise,
                             confirm=(3, 3), search=SearchSettings(max_rollouts=40))
    metrics = Learner(task, settings, tmp_path, make_rollouts(
        'batch', task, measurement_noise=noise)).run()
    added = SkillMemory.read(tmp_path / 'memory.npz').get(task.name).num_samples
    records = metrics.tasks
    assert added == sum(r.fulfilled and not r.unconfirmed for r in records)
    for r in records:
        assert r.confirm_rollouts == (2 if r.fulfilled else 0)
        assert not r.unconfirmed or r.fulfilled
    assert metrics.summary.confirm_rollouts == sum(r.confirm_rollouts for r in records)
    assert metrics.summary.unconfirmed_tasks == sum(r.unconfirmed for r in records)
    assert metrics.summary.total_rollouts == sum(r.rollouts for r in records)
    assert metrics.settings['confirm'] == [3, 3]


def test_a_resumed_noisy_session_makes_the_same_decisions(task, tmp_path):
    """The noise of a rollout depends on the rollout and its occurrence, not on what this
    process rolled out before: a session stopped after two tasks and resumed (new rollouts)
    equals the uninterrupted one."""
    noise = 'position=0.00022,velocity=0.02'
    settings = LearnSettings(seed=21, num_tasks=4, num_test=2, measurement_noise=noise,
                             confirm=(2, 3), search=SearchSettings(max_rollouts=30))
    whole = Learner(task, settings, tmp_path / 'whole', make_rollouts(
        'batch', task, measurement_noise=noise)).run()
    calls = iter(range(100))
    first = Learner(task, settings, tmp_path / 'resumed', make_rollouts(
        'batch', task, measurement_noise=noise))
    first.run(should_stop=lambda: next(calls) >= 2)
    resumed = Learner(task, settings, tmp_path / 'resumed', make_rollouts(
        'batch', task, measurement_noise=noise)).run()
    key = ('tau', 'rollouts', 'fulfilled', 'best_reward', 'unconfirmed')
    assert ([[getattr(t, k) for k in key] for t in resumed.tasks]
            == [[getattr(t, k) for k in key] for t in whole.tasks])
    assert resumed.summary.test_rewards == whole.summary.test_rewards


def test_a_checkpoint_of_another_noise_or_confirmation_is_not_resumed(task, tmp_path):
    noise = 'velocity=0.02'
    settings = LearnSettings(seed=1, num_tasks=2, num_test=1, measurement_noise=noise,
                             search=SearchSettings(max_rollouts=20))
    Learner(task, settings, tmp_path, make_rollouts('batch', task, measurement_noise=noise)).run(
        should_stop=iter([False, True]).__next__)
    for change in ({'confirm': (2, 3)}, {'measurement_noise': 'velocity=0.03'}):
        other = LearnSettings(**{**settings.__dict__, **change})
        rollouts = make_rollouts('batch', task, measurement_noise=other.measurement_noise)
        with pytest.raises(ValueError, match='another session'):
            Learner(task, other, tmp_path, rollouts).run()
