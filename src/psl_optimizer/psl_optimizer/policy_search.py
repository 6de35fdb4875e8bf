"""Policy search for one task instance with CMA-ES (`cma`), started from the skill.

Strategies (Queißer et al. 2016; reference chapter section 2.2.1):
- ``scratch``: CMA-ES from the task's default theta (the demonstration's fit);
- ``bootstrap``: CMA-ES from the skill's estimate PS(tau_i) (incremental bootstrapping);
- ``bootstrap_cost``: as bootstrap, plus ``beta ||theta - PS(tau_i)||^2`` in the objective
  (normalised theta units), which prefers solutions the skill can represent;
- ``hybrid``: first a coarse search over tau' in the E-dimensional task space with
  theta = PS(tau'), then refinement in the full F-dimensional policy space from the best theta.
  The coarse phase is only worth its rollouts when the skill already maps the task space to
  distinct policies and the search makes headway, so it is skipped while PS(tau') stays within
  one fine step of PS(tau) around tau (a young skill: with no sample PS is constant), and it
  ends once `hybrid_patience` generations in a row raise the best reward by no more than
  `hybrid_min_gain` of its magnitude (see `hybrid_search`).
A skill may offer other guesses than its estimate (a continued skill: the simulated skill
without the robot's correction, an empty skill's answer; `psl_optimizer.learning
.ResidualComposition.alternatives`): when the start misses, each is rolled out once before the
search pays a CMA-ES generation, and the search goes on from the best of them (`try_guesses`;
'scratch' uses none). Every search stops as soon as its estimate of the solution fulfils the
task instance or the rollout budget is spent; every rollout is counted. CMA-ES's estimate is
the mean of its search distribution, rolled out after every generation (`cma_search`): a draw
that fulfils the instance ends the search only if the budget ends before a mean does. CMA-ES
works in normalised coordinates (theta = centre + scale * z) so one step size fits every task.
Imports no ROS.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np

STRATEGIES = ('scratch', 'bootstrap', 'bootstrap_cost', 'hybrid')
SAME_GUESS = 1e-9      # normalised theta units: guesses this close are one policy (`try_guesses`)

# The objective of one task instance: objective(thetas (B, F)) -> (rewards (B,), fulfilled (B,))
# (the learner binds its rollouts to the instance: `Rollouts.evaluate(thetas, tau)`)
Objective = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclasses.dataclass(frozen=True)
class SearchSettings:
    max_rollouts: int = 200         # per task instance
    popsize: int = 10
    sigma0: float = 0.1             # initial step size, normalised theta units
    cost_weight: float = 0.05       # beta of bootstrap_cost, per normalised unit squared
    hybrid_rollouts: float = 0.3    # share of the budget for the coarse task-space search
    hybrid_sigma0: float = 0.3      # initial step size of the task-space search, share of range
    hybrid_patience: int = 1        # coarse generations in a row without progress before refining
    hybrid_min_gain: float = 0.01   # progress: best reward up by more than this share of |best|
    hybrid_min_reach: float = 1.0   # coarse phase only if PS moves theta >= this many sigma0

    def __post_init__(self):
        if self.hybrid_patience < 1:
            raise ValueError(f'hybrid_patience must be >= 1, got {self.hybrid_patience}')
        if self.hybrid_min_gain < 0.0 or self.hybrid_min_reach < 0.0:
            raise ValueError('hybrid_min_gain and hybrid_min_reach must be >= 0')


@dataclasses.dataclass
class SearchResult:
    theta: np.ndarray               # best policy found (F,)
    reward: float
    fulfilled: bool
    rollouts: int
    start_theta: np.ndarray         # where the search started (F,)
    rewards: list[float]            # every rollout's reward, in order


class _Budget:
    """Counts rollouts, keeps the best, and says when to stop: when a rollout of an estimate
    (`settles`) fulfils the instance, or the budget is spent. Until then the best is the best
    fulfilling rollout, or the best rollout if none fulfils; a settling success is the result
    whatever a draw before it scored."""

    def __init__(self, objective: Objective, max_rollouts: int):
        self.objective, self.max_rollouts = objective, max_rollouts
        self.rewards: list[float] = []
        self.best_theta, self.best_reward, self.fulfilled = None, -np.inf, False
        self.settled = False

    @property
    def left(self) -> int:
        return self.max_rollouts - len(self.rewards)

    @property
    def done(self) -> bool:
        return self.settled or self.left <= 0

    def __call__(self, thetas: np.ndarray, settles: bool = True) -> np.ndarray:
        """Rewards of thetas (B, F), within the budget. `settles`: they are estimates of the
        solution (a start, a search distribution's mean), not draws around one."""
        thetas = thetas[: self.left]
        rewards, fulfilled = self.objective(thetas)
        for theta, reward, ok in zip(thetas, rewards, fulfilled):
            self.rewards.append(float(reward))
            if ok and settles and not self.settled:
                self.best_theta, self.best_reward = theta.copy(), float(reward)
                self.fulfilled = self.settled = True
            elif (ok and not self.fulfilled) or (ok == self.fulfilled
                                                 and reward > self.best_reward):
                self.best_theta, self.best_reward = theta.copy(), float(reward)
                self.fulfilled = self.fulfilled or bool(ok)
        return np.asarray(rewards, dtype=float)


def _cma(x0: np.ndarray, sigma0: float, popsize: int, seed: int, bounds=None):
    import cma        # here, not at the top: the command line reads STRATEGIES without it

    options = {'popsize': popsize, 'seed': int(seed) + 1, 'verbose': -9,
               'CMA_diagonal': x0.size > 20}
    if bounds is not None:
        options['bounds'] = bounds
    return cma.CMAEvolutionStrategy(x0, sigma0, options)


def cma_search(budget: _Budget, x0: np.ndarray, to_theta: Callable[[np.ndarray], np.ndarray],
               sigma0: float, popsize: int, seed: int, max_rollouts: int,
               penalty: Callable[[np.ndarray], float] | None = None, bounds=None,
               patience: int | None = None, min_gain: float = 0.0, by_mean: bool = True) -> None:
    """Minimise -reward (+ penalty) over x with CMA-ES until done or max_rollouts used.

    `by_mean`: the search's answer is the mean m of its distribution (Hansen, The CMA Evolution
    Strategy: A Tutorial, arXiv:1604.00772; pycma's ``result.xfavorite``, "to be considered as
    current best estimate of the optimum"), rolled out after every generation: the search ends
    when the mean fulfils the instance, and the mean is the sample the skill learns. A draw that
    fulfils it only ends the search when the budget ends first. A draw is the mean plus sigma
    times a random step in all F dimensions, most of which a task does not constrain (a
    redundant arm reaching a point: the rest of its joint space), so a lucky draw teaches the
    skill that noise; the mean is the weighted average of the best draws, in which it averages
    out, and neighbouring instances' samples stay consistent (issue 26, psl bench learn on
    planar_10dof_reach, bootstrap, seeds 0-9: zero-shot 83 -> 88.5 %, lowest seed 55 -> 70 %,
    538 -> 570 rollouts per session; leave-one-out distance of a sample to the others'
    prediction 0.024 -> 0.014 normalised units). Without it (the task-space phase of hybrid,
    whose draws are on the skill's image anyway) the first fulfilling draw ends the search.

    With `patience`, also stop after that many generations in a row none of which raised the
    budget's best reward by more than ``min_gain * |best before the generation|`` (the first
    generation is measured against the best before the search, e.g. its start)."""
    es = _cma(x0, sigma0, popsize, seed, bounds)
    stop_at = len(budget.rewards) + max_rollouts
    idle = 0                                # generations in a row without progress
    while not budget.done and len(budget.rewards) < stop_at:
        best_before = budget.best_reward
        xs = np.array(es.ask())
        xs = xs[: max(1, stop_at - len(budget.rewards))]
        rewards = budget(np.array([to_theta(x) for x in xs]), settles=not by_mean)
        if len(rewards) < popsize:          # budget cut the generation short: stop here
            break
        costs = -rewards + (np.array([penalty(x) for x in xs]) if penalty else 0.0)
        es.tell(list(xs), costs.tolist())
        if by_mean and len(budget.rewards) < stop_at:
            budget(np.asarray(to_theta(es.result.xfavorite))[None])
        if patience is not None:
            progress = (not np.isfinite(best_before)
                        or budget.best_reward - best_before > min_gain * abs(best_before))
            idle = 0 if progress else idle + 1
            if idle >= patience:
                break


def task_space_reach(skill_estimate: Callable[[np.ndarray], np.ndarray], tau: np.ndarray,
                     tau_low: np.ndarray, tau_high: np.ndarray, theta_scale: np.ndarray,
                     step: float) -> float:
    """How far the skill moves theta when tau moves: the largest RMS over theta's normalised
    coordinates of PS(tau') - PS(tau), over the probes tau' = tau +- step * (high - low) along
    each task axis, clipped to the ranges. Costs skill queries only, no rollout."""
    centre = skill_estimate(tau)
    span = tau_high - tau_low
    reach = 0.0
    for axis in np.eye(tau.size):
        for sign in (-1.0, 1.0):
            probe = np.clip(tau + sign * step * span * axis, tau_low, tau_high)
            moved = (skill_estimate(probe) - centre) / theta_scale
            reach = max(reach, float(np.sqrt(np.mean(moved ** 2))))
    return reach


def hybrid_search(budget: _Budget, tau: np.ndarray, skill_estimate, to_theta, to_z,
                  theta_scale: np.ndarray, tau_low: np.ndarray, tau_high: np.ndarray,
                  settings: SearchSettings, seed: int) -> None:
    """Coarse CMA-ES over u = (tau' - low) / span with theta = PS(tau'), then CMA-ES in the
    full normalised theta space from the best theta found (budget's start already evaluated).

    The coarse phase runs only when the skill reaches at least ``hybrid_min_reach * sigma0``
    (`task_space_reach` with probes 2 hybrid_sigma0 away, where its first generations land):
    otherwise every PS(tau') lies within the step the refinement's first generation takes
    anyway. It gets at most ``hybrid_rollouts`` of the budget and stops early on stagnation
    (``hybrid_patience``, ``hybrid_min_gain``; see `cma_search`)."""
    span = tau_high - tau_low
    if not budget.done and task_space_reach(skill_estimate, tau, tau_low, tau_high, theta_scale,
                                            2.0 * settings.hybrid_sigma0) \
            >= settings.hybrid_min_reach * settings.sigma0:
        coarse = max(settings.popsize, int(settings.hybrid_rollouts * settings.max_rollouts))
        u0 = (tau - tau_low) / span

        def task_theta(u):
            return skill_estimate(tau_low + np.clip(u, 0.0, 1.0) * span)
        if tau.size == 1:   # cma needs >= 2 dimensions: search a duplicated coordinate
            x0, to_coarse_theta = np.r_[u0, u0], lambda u: task_theta(u[:1])
        else:
            x0, to_coarse_theta = u0, task_theta
        cma_search(budget, x0, to_coarse_theta, settings.hybrid_sigma0, settings.popsize, seed,
                   coarse - 1, patience=settings.hybrid_patience,
                   min_gain=settings.hybrid_min_gain, by_mean=False)
    if not budget.done:
        cma_search(budget, to_z(budget.best_theta), to_theta, settings.sigma0,
                   settings.popsize, seed + 7, budget.left)


def try_guesses(budget: _Budget, guesses: Sequence[np.ndarray],
                to_z: Callable[[np.ndarray], np.ndarray]) -> None:
    """Roll out guesses of the solution (each (F,)) one at a time, in order, until one
    fulfils the instance (each settles the search, `_Budget`) or none is left; a guess within
    `SAME_GUESS` (normalised units, every coordinate) of one rolled out before is the same
    policy and skipped. One rollout per guess: a wrong first guess followed by CMA-ES costs a
    whole generation and its mean (popsize + 1 rollouts), so a second guess that fulfils saves
    at least popsize rollouts, and one that does not costs one."""
    tried: list[np.ndarray] = []
    for theta in guesses:
        if budget.done:
            return
        z = to_z(theta)
        if any(np.max(np.abs(z - other)) <= SAME_GUESS for other in tried):
            continue
        budget(np.asarray(theta, dtype=float)[None])
        tried.append(z)


def search(strategy: str, objective: Objective, tau: np.ndarray, default_theta: np.ndarray,
           skill_estimate: Callable[[np.ndarray], np.ndarray], theta_centre: np.ndarray,
           theta_scale: np.ndarray, tau_low: np.ndarray, tau_high: np.ndarray,
           settings: SearchSettings = SearchSettings(), seed: int = 0,
           alternatives: Sequence[np.ndarray] = ()) -> SearchResult:
    """Search theta for task instance tau with the given strategy (see the module docstring).

    Args:
        objective: rolls out thetas (B, F) on tau, returns rewards (B,) and fulfilled flags
            (B,).
        skill_estimate: tau (E,) -> PS(tau) (F,), the current skill.
        theta_centre, theta_scale: normalisation theta = centre + scale * z.
        alternatives: other guesses of the skill (each (F,)) than its estimate, tried in
            order after the start fails (`try_guesses`); 'scratch' does not use the skill.
    """
    if strategy not in STRATEGIES:
        raise ValueError(f'unknown strategy {strategy!r}; known: {", ".join(STRATEGIES)}')
    budget = _Budget(objective, settings.max_rollouts)

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
    # the start is a candidate too (zero-shot success counts), then the skill's other guesses
    try_guesses(budget, [start, *(() if strategy == 'scratch' else alternatives)], to_z)
    if strategy == 'hybrid':    # the start is the first coarse candidate: theta = PS(tau)
        hybrid_search(budget, tau, skill_estimate, to_theta, to_z, theta_scale, tau_low,
                      tau_high, settings, seed)
    elif not budget.done:       # from the best guess (the start when it was the only one)
        cma_search(budget, to_z(budget.best_theta), to_theta, settings.sigma0,
                   settings.popsize, seed, budget.left, penalty)
    return SearchResult(theta=budget.best_theta, reward=budget.best_reward,
                        fulfilled=budget.fulfilled, rollouts=len(budget.rewards),
                        start_theta=start, rewards=budget.rewards)
