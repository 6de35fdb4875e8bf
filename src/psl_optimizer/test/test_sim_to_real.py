"""Sim to real in batch mode: the model error reaches the simulation (and only it), and a
continued skill learns the robot's correction on top of the simulated skill."""
import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import (CORRECTION_SUFFIX, InProcessSkill, Learner, LearnSettings,
                                    search_normalisation)
from psl_optimizer.policy_search import SearchSettings
from psl_optimizer.reward import RewardResult
from psl_optimizer.rollout_modes import make_rollouts
from psl_optimizer.rollouts import RolloutResult, Rollouts
from psl_memory.skill_config import SkillConfig
from psl_task.model_error import ModelError
from psl_task.task import load_task

REAL = 'mass_scale=1.3,frictionloss=0.05,damping=0.3'


@pytest.fixture(scope='module')
def payload():
    return load_task('payload_transport')


def pd_only(task, count):
    """count thetas: the default path with a zero feed-forward, and small variations."""
    policy = policy_for(task)
    base = policy.with_feedforward(policy.default_theta,
                                   np.zeros(policy.feedforward.num_parameters))
    rng = np.random.default_rng(0)
    thetas = np.tile(base, (count, 1))
    thetas[1:, policy.kinematics] += 0.01 * rng.standard_normal(
        (count - 1, int(np.size(base[policy.kinematics]))))
    return thetas


def test_no_model_error_is_bit_identical_to_no_option(payload):
    thetas = pd_only(payload, 3)
    taus = np.tile(payload.tau_default, (3, 1))
    plain = BatchRollouts(payload).run(thetas, taus)
    identity = BatchRollouts(payload, model_error=ModelError()).run(thetas, taus)
    for a, b in zip(plain, identity):
        assert np.array_equal(a.q, b.q) and np.array_equal(a.torque, b.torque)
        assert a.evaluation.reward == b.evaluation.reward


def test_a_heavier_robot_sags_more_under_the_same_theta(payload):
    """PD only against gravity: the heavier the arm, the larger the tracking error; friction
    and damping change the trajectory too. The skill's own models stay nominal."""
    thetas = pd_only(payload, 1)
    taus = payload.tau_default[None]
    errors = {}
    for scale in (1.0, 1.3, 1.6):
        rollouts = BatchRollouts(payload, model_error=ModelError(mass_scale=scale))
        result = rollouts.run(thetas, taus)[0]
        errors[scale] = result.evaluation.components['tracking_error']
        assert rollouts.arm.model.body_mass.sum() == BatchRollouts(payload).arm.model.body_mass.sum()
    assert errors[1.0] < errors[1.3] < errors[1.6]
    nominal = BatchRollouts(payload).run(thetas, taus)[0]
    damped = BatchRollouts(payload, model_error=ModelError(frictionloss=0.05, damping=0.3)).run(
        thetas, taus)[0]
    assert not np.allclose(nominal.q, damped.q)


def test_make_rollouts_takes_the_model_error_as_text_and_batch_mode_only(payload):
    rollouts = make_rollouts('batch', payload, model_error=REAL)
    assert rollouts.model_error == ModelError(1.3, 0.05, 0.3)
    with pytest.raises(ValueError, match='mass_scale'):
        make_rollouts('batch', payload, model_error='mass_scale=-1')
    with pytest.raises(ValueError, match='batch mode'):
        make_rollouts('graph', payload, workers=[object()], model_error=REAL)


def test_the_settings_record_the_model_error_the_rollouts_have(payload, tmp_path):
    real = make_rollouts('batch', payload, model_error=REAL)
    with pytest.raises(ValueError, match='model error'):
        Learner(payload, LearnSettings(num_tasks=1), tmp_path, real)
    with pytest.raises(ValueError, match='KEY=VALUE'):
        LearnSettings(model_error='heavier')
    with pytest.raises(ValueError, match='continuation'):
        LearnSettings(continuation='forget')


def reach_skill(continuation):
    task = load_task('reach_over_obstacle')
    policy = policy_for(task)
    return task, InProcessSkill(task, SkillConfig(), policy.default_theta, continuation)


def test_a_residual_continuation_starts_from_the_loaded_skill_and_learns_on_top(tmp_path):
    task, first = reach_skill('samples')
    rng = np.random.default_rng(1)
    theta = first.default_theta + 0.05 * rng.standard_normal(first.default_theta.shape)
    taus = task.tau_low + (task.tau_high - task.tau_low) * rng.random((3, len(task.tau_low)))
    for tau in taus:
        first.add(tau, theta)
    first.save(tmp_path / 'sim.npz')
    _, residual = reach_skill('residual')
    residual.start(str(tmp_path / 'sim.npz'))
    probe = taus[0] + 0.01
    assert np.array_equal(residual.query(probe), first.query(probe))   # empty correction
    shifted = theta + 0.02
    residual.add(taus[1], shifted)
    sim = residual.memory.get(task.name)
    assert sim.num_samples == 3                                        # the base untouched
    assert residual.memory.get(task.name + CORRECTION_SUFFIX).num_samples == 1
    # the sum moved towards the robot's solution where it was given
    assert (np.abs(residual.query(taus[1]) - shifted).max()
            < np.abs(first.query(taus[1]) - shifted).max())
    # the file holds both; a resumed session answers the same
    residual.save(tmp_path / 'continued.npz')
    _, again = reach_skill('residual')
    again.restore(tmp_path / 'continued.npz')
    assert np.array_equal(again.query(probe), residual.query(probe))
    # the old way: the robot's solutions join the simulated samples
    _, samples = reach_skill('samples')
    samples.start(str(tmp_path / 'sim.npz'))
    samples.add(taus[1], shifted)
    assert samples.memory.get(task.name).num_samples == 4
    assert task.name + CORRECTION_SUFFIX not in samples.memory.skills
    with pytest.raises(ValueError, match='residual way'):
        samples.start(str(tmp_path / 'continued.npz'))


