"""The one factory of rollouts: a rollout mode's name -> a `psl_optimizer.rollouts.Rollouts`.

How a session's rollouts run is one choice (`MODES`): ``batch``, in this process with
``mujoco.rollout`` (`BatchRollouts`), or ``graph``, through the rollout workers of a running
graph (`GraphRollouts`, over ROS). Where the session runs — this process (``psl learn``) or the
graph's learner node (``psl learn --learner node``) — is another: either takes either mode.
The learning loop takes a `Rollouts` and imports no implementation.
"""
from __future__ import annotations

from typing import Callable, Sequence

from psl_optimizer.rollouts import MODES, Rollouts
from psl_ros.timeouts import ROLLOUT_TIMEOUT
from psl_task.task import TaskDefinition


def make_rollouts(mode: str, task: TaskDefinition, *, workers: Sequence | None = None,
                  timeout: float = ROLLOUT_TIMEOUT,
                  should_stop: Callable[[], bool] | None = None) -> Rollouts:
    """The rollouts of `mode` for `task`.

    Args:
        workers: graph mode: one `psl_ros.client.RolloutClient` per rollout worker.
        timeout: graph mode: seconds to wait for one rollout.
        should_stop: graph mode: asked between two rollouts (e.g. a cancelled goal).

    Raises:
        ValueError: an unknown mode, or graph mode without workers.
    """
    if mode == 'batch':
        from psl_optimizer.batch_rollout import BatchRollouts
        return BatchRollouts(task)
    if mode == 'graph':
        if not workers:
            raise ValueError('graph mode needs the rollout workers (RolloutClient per worker)')
        from psl_optimizer.graph_rollout import GraphRollouts
        return GraphRollouts(task, list(workers), timeout=timeout,
                             should_stop=should_stop or (lambda: False))
    raise ValueError(f'unknown rollout mode {mode!r}; known: {", ".join(MODES)}')
