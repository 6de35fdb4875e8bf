"""Where a learning session stands after each rollout: the learning curve a viewer plots.

`SessionProgress` watches a `Learner`'s rollouts from outside (it is handed each batch and
its results) and turns them into one `ProgressPoint` per rollout of a training task: the
rollout's reward, the best so far on its task, the rollouts so far (on the task and in all),
the training tasks finished and fulfilled, and the skill's predictive variance (eq. 2.14, the
mean over theta's dimensions) at the task's instance before its search changed the skill.
The held-out test at the end is no training rollout and gives no point. Imports no ROS: the
learner node publishes the points (psl_msgs/LearningProgress) and its goal feedback from them.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np


@dataclasses.dataclass(frozen=True)
class ProgressPoint:
    """One rollout of a training task and the session around it (psl_msgs/LearningProgress)."""

    task_index: int             # the training task (0-based)
    tau: tuple[float, ...]      # its instance
    rollout: int                # rollouts of the session so far, this one counted
    rollouts_on_task: int       # rollouts of the current task so far, this one counted
    reward: float               # this rollout's
    fulfilled: bool             # this rollout's
    best_reward: float          # best on the current task so far
    task_fulfilled: bool        # some rollout of the current task fulfilled it
    tasks_done: int             # training tasks finished before the current one
    tasks_solved: int           # ... of which fulfilled
    skill_variance: float       # mean predictive variance at tau before the task; NaN: none


class SessionProgress:
    """The progress points of a `Learner`'s session (`after` each batch of its rollouts).

    Reads the learner's finished tasks (``done``, resumed ones included), its number of
    training tasks and its skill's ``variance``; the variance at a task's instance is taken at
    the task's first batch, before the task's sample enters the skill."""

    def __init__(self, learner):
        self.learner = learner
        self._task = -1                 # the index of the task the points are of
        self._on_task = 0
        self._best = -math.inf
        self._task_fulfilled = False
        self._variance = math.nan

    def after(self, taus: np.ndarray, results: Sequence) -> list[ProgressPoint]:
        """The points of a batch of rollouts (`Rollouts.run`'s taus, (B, E) or one (E,), and
        results); none in the held-out test after the last training task."""
        done, learner = self.learner.done, self.learner
        if len(done) >= learner.settings.num_tasks or not len(results):
            return []
        taus = np.asarray(taus, dtype=float)
        if taus.ndim == 1:
            taus = np.broadcast_to(taus, (len(results), len(taus)))
        if self._task != len(done):                         # a new task
            self._task, self._on_task, self._best = len(done), 0, -math.inf
            self._task_fulfilled = False
            variance = learner.skill.variance(np.asarray(taus[0], dtype=float))
            self._variance = (math.nan if variance is None
                              else float(np.mean(np.asarray(variance, dtype=float))))
        before = sum(record.rollouts for record in done)
        solved = sum(bool(record.fulfilled) for record in done)
        points = []
        for tau, result in zip(taus, results):
            evaluation = result.evaluation
            reward, fulfilled = float(evaluation.reward), bool(evaluation.fulfilled)
            self._on_task += 1
            self._best = max(self._best, reward)
            self._task_fulfilled = self._task_fulfilled or fulfilled
            points.append(ProgressPoint(
                task_index=self._task, tau=tuple(float(x) for x in tau),
                rollout=before + self._on_task, rollouts_on_task=self._on_task,
                reward=reward, fulfilled=fulfilled, best_reward=self._best,
                task_fulfilled=self._task_fulfilled, tasks_done=len(done),
                tasks_solved=solved, skill_variance=self._variance))
        return points