def test_a_session_continues_the_residual_way_unless_told_otherwise(tmp_path):
    task = load_task('reach_over_obstacle')
    rollouts = make_rollouts('batch', task)
    Learner(task, LearnSettings(num_tasks=2, num_test=2, seed=1), tmp_path / 'a', rollouts).run()
    kept = str(tmp_path / 'a' / 'memory.npz')
    for way, corrected in (('', True), ('residual', True), ('samples', False)):
        settings = LearnSettings(num_tasks=2, num_test=2, seed=2, continue_from=kept,
                                 continuation=way)
        learner = Learner(task, settings, tmp_path / f'b{way}', rollouts)
        metrics = learner.run()
        assert metrics.settings['continuation'] == way and metrics.settings['model_error'] == ''
        assert (task.name + CORRECTION_SUFFIX in learner.skill.memory.skills) == corrected


class SamplesOnly:
    """A skill slot that continues by adding samples (as the memory node's)."""


def test_a_skill_slot_that_cannot_continue_residually_refuses_to(tmp_path):
    task = load_task('reach_over_obstacle')
    rollouts = make_rollouts('batch', task)
    with pytest.raises(ValueError, match="not 'residual'"):
        Learner(task, LearnSettings(continuation='residual'), tmp_path, rollouts,
                skill=SamplesOnly())
    Learner(task, LearnSettings(), tmp_path, rollouts, skill=SamplesOnly())   # its own way


def test_a_residual_continuation_guesses_the_simulated_skill_then_an_empty_skills_answer(
        tmp_path):
    """Besides PS_sim + C, a residual continuation offers the guesses a search tries when that
    one misses: PS_sim alone (which the robot's correction does not move) and c0, the answer of
    a skill without samples (a session from scratch's first guess). A skill alone offers
    none."""
    task, first = reach_skill('samples')
    rng = np.random.default_rng(2)
    taus = task.tau_low + (task.tau_high - task.tau_low) * rng.random((3, len(task.tau_low)))
    for tau in taus:
        first.add(tau, first.default_theta + 0.05 * rng.standard_normal(
            first.default_theta.shape))
    first.save(tmp_path / 'sim.npz')
    _, empty = reach_skill('residual')
    _, residual = reach_skill('residual')
    residual.start(str(tmp_path / 'sim.npz'))
    probe = taus[0] + 0.01
    assert empty.alternatives(probe) == [] and first.alternatives(probe) == []
    sim_alone, without_samples = residual.alternatives(probe)
    np.testing.assert_array_equal(sim_alone, first.query(probe))
    np.testing.assert_array_equal(without_samples, empty.query(probe))
    residual.add(taus[1], first.query(taus[1]) + 0.1)
    assert not np.array_equal(residual.query(probe), first.query(probe))
    np.testing.assert_array_equal(residual.alternatives(probe)[0], first.query(probe))


class DefaultRobot(Rollouts):
    """A stand-in robot on which only policies near the task's default theta fulfil an
    instance (reward: minus their RMS distance to it in CMA-ES units; fulfilled within `tol`):
    a skill learned in simulation away from the default is wrong on it everywhere, a skill
    without samples is right."""

    def __init__(self, task, tol: float):
        super().__init__(task)
        self.target, self.tol = self.policy.default_theta, tol
        self.scale = search_normalisation(task, self.target)[1]

    def run(self, thetas, taus):
        thetas, taus = self._inputs(thetas, taus)
        distance = np.sqrt(np.mean(((thetas - self.target) / self.scale) ** 2, axis=1))
        return self._count([RolloutResult(evaluation=RewardResult(
            reward=-float(d), fulfilled=bool(d <= self.tol), components={}))
            for d in distance])


def test_a_wrong_simulated_skill_costs_a_continued_session_its_guesses_not_a_search(tmp_path):
    """On a robot where the simulated skill misses everywhere and the default policy is right,
    each task of a residual continuation costs at most its three guesses (PS_sim + C, PS_sim,
    c0) and is solved; a session from scratch pays one rollout per task. Without the guesses
    the first task alone would need CMA-ES to walk 0.3 units back to the default (more than
    the budget)."""
    task, sim = reach_skill('samples')
    robot = DefaultRobot(task, tol=0.01)
    rng = np.random.default_rng(3)
    away = sim.default_theta + 0.3 * robot.scale * np.sign(
        rng.standard_normal(sim.default_theta.shape))
    for tau in task.tau_low + (task.tau_high - task.tau_low) * rng.random((5, 2)):
        sim.add(tau, away)
    sim.save(tmp_path / 'sim.npz')
    settings = dict(num_tasks=4, num_test=2, seed=5, search=SearchSettings(max_rollouts=30))
    scratch = Learner(task, LearnSettings(**settings), tmp_path / 'scratch', robot).run()
    continued = Learner(task, LearnSettings(**settings, continue_from=str(tmp_path / 'sim.npz')),
                        tmp_path / 'continued', robot).run()
    assert scratch.summary.rollouts_per_task == [1, 1, 1, 1]
    assert continued.summary.fulfilled_tasks == 4
    assert all(n <= 3 for n in continued.summary.rollouts_per_task)
    assert continued.summary.total_rollouts <= 3 * scratch.summary.total_rollouts
