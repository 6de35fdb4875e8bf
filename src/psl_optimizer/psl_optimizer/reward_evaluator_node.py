"""The reward evaluator node: watches each episode and publishes ``rollout_evaluation``.

An episode is announced by the simulator on ``task_instance`` (task, tau, stamp of the first
state, number of steps). The evaluator collects the ``joint_states`` of that episode and the
controller's ``reference`` for each of them (matched by time stamp, so arrival order does not
matter), scores the rollout with the task's reward (`psl_optimizer.reward.Reward`, the
geometry from a kinematic replay of the measured joint angles) and publishes a
psl_msgs/RolloutEvaluation stamped with the episode's first state.
"""
from __future__ import annotations

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState

from psl_msgs.msg import RolloutEvaluation, TaskInstance
from psl_optimizer.reward import Reward
from psl_ros import names
from psl_ros.hot_path import HotPath
from psl_ros.node_main import run_node
from psl_ros.qos import LATCHED, RELIABLE, WHOLE_EPISODE
from psl_ros.stamps import to_ns
from psl_sim.arm_model import ArmModel
from psl_sim.reward_geometry import RewardGeometry
from psl_sim.task import TaskError, load_task
BUFFER = 5000   # messages kept per stream while the episode announcement is on its way


class RewardEvaluator(Node):

    def __init__(self):
        super().__init__('reward_evaluator')
        self._rewards: dict[str, Reward] = {}       # by task id
        self.episode: TaskInstance | None = None
        self.states: dict[int, JointState] = {}
        self.references: dict[int, JointState] = {}
        self.pub = self.create_publisher(RolloutEvaluation, names.ROLLOUT_EVALUATION, RELIABLE)
        self.hot_path = HotPath(self)
        self.hot_path.subscribe(TaskInstance, names.TASK_INSTANCE, self.on_task, LATCHED)
        self.hot_path.subscribe(JointState, names.JOINT_STATES, self.on_state, WHOLE_EPISODE)
        self.hot_path.subscribe(JointState, names.REFERENCE, self.on_reference, WHOLE_EPISODE)
        self.hot_path.start()
        self.get_logger().info('evaluating episodes announced on task_instance')

    def on_task(self, msg: TaskInstance) -> None:
        if self.episode is not None:
            self.get_logger().warning(
                f'episode at {to_ns(self.episode.stamp)} ns was not evaluated: got '
                f'{len(self.states)} states and {len(self.references)} references of '
                f'{self.episode.num_steps + 1}')
        self.episode = msg
        t0 = to_ns(msg.stamp)
        for stream in (self.states, self.references):
            for t in [t for t in stream if t < t0]:
                del stream[t]
        self._try_finish()

    def on_state(self, msg: JointState) -> None:
        self._store(self.states, msg)

    def on_reference(self, msg: JointState) -> None:
        self._store(self.references, msg)

    def _store(self, stream: dict[int, JointState], msg: JointState) -> None:
        stream[to_ns(msg.header.stamp)] = msg
        if len(stream) > BUFFER:
            del stream[min(stream)]
        self._try_finish()

    def _try_finish(self) -> None:
        ep = self.episode
        if ep is None:
            return
        if min(len(self.states), len(self.references)) <= ep.num_steps:
            return
        t0, period = to_ns(ep.stamp), int(round(ep.control_period * 1e9))
        times = [t0 + k * period for k in range(ep.num_steps + 1)]
        if not all(t in self.states and t in self.references for t in times):
            return
        self.episode = None
        states = [self.states.pop(t) for t in times]
        refs = [self.references.pop(t) for t in times]
        try:
            self.pub.publish(self._evaluate(ep, states, refs))
        except (TaskError, ValueError) as exc:
            self.get_logger().error(f'cannot evaluate episode of {ep.task!r}: {exc}')

    def _evaluate(self, ep: TaskInstance, states, refs) -> RolloutEvaluation:
        if ep.task not in self._rewards:
            task = load_task(ep.task)
            self._rewards[ep.task] = Reward(task, RewardGeometry(ArmModel(task)))
        q = np.array([[s.position for s in states]])             # a population of one
        torque = np.array([[s.effort for s in states]])
        q_ref = np.array([[r.position for r in refs]])
        result = self._rewards[ep.task].evaluate_replayed(q, torque, q_ref,
                                                          np.asarray(ep.tau)[None])[0]
        return RolloutEvaluation(
            stamp=ep.stamp, task=ep.task, tau=list(ep.tau), reward=result.reward,
            fulfilled=result.fulfilled, component_names=list(result.components),
            component_values=list(result.components.values()),
            tracking_error=result.components['tracking_error'], num_steps=ep.num_steps)


    def destroy_node(self):
        self.hot_path.stop()
        super().destroy_node()


def main(args=None):
    run_node(RewardEvaluator, args)


if __name__ == '__main__':
    main()
