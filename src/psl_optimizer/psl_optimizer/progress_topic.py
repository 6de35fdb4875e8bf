"""The learning curve on the graph: a session's progress points (`SessionProgress`) published
as psl_msgs/LearningProgress on ``learning_progress``, one message per rollout, by whoever runs
a session with the graph (the learner node; ``psl learn --learner here --mode graph``). The view
(`psl_ros.foxglove_view`) plots them live, and ``psl record`` keeps them. `graph_session` is
such a session, assembled in one place for the learner node and ``psl learn``.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
from rclpy.node import Node
from std_msgs.msg import Header

from psl_msgs.msg import LearningProgress
from psl_optimizer.learning import Learner
from psl_optimizer.rollouts import Rollouts, Stopped
from psl_optimizer.session_progress import ProgressPoint, SessionProgress
from psl_ros import names
from psl_ros.qos import RELIABLE


def graph_session(task, settings, out, rollouts: Rollouts, node: Node, *, publisher=None,
                  skill=None, instances=None, should_stop: Callable[[], bool] | None = None,
                  on_points: Callable[[list[ProgressPoint]], None] | None = None) -> Learner:
    """A `Learner` session run with the graph's `node`: its rollouts reported
    (`ReportedRollouts`: its learning curve on ``learning_progress`` through `publisher`, by
    default a new one of the node's, stamped with the node's clock; `should_stop` and
    `on_points` as there); `skill` and `instances` as `Learner` takes them. Raises what
    `Learner` raises (a folder of another session, a bad memory file)."""
    learner = Learner(task, settings, out, rollouts, skill=skill, instances=instances)
    learner.rollouts = ReportedRollouts(learner.rollouts, learner,
                                        publisher or progress_publisher(node), node.get_clock(),
                                        should_stop=should_stop, on_points=on_points)
    return learner


def progress_publisher(node: Node):
    """The node's publisher of the learning curve (``learning_progress``)."""
    return node.create_publisher(LearningProgress, names.LEARNING_PROGRESS, RELIABLE)


class ReportedRollouts(Rollouts):
    """A session's rollouts, checked before each batch (`should_stop`: raise Stopped) and
    reported after it: a LearningProgress per rollout on `publisher`, stamped with `clock`,
    and the batch's points to `on_points` (e.g. an action's feedback). The counts of rollouts
    run, refused, failed and preempted are the inner rollouts' (the learner records them per
    task)."""

    def __init__(self, inner: Rollouts, learner: Learner, publisher, clock,
                 should_stop: Callable[[], bool] | None = None,
                 on_points: Callable[[list[ProgressPoint]], None] | None = None):
        # no Rollouts.__init__: the counts are the inner rollouts' (properties below)
        self.task, self.policy = inner.task, inner.policy
        self.inner, self.publisher, self.clock = inner, publisher, clock
        self.progress = SessionProgress(learner)
        self.should_stop, self.on_points = should_stop, on_points
        self.header = {'task': learner.task.name, 'strategy': learner.settings.strategy}

    @property
    def refused(self) -> int:
        return self.inner.refused

    @property
    def checked(self) -> int:
        return self.inner.checked

    @property
    def failed(self) -> int:
        return self.inner.failed

    @property
    def last_failure(self) -> str:
        return self.inner.last_failure

    @property
    def preempted(self) -> int:
        return self.inner.preempted

    @property
    def last_preemption(self) -> str:
        return self.inner.last_preemption

    def run(self, thetas: np.ndarray, taus: np.ndarray):
        if self.should_stop is not None and self.should_stop():
            raise Stopped('stopped between two rollouts')
        results = self.inner.run(thetas, taus)
        points = self.progress.after(taus, results)
        stamp = self.clock.now().to_msg()
        for point in points:
            fields = dataclasses.asdict(point)
            fields['tau'] = list(point.tau)
            self.publisher.publish(LearningProgress(header=Header(stamp=stamp), **self.header,
                                                    **fields))
        if points and self.on_points is not None:
            self.on_points(points)
        return results
