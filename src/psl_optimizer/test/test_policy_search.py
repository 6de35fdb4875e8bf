"""CMA-ES policy search: what each strategy starts from and optimises, checked on a known
quadratic problem instead of assumed."""
import numpy as np
import pytest

from psl_optimizer.policy_search import STRATEGIES, SearchSettings, search

F, E = 6, 2
TARGET = np.linspace(-1.0, 1.0, F)
DEFAULT = np.zeros(F)
TAU = np.array([0.3, 0.7])
LOW, HIGH = np.zeros(E), np.ones(E)
A = np.arange(F * E, dtype=float).reshape(F, E) / 10.0   # a linear "skill": PS(tau) = A tau + b
B = np.full(F, 0.5)


def skill(tau):
    return A @ tau + B


class Recorder:
    """reward = -||theta - target||^2; fulfilled when within `tol`; records every theta."""

    def __init__(self, target=TARGET, tol=-1.0):
        self.target, self.tol, self.thetas = target, tol, []

    def __call__(self, thetas):
        self.thetas.extend(np.array(thetas))
        rewards = -np.sum((thetas - self.target) ** 2, axis=1)
        return rewards, rewards >= -self.tol if self.tol >= 0 else np.zeros(len(thetas), bool)


def run(strategy, evaluate, settings=SearchSettings(max_rollouts=60, popsize=6), seed=0):
    return search(strategy, evaluate, TAU, DEFAULT, skill, np.zeros(F), np.ones(F), LOW, HIGH,
                  settings, seed=seed)


@pytest.mark.parametrize('strategy, expected', [
    ('scratch', DEFAULT), ('bootstrap', skill(TAU)), ('bootstrap_cost', skill(TAU)),
    ('hybrid', skill(TAU))])
def test_the_first_rollout_is_the_strategy_start(strategy, expected):
    recorder = Recorder()
    result = run(strategy, recorder)
    np.testing.assert_array_equal(recorder.thetas[0], expected)
    np.testing.assert_array_equal(result.start_theta, expected)


@pytest.mark.parametrize('strategy', STRATEGIES)
def test_budget_and_rollout_count(strategy):
    recorder = Recorder()
    result = run(strategy, recorder)
    assert result.rollouts == len(recorder.thetas) == 60
    assert not result.fulfilled
    assert result.reward == pytest.approx(max(-np.sum((t - TARGET) ** 2)
                                              for t in recorder.thetas))


@pytest.mark.parametrize('strategy', STRATEGIES)
def test_stops_at_the_first_success(strategy):
    recorder = Recorder(target=skill(TAU) + 0.05, tol=0.5)     # the start already succeeds
    if strategy == 'scratch':
        recorder = Recorder(target=DEFAULT + 0.05, tol=0.5)
    result = run(strategy, recorder)
    assert result.fulfilled and result.rollouts == 1


def test_cost_term_changes_the_objective():
    """Same seed, same rewards: bootstrap_cost keeps its samples nearer PS(tau) than
    bootstrap, because its objective adds beta ||z - z_start||^2."""
    start = skill(TAU)
    spread = {}
    for strategy, weight in (('bootstrap', 0.0), ('bootstrap_cost', 50.0)):
        recorder = Recorder()
        run(strategy, recorder, SearchSettings(max_rollouts=121, popsize=6, cost_weight=weight))
        late = np.array(recorder.thetas[-30:])
        spread[strategy] = np.mean(np.linalg.norm(late - start, axis=1))
        first_generation = np.array(recorder.thetas[1:7])
        spread[strategy + '_first'] = first_generation
    # the first generation is drawn before any objective value is seen: identical
    np.testing.assert_array_equal(spread['bootstrap_first'], spread['bootstrap_cost_first'])
    assert spread['bootstrap_cost'] < 0.5 * spread['bootstrap']


def test_hybrid_searches_the_task_space_first():
    """Coarse phase: every theta is PS(tau') for some tau' within the task ranges."""
    recorder = Recorder()
    settings = SearchSettings(max_rollouts=40, popsize=6, hybrid_rollouts=0.5)
    run('hybrid', recorder, settings)
    coarse = np.array(recorder.thetas[:20])
    taus, *_ = np.linalg.lstsq(A, (coarse - B).T, rcond=None)       # (E, n)
    np.testing.assert_allclose(A @ taus + B[:, None], coarse.T, atol=1e-9)
    assert np.all(taus >= -1e-9) and np.all(taus <= 1 + 1e-9)
    fine = np.array(recorder.thetas[20:])
    residual = fine.T - (A @ np.linalg.lstsq(A, (fine - B).T, rcond=None)[0] + B[:, None])
    assert np.abs(residual).max() > 1e-3        # then the full policy space


def test_unknown_strategy():
    with pytest.raises(ValueError, match='unknown strategy'):
        run('magic', Recorder())
