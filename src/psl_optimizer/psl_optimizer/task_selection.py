"""Which task instances a session trains and tests on.

Training instances come from a seed (`task_sequence`, uniform over the task's ranges); the
held-out test instances from a separate stream of the same seed (`held_out_tasks`), never
trained on. With active task selection (``variance``) the next training instance is instead
the candidate where the skill is least certain (`most_uncertain`). With ``given`` the instances
come from the environment ("the task parameterization is typically given by environmental
conditions and cannot be influenced by the learning method"): a source the session is handed
(`psl_ros.instance_source.TopicInstances`: perception or an operator on a topic) says each
one; the session learns on whatever it is given. Imports no ROS.
"""
from __future__ import annotations

import itertools
from typing import Callable, Iterator

import numpy as np

from psl_task.task import TaskDefinition

TEST_SEED_OFFSET = 1_000_003     # held-out instances: a stream no training sequence uses


def task_stream(task: TaskDefinition, seed: int) -> Iterator[np.ndarray]:
    """The training instances of a seed, one at a time (E,), uniform over the task's ranges;
    endless and lazy, so a session of any length costs memory for one instance only."""
    rng = np.random.default_rng(seed)
    while True:
        yield task.sample_tau(rng)


def task_sequence(task: TaskDefinition, count: int, seed: int) -> np.ndarray:
    """The first `count` instances of `task_stream` as an array (count, E)."""
    return np.array(list(itertools.islice(task_stream(task, seed), count))).reshape(count, -1)


def held_out_tasks(task: TaskDefinition, count: int, seed: int) -> np.ndarray:
    return task_sequence(task, count, seed + TEST_SEED_OFFSET)


TASK_SELECTIONS = ('random', 'variance', 'given')
CANDIDATE_SEED_OFFSET = 2_000_003   # candidates of variance-driven selection: their own stream


def most_uncertain(task: TaskDefinition, variance: Callable[[np.ndarray], np.ndarray | None],
                   count: int, seed: int, index: int) -> np.ndarray:
    """Active task selection: of `count` candidates drawn from the task distribution (a stream
    seeded by seed and index, so a resumed session draws the same ones), the one whose
    predictive variance (eq. 2.14), averaged over theta's dimensions, is largest (a skill
    scales every theta dimension alike, `scaler_around`, so theta units rank as normalised
    ones). Raises ValueError when the skill's readout gives no variance."""
    candidates = task_sequence(task, count, (seed + CANDIDATE_SEED_OFFSET) * 100_003 + index)
    scores = []
    for tau in candidates:
        var = variance(tau)
        if var is None:
            raise ValueError("task selection 'variance' needs a readout with predictive "
                             "variance (readout: bayes)")
        scores.append(float(np.mean(var)))
    return candidates[int(np.argmax(scores))]
