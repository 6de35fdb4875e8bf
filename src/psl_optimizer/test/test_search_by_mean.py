"""CMA-ES's answer is the mean of its search distribution (`policy_search.cma_search`,
``by_mean``): the mean is rolled out after every generation, the search ends when it fulfils
the instance, and it is the sample the skill learns; a draw that fulfils the instance ends the
search only if the budget ends before a mean fulfils (issue 26: on planar_10dof_reach the
samples lie nearer the other samples' prediction, zero-shot 83 -> 88.5 %)."""
import numpy as np

from psl_optimizer.policy_search import SearchSettings, search

F, E = 20, 2
TAU, LOW, HIGH = np.array([0.5, 0.5]), np.zeros(E), np.ones(E)
START = np.zeros(F)
GOAL = np.array([0.3, -0.3])      # what the task constrains: theta[:2] (a redundant task)
TOL = 0.02                        # fulfilled within this squared distance of GOAL
POPSIZE = 6


class Redundant:
    """reward = -||theta[:2] - GOAL||^2, the other coordinates do not matter; records every
    batch it is called with. `draws_only`: only a batch of more than one theta (a generation's
    draws, not the start or a mean) can fulfil the instance."""

    def __init__(self, draws_only=False):
        self.batches, self.draws_only = [], draws_only

    def __call__(self, thetas):
        self.batches.append(np.array(thetas))
        rewards = -np.sum((thetas[:, :2] - GOAL) ** 2, axis=1)
        return rewards, (rewards >= -TOL) & (len(thetas) > 1 or not self.draws_only)


def run(seed, objective, max_rollouts=300):
    return search('bootstrap', objective, TAU, START, lambda tau: START.copy(), np.zeros(F),
                  np.ones(F), LOW, HIGH,
                  SearchSettings(max_rollouts=max_rollouts, popsize=POPSIZE, sigma0=0.1),
                  seed=seed)


def fulfils(thetas):
    return np.sum((np.atleast_2d(thetas)[:, :2] - GOAL) ** 2, axis=1) <= TOL


def test_the_search_ends_at_a_fulfilling_mean_not_at_a_fulfilling_draw():
    went_on = 0                 # searches that went on after a generation with a success
    for seed in range(5):
        objective = Redundant()
        result = run(seed, objective)
        # the start, then per generation its draws and, alone, the mean after them
        sizes = [len(b) for b in objective.batches]
        assert sizes == [1] + [POPSIZE, 1] * ((len(sizes) - 1) // 2)
        assert result.fulfilled and result.rollouts == sum(sizes)
        # the sample is the last rollout: the first mean that fulfils the instance
        np.testing.assert_array_equal(result.theta, objective.batches[-1][0])
        means = objective.batches[2::2]
        assert fulfils(means[-1]).all() and not any(fulfils(m).any() for m in means[:-1])
        draws = objective.batches[1::2]
        went_on += any(fulfils(d).any() for d in draws[:-1])
    assert went_on          # e.g. seed 2: a draw fulfilled, the mean after it did not


def test_a_fulfilling_draw_is_the_result_when_the_budget_ends_first():
    objective = Redundant(draws_only=True)
    result = run(0, objective, max_rollouts=60)
    assert result.rollouts == 60 and result.fulfilled
    assert fulfils(result.theta).all()
    assert any(np.array_equal(result.theta, d) for b in objective.batches[1::2] for d in b)
