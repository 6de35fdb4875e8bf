"""The reward evaluator node: watches each episode and publishes ``rollout_evaluation``.

An episode is announced by the simulator on ``task_instance`` (task, tau, stamp of the first
state, number of steps). The evaluator collects the ``joint_states`` of that episode and the
controller's ``reference`` for each of them (matched by time stamp, so arrival order does not
matter), scores the rollout with the task's reward (`psl_optimizer.reward.Reward`, the
geometry from a kinematic replay of the measured joint angles) and publishes a
psl_msgs/RolloutEvaluation stamped with the episode's first state, carrying the measured
episode (joint angles, velocities, applied torques and the controller's reference of each
state) for learners that need it (ILC in graph mode).

A robot psl does not simulate stamps its states with its own clock (jitter, a state late or
missing): when the states are not on the control grid, the episode is complete once a state
and a reference past its end have come, and both streams are interpolated onto the grid
(`psl_optimizer.episode_grid`; a gap of more than `MAX_GAP` is logged and the episode not
scored). States are read by joint name (`psl_task.joint_selection`: the robot's
order, extra joints ignored); a robot that reports no effort is scored with zero torque (a
warning says so).

A goal change the executor made (``~/goal_change``, psl_msgs/GoalChange: stamped with the
episode's start, or zero for the next episode) makes the episode's goal the new goal's
position (and, for a pose, orientation: `Reward.goal_of`) if the controller tracked it: its reference of the
episode's last state is the changed trajectory's (``last_reference``, compared exactly; the
controller refuses a live change that came too late, and the episode keeps its goal). The
evaluation says which goal it scored against (``goal_position``) and when the goal started to
move (``goal_change_time``, -1 for none). A service, so that the executor knows the change is
in place before the episode can use it (a reset for one made before the start).
"""
from __future__ import annotations

import threading

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState

from psl_msgs.msg import GoalUpdate, RolloutEvaluation, TaskInstance
from psl_msgs.srv import GoalChange
from psl_optimizer.episode_grid import grid, on_grid
from psl_optimizer.reward import Reward
from psl_ros import names
from psl_ros.hot_path import HotPath
from psl_ros.matching import MatchReport
from psl_ros.node_main import run_node
from psl_ros.qos import LATCHED, RELIABLE, WHOLE_EPISODE
from psl_ros.service import create_service
from psl_ros.stamps import to_ns
from psl_task.arm_model import ArmModel
from psl_task.joint_selection import JointSelection
from psl_task.reward_geometry import RewardGeometry
from psl_task.task import TaskError, load_task
# [s] rest of the taking thread after each wake-up: the evaluator is not on the lockstep path,
# so the loop's states and references queue up in the middleware meanwhile (WHOLE_EPISODE
# keeps them all) and are taken with one wake-up instead of one each: 38 % less CPU per
# episode (docs/benchmarks.md), an evaluation at most this much later
TAKE_PAUSE = 0.005
BUFFER = 5000   # messages kept per stream while the episode announcement is on its way
KEEP_BEFORE = 100_000_000   # ns of states kept before an episode's start (interpolation)
MAX_GAP = 300_000_000       # ns: a longer gap in a robot's states spoils the episode (the
                            # controller's watchdog, psl_ros.graph.STATE_TIMEOUT, stops first)


