"""Policy search for one task instance with CMA-ES (`cma`), started from the skill.

Strategies (Queißer et al. 2016; reference chapter section 2.2.1):
- ``scratch``: CMA-ES from the task's default theta (the demonstration's fit);
- ``bootstrap``: CMA-ES from the skill's estimate PS(tau_i) (incremental bootstrapping);
- ``bootstrap_cost``: as bootstrap, plus ``beta ||theta - PS(tau_i)||^2`` in the objective
  (normalised theta units), which prefers solutions the skill can represent;
- ``hybrid``: first a coarse search over tau' in the E-dimensional task space with
  theta = PS(tau'), then refinement in the full F-dimensional policy space from the best theta.
Every search stops as soon as a rollout fulfils the task instance or the rollout budget is
spent; every rollout is counted. CMA-ES works in normalised coordinates
(theta = centre + scale * z) so one step size fits every task. Imports no ROS.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import cma
import numpy as np

STRATEGIES = ('scratch', 'bootstrap', 'bootstrap_cost', 'hybrid')

# evaluate(thetas (B, F)) -> (rewards (B,), fulfilled (B,))
Evaluate = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclasses.dataclass(frozen=True)
class SearchSettings:
    max_rollouts: int = 200         # per task instance
    popsize: int = 10
    sigma0: float = 0.1             # initial step size, normalised theta units
    cost_weight: float = 0.05       # beta of bootstrap_cost, per normalised unit squared
    hybrid_rollouts: float = 0.3    # share of the budget for the coarse task-space search
    hybrid_sigma0: float = 0.3      # initial step size of the task-space search, share of range


@dataclasses.dataclass
class SearchResult:
    theta: np.ndarray               # best policy found (F,)
    reward: float
    fulfilled: bool
    rollouts: int
    start_theta: np.ndarray         # where the search started (F,)
    rewards: list[float]            # every rollout's reward, in order


class _Budget:
    """Counts rollouts, keeps the best, and says when to stop."""

    def __init__(self, evaluate: Evaluate, max_rollouts: int):
        self.evaluate, self.max_rollouts = evaluate, max_rollouts
        self.rewards: list[float] = []
        self.best_theta, self.best_reward, self.fulfilled = None, -np.inf, False

    @property
    def left(self) -> int:
        return self.max_rollouts - len(self.rewards)

    @property
    def done(self) -> bool:
        return self.fulfilled or self.left <= 0

    def __call__(self, thetas: np.ndarray) -> np.ndarray:
        thetas = thetas[: self.left]
        rewards, fulfilled = self.evaluate(thetas)
        for theta, reward, ok in zip(thetas, rewards, fulfilled):
            self.rewards.append(float(reward))
            if (ok and not self.fulfilled) or (ok == self.fulfilled and reward > self.best_reward):
                self.best_theta, self.best_reward = theta.copy(), float(reward)
                self.fulfilled = self.fulfilled or bool(ok)
        return np.asarray(rewards, dtype=float)


def _cma(x0: np.ndarray, sigma0: float, popsize: int, seed: int, bounds=None):
    options = {'popsize': popsize, 'seed': int(seed) + 1, 'verbose': -9,
               'CMA_diagonal': x0.size > 20}
    if bounds is not None:
        options['bounds'] = bounds
    return cma.CMAEvolutionStrategy(x0, sigma0, options)


def cma_search(budget: _Budget, x0: np.ndarray, to_theta: Callable[[np.ndarray], np.ndarray],
               sigma0: float, popsize: int, seed: int, max_rollouts: int,
               penalty: Callable[[np.ndarray], float] | None = None, bounds=None) -> None:
    """Minimise -reward (+ penalty) over x with CMA-ES until done or max_rollouts used."""
    es = _cma(x0, sigma0, popsize, seed, bounds)
    stop_at = len(budget.rewards) + max_rollouts
    while not budget.done and len(budget.rewards) < stop_at:
        xs = np.array(es.ask())
        xs = xs[: max(1, stop_at - len(budget.rewards))]
        rewards = budget(np.array([to_theta(x) for x in xs]))
        if len(rewards) < popsize:          # budget cut the generation short: stop here
            break
        costs = -rewards + (np.array([penalty(x) for x in xs]) if penalty else 0.0)
        es.tell(list(xs), costs.tolist())


def search(strategy: str, evaluate: Evaluate, tau: np.ndarray, default_theta: np.ndarray,
           skill_estimate: Callable[[np.ndarray], np.ndarray], theta_centre: np.ndarray,
           theta_scale: np.ndarray, tau_low: np.ndarray, tau_high: np.ndarray,
           settings: SearchSettings = SearchSettings(), seed: int = 0) -> SearchResult:
    """Search theta for task instance tau with the given strategy (see the module docstring).

    Args:
        evaluate: rolls out thetas (B, F), returns rewards (B,) and fulfilled flags (B,).
        skill_estimate: tau (E,) -> PS(tau) (F,), the current skill.
        theta_centre, theta_scale: normalisation theta = centre + scale * z.
    """
    if strategy not in STRATEGIES:
        raise ValueError(f'unknown strategy {strategy!r}; known: {", ".join(STRATEGIES)}')
    budget = _Budget(evaluate, settings.max_rollouts)

    def to_theta(z):
        return theta_centre + theta_scale * z

    def to_z(theta):
        return (theta - theta_centre) / theta_scale

    estimate = skill_estimate(tau)
    start = default_theta if strategy == 'scratch' else estimate
    z_start = to_z(start)
    penalty = None
    if strategy == 'bootstrap_cost':
        def penalty(z):
            return settings.cost_weight * float(np.sum((z - z_start) ** 2))
    if strategy == 'hybrid':
        span = tau_high - tau_low
        coarse = max(settings.popsize, int(settings.hybrid_rollouts * settings.max_rollouts))
        # the start itself is the first coarse candidate: theta = PS(tau)
        budget(start[None])
        if not budget.done:
            u0 = (tau - tau_low) / span

            def task_theta(u):
                return skill_estimate(tau_low + np.clip(u, 0.0, 1.0) * span)
            if tau.size == 1:   # cma needs >= 2 dimensions: search a duplicated coordinate
                cma_search(budget, np.r_[u0, u0], lambda u: task_theta(u[:1]),
                           settings.hybrid_sigma0, settings.popsize, seed, coarse - 1)
            else:
                cma_search(budget, u0, task_theta, settings.hybrid_sigma0, settings.popsize,
                           seed, coarse - 1)
        if not budget.done:
            cma_search(budget, to_z(budget.best_theta), to_theta, settings.sigma0,
                       settings.popsize, seed + 7, budget.left)
    else:
        budget(start[None])       # the start is a candidate too: zero-shot success counts
        if not budget.done:
            cma_search(budget, z_start, to_theta, settings.sigma0, settings.popsize, seed,
                       budget.left, penalty)
    return SearchResult(theta=budget.best_theta, reward=budget.best_reward,
                        fulfilled=budget.fulfilled, rollouts=len(budget.rewards),
                        start_theta=start, rewards=budget.rewards)
