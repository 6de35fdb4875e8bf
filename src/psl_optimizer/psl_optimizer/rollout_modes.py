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
from psl_task.model_error import ModelError
from psl_task.task import TaskDefinition


def make_rollouts(mode: str, task: TaskDefinition, *, workers: Sequence | None = None,
                  timeout: float = ROLLOUT_TIMEOUT,
                  should_stop: Callable[[], bool] | None = None,
                  model_error: ModelError | str = '',
                  measurement_noise=None, threads: int = 2) -> Rollouts:
    """The rollouts of `mode` for `task`.

    Args:
        model_error: batch mode: how the simulated robot differs from the task's model
            (`ModelError`, or its text for `ModelError.parse`; sim to real). Graph mode rolls
            out on the graph's robot, which is what it is: only the identity is accepted.
        measurement_noise: batch mode: noise on the measured joint states
            (`psl_optimizer.batch_rollout.MeasurementNoise`, or its text); graph mode: none.
        threads: batch mode: of `mujoco.rollout` for a population (the same results with
            any; 1 for a session of a sweep whose cores are the sweep's).
        workers: graph mode: one `psl_ros.client.RolloutClient` per rollout worker.
        timeout: graph mode: seconds to wait for one rollout.
        should_stop: graph mode: asked between two rollouts (e.g. a cancelled goal).

    Raises:
        ValueError: an unknown mode, graph mode without workers or with a model error, or a
            model error that does not parse.
    """
    from psl_optimizer.batch_rollout import MeasurementNoise
    if isinstance(model_error, str):
        model_error = ModelError.parse(model_error)
    if measurement_noise is None or isinstance(measurement_noise, str):
        measurement_noise = MeasurementNoise.parse(measurement_noise or '')
    if mode == 'batch':
        from psl_optimizer.batch_rollout import BatchRollouts
        return BatchRollouts(task, n_threads=threads, model_error=model_error,
                             measurement_noise=measurement_noise)
    if mode == 'graph':
        if not (model_error.is_identity and measurement_noise.is_off):
            raise ValueError('a model error and measurement noise are for batch mode: graph '
                             "mode rolls out on the graph's robot (a simulator's error and "
                             'noise are its own settings)')
        if not workers:
            raise ValueError('graph mode needs the rollout workers (RolloutClient per worker)')
        from psl_optimizer.graph_rollout import GraphRollouts
        return GraphRollouts(task, list(workers), timeout=timeout,
                             should_stop=should_stop or (lambda: False))
    raise ValueError(f'unknown rollout mode {mode!r}; known: {", ".join(MODES)}')
