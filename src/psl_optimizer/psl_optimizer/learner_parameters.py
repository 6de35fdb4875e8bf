"""The learner node's parameters (`psl_ros.parameters.declare` makes them; imports no ROS)."""
from __future__ import annotations

import dataclasses
from dataclasses import field

from psl_optimizer.learning import LearnSettings
from psl_optimizer.policy_search import SearchSettings
from psl_optimizer.rollouts import MODES
from psl_ros.timeouts import ROLLOUT_TIMEOUT, SERVICE_TIMEOUT


@dataclasses.dataclass(frozen=True)
class LearnerParameters:
    """What a learn goal does not say; the search's defaults are `SearchSettings`'."""

    mode: str = field(default=MODES[0], metadata={'doc': (
        'batch (in-process mujoco.rollout) | graph (execute_rollout); a goal may choose')})
    output_root: str = field(default='runs', metadata={'doc': (
        'sessions write into <output_root>/<task>-<strategy>-seed<seed>')})
    test_tasks: int = field(default=LearnSettings.num_test, metadata={'doc': (
        'held-out instances tested zero-shot at the end of a session')})
    max_tasks: int = field(default=10_000, metadata={'doc': (
        'a goal with more training (or test) tasks is refused')})
    max_rollouts_per_task: int = field(default=10_000, metadata={'doc': (
        'a goal with a larger budget per task is refused')})
    popsize: int = field(default=SearchSettings.popsize, metadata={'doc': (
        'CMA-ES population size')})
    sigma0: float = field(default=SearchSettings.sigma0, metadata={'doc': (
        'CMA-ES initial step size, normalised theta units')})
    cost_weight: float = field(default=SearchSettings.cost_weight, metadata={'doc': (
        'beta of bootstrap_cost (normalised theta units squared)')})
    service_timeout: float = field(default=SERVICE_TIMEOUT, metadata={'doc': (
        'seconds to wait for a skill memory answer')})
    rollout_timeout: float = field(default=ROLLOUT_TIMEOUT, metadata={'doc': (
        'seconds to wait for one graph-mode rollout')})
    tau_topic: str = field(default='task_instance_request', metadata={'doc': (
        "task selection 'given': the topic the instances come on (std_msgs/Float64MultiArray, "
        'data = tau; psl_ros/instance_source.py)')})
    tau_timeout: float = field(default=600.0, metadata={'doc': (
        "task selection 'given': seconds to wait for the next instance before the session "
        'ends with the reason')})
    workers: tuple[str, ...] = field(default=('',), metadata={'doc': (
        "graph mode: namespaces of the rollout workers, relative to this node's ('' = its "
        'own); a population is spread over them, one rollout per worker at a time; psl up '
        '--workers N sets worker0..N-1')})

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f'mode must be one of {", ".join(MODES)}, got {self.mode!r}')
        if not self.workers:
            raise ValueError("workers needs at least one namespace ('' = own)")
        if self.test_tasks < 0:
            raise ValueError(f'test_tasks must be >= 0, got {self.test_tasks}')
        for name in ('max_tasks', 'max_rollouts_per_task', 'popsize'):
            if getattr(self, name) < 1:
                raise ValueError(f'{name} must be >= 1, got {getattr(self, name)}')
        if not self.tau_topic:
            raise ValueError('tau_topic must name a topic')
        for name in ('sigma0', 'service_timeout', 'rollout_timeout', 'tau_timeout'):
            if not getattr(self, name) > 0.0:
                raise ValueError(f'{name} must be > 0, got {getattr(self, name)}')
        if not self.cost_weight >= 0.0:
            raise ValueError(f'cost_weight must be >= 0, got {self.cost_weight}')

    def search(self, max_rollouts: int) -> SearchSettings:
        """The search settings of a goal with this budget."""
        return SearchSettings(max_rollouts=max_rollouts, popsize=self.popsize,
                              sigma0=self.sigma0, cost_weight=self.cost_weight)