class RewardEvaluator(Node):

    def __init__(self):
        super().__init__('reward_evaluator')
        self._rewards: dict[str, Reward] = {}       # by task id
        self._selections: dict[str, JointSelection] = {}    # by task id
        self._warned_effort = False
        self.newest: dict[int, int] = {}       # id of a stream -> its newest stamp [ns]
        self.episode: TaskInstance | None = None
        self.states: dict[int, JointState] = {}
        self.references: dict[int, JointState] = {}
        # goal changes (the service's thread and the hot path's share them)
        self.goal_lock = threading.Lock()
        self.next_goal: GoalUpdate | None = None            # for the next episode announced
        self.goal_changes: dict[int, GoalUpdate] = {}       # by episode start [ns]
        self.evaluated_ns = -1                              # start of the last episode scored
        self.matches = MatchReport(self)        # what the loop's endpoints matched
        self.pub = self.matches.create_publisher(RolloutEvaluation, names.ROLLOUT_EVALUATION,
                                                 RELIABLE)
        create_service(self, GoalChange, '~/goal_change', self.on_goal_change)
        self.hot_path = HotPath(self, pause=TAKE_PAUSE)
        for msg_type, topic, callback, qos in (
                (TaskInstance, names.TASK_INSTANCE, self.on_task, LATCHED),
                (JointState, names.JOINT_STATES, self.on_state, WHOLE_EPISODE),
                (JointState, names.REFERENCE, self.on_reference, WHOLE_EPISODE)):
            self.matches.subscribe(self.hot_path, msg_type, topic, callback, qos)
        self.hot_path.start()
        self.get_logger().info('evaluating episodes announced on task_instance')

    def on_task(self, msg: TaskInstance) -> None:
        if msg.homing:          # the executor drives the arm to the start: nothing to score
            return
        if self.episode is not None:
            self.get_logger().warning(
                f'episode at {to_ns(self.episode.stamp)} ns was not evaluated: got '
                f'{len(self.states)} states and {len(self.references)} references of '
                f'{self.episode.num_steps + 1}')
        self.episode = msg
        t0 = to_ns(msg.stamp)
        for stream in (self.states, self.references):
            for t in [t for t in stream if t < t0 - KEEP_BEFORE]:
                del stream[t]
        with self.goal_lock:
            for t in [t for t in self.goal_changes if t < t0]:
                del self.goal_changes[t]
            if self.next_goal is not None:
                self.goal_changes.setdefault(t0, self.next_goal)   # a live one comes later
                self.next_goal = None
        self._try_finish()

    def on_goal_change(self, request: GoalChange.Request, response: GoalChange.Response):
        change = request.change
        t0 = to_ns(change.stamp)
        with self.goal_lock:
            if t0 == 0:
                self.next_goal = change if len(change.goal) else None    # empty: withdrawn
            elif t0 <= self.evaluated_ns:
                response.success, response.message = False, (
                    f'the episode at {t0} ns has been evaluated already')
                return response
            elif len(change.goal):
                self.goal_changes[t0] = change
            else:
                self.goal_changes.pop(t0, None)
        response.success, response.message = True, 'goal change noted'
        return response

    def on_state(self, msg: JointState) -> None:
        self._store(self.states, msg)

    def on_reference(self, msg: JointState) -> None:
        self._store(self.references, msg)

    def _store(self, stream: dict[int, JointState], msg: JointState) -> None:
        t = to_ns(msg.header.stamp)
        stream[t] = msg
        self.newest[id(stream)] = max(t, self.newest.get(id(stream), t))
        if len(stream) > BUFFER:
            del stream[min(stream)]
        self._try_finish()

    def _try_finish(self) -> None:
        ep = self.episode
        if ep is None or not self.states or not self.references:
            return
        t0, period = to_ns(ep.stamp), int(round(ep.control_period * 1e9))
        times = [t0 + k * period for k in range(ep.num_steps + 1)]
        end = times[-1]
        on_the_grid = (min(len(self.states), len(self.references)) > ep.num_steps
                       and all(t in self.states and t in self.references for t in times))
        if not on_the_grid and not (self.newest[id(self.states)] > end
                                    and self.newest[id(self.references)] > end):
            return                  # a robot's stamps: wait for a state past the end
        with self.goal_lock:
            self.episode, self.evaluated_ns = None, t0
            change = self.goal_changes.pop(t0, None)
        try:
            if on_the_grid:
                states = [self.states.pop(t) for t in times]
                refs = [self.references.pop(t) for t in times]
                self.pub.publish(self._evaluate(ep, states, refs, change))
            else:
                self.pub.publish(self._evaluate(ep, *self._interpolated(ep, t0, period),
                                                change))
        except (TaskError, ValueError) as exc:      # EpisodeGap too
            self.get_logger().error(f'cannot evaluate episode of {ep.task!r}: {exc}')

    def _interpolated(self, ep: TaskInstance, t0: int,
                      period: int) -> tuple[list[JointState], list[JointState]]:
        """The episode's states and references on the control grid, interpolated from the
        robot's stamps (`episode_grid.on_grid`), as JointStates of the task's joints."""
        times = grid(t0, period, ep.num_steps)
        select = self._selection(ep.task)
        streams = []
        for stream in (self.states, self.references):
            stamps = np.array(sorted(stream), dtype=np.int64)
            messages = [stream[t] for t in stamps]
            fields = {}
            for field in ('position', 'velocity', 'effort'):
                rows = [select.pick(m.name, getattr(m, field)) for m in messages]
                if any(r.size == 0 for r in rows):
                    if field == 'effort' and not self._warned_effort:
                        self._warned_effort = True
                        self.get_logger().warning('the robot reports no effort: episodes are '
                                                  'scored with zero torque')
                    rows = [np.zeros(len(select.joints)) for _ in rows]
                fields[field] = on_grid(stamps, np.array(rows), times,
                                        MAX_GAP)
            streams.append([JointState(name=list(select.joints),
                                       position=fields['position'][k].tolist(),
                                       velocity=fields['velocity'][k].tolist(),
                                       effort=fields['effort'][k].tolist())
                            for k in range(len(times))])
            for t in [t for t in stream if t <= times[-1]]:
                del stream[t]
        return streams[0], streams[1]

    def _selection(self, task: str) -> JointSelection:
        if task not in self._selections:
            self._selections[task] = JointSelection(
                ArmModel(load_task(task)).joint_names)
        return self._selections[task]

    def _evaluate(self, ep: TaskInstance, states, refs,
                  change: GoalUpdate | None) -> RolloutEvaluation:
        if ep.task not in self._rewards:
            task = load_task(ep.task)
            self._rewards[ep.task] = Reward(task, RewardGeometry(ArmModel(task)))
        select = self._selection(ep.task)
        if list(states[0].name) != list(select.joints):     # the robot's order, extra joints
            states = [JointState(header=s.header, name=list(select.joints),
                                 position=select.pick(s.name, s.position).tolist(),
                                 velocity=select.pick(s.name, s.velocity).tolist(),
                                 effort=select.pick(s.name, s.effort).tolist())
                      for s in states]
        q = np.array([[s.position for s in states]])             # a population of one
        torque = np.array([[s.effort for s in states]])
        q_ref = np.array([[r.position for r in refs]])
        reward, taus = self._rewards[ep.task], np.asarray(ep.tau)[None]
        if change is not None and list(refs[-1].position) != list(change.last_reference):
            self.get_logger().warning(
                f'the goal change of episode {to_ns(ep.stamp)} ns at {change.time_from_start:g} '
                's did not reach the controller in time: scored against the old goal')
            change = None
        goal_position, goal_rotation = ((reward.goals(taus)[0][0], None) if change is None
                                        else reward.goal_of(change.goal))   # (3,), (3, 3)
        result = reward.evaluate_replayed(
            q, torque, q_ref, taus, goal_position[None],
            None if goal_rotation is None else goal_rotation[None])[0]

        def rows(messages, field):
            return [x for m in messages for x in getattr(m, field)]
        return RolloutEvaluation(
            stamp=ep.stamp, task=ep.task, tau=list(ep.tau), reward=result.reward,
            fulfilled=result.fulfilled, component_names=list(result.components),
            component_values=list(result.components.values()),
            tracking_error=result.components['tracking_error'], num_steps=ep.num_steps,
            goal_position=goal_position.tolist(),
            goal_change_time=-1.0 if change is None else change.time_from_start,
            control_period=ep.control_period, joint_names=list(states[0].name),
            position=rows(states, 'position'), velocity=rows(states, 'velocity'),
            effort=rows(states, 'effort'), reference_position=rows(refs, 'position'),
            reference_velocity=rows(refs, 'velocity'), reference_effort=rows(refs, 'effort'))


    def destroy_node(self):
        self.hot_path.stop()
        super().destroy_node()


def main(args=None):
    run_node(RewardEvaluator, args)


if __name__ == '__main__':
    main()
