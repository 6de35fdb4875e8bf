"""The reward evaluator node: scores the episodes the executor runs.

It keeps the robot's ``joint_states`` (by stamp, so arrival order does not matter) from the
start of the newest episode announced on ``task_instance`` (a little before it, for the
interpolation of a robot's stamps). When the executor's episode is over it asks
``~/evaluate`` (psl_msgs/EvaluateEpisode: the episode, the trajectory the controller was given,
a goal change, whether the controller aborted it): the evaluator waits until it has a state at
or past the episode's end, scores the rollout with the task's reward (`psl_optimizer.reward.
Reward`, the geometry from a kinematic replay of the measured joint angles, the reference the
trajectory's own points), answers with the psl_msgs/RolloutEvaluation and publishes it on
``rollout_evaluation`` (for a bag or a viewer), stamped with the episode's first state and
carrying the measured episode (joint angles, velocities, applied torques and the reference of
each state) for learners that need it (ILC in graph mode).

A robot psl does not simulate stamps its states with its own clock (jitter, a state late or
missing): when the states are not on the control grid, both the states and the reference are
taken on the grid, the states interpolated from the robot's stamps
(`psl_optimizer.episode_grid`; a gap of more than `MAX_GAP` spoils the episode, said in the
answer). States are read by joint name (`psl_task.joint_selection`: the robot's order, extra
joints ignored); a robot that reports no effort is scored with zero torque (a warning says so).

The bodies of the world a task observes (``reward.observe``: a ball) are measured apart from
the arm: their poses come on ``world/<body>/pose`` (geometry_msgs/PoseStamped; psl's simulator
publishes them, a robot's motion capture or detector can, remapped), subscribed at the task's
first announced episode and kept by stamp like the joint states (a reader that joins late gets
the episode's poses from the publisher's history: `psl_ros.qos.WORLD_POSES`); at the
evaluation they are taken on the control grid the same way (the poses themselves on the grid,
else interpolated and the orientation normalised) and the reward's components read them
(`RolloutData.world`).

A goal change the executor made: the episode is scored against the new goal's position (and,
for a pose, orientation: `Reward.goal_of`). An episode the controller aborted (its tracking
error beyond the path tolerance) is scored as the task's penalty minus the excess error,
replayed on the measured episode (`psl_task.safety_check.tracking_abort`), as batch mode does.
"""
from __future__ import annotations

import threading
import time

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import JointState

from psl_controller.trajectory_sampling import SampledTrajectory
from psl_msgs.msg import RolloutEvaluation, TaskInstance
from psl_msgs.srv import EvaluateEpisode
from psl_optimizer.episode_grid import grid, on_grid
from psl_optimizer.reward import Reward
from psl_ros import names
from psl_ros.hot_path import HotPath
from psl_ros.matching import MatchReport
from psl_ros.node_main import run_node
from psl_ros.qos import LATCHED, WHOLE_EPISODE, WORLD_POSES
from psl_ros.service import create_service
from psl_ros.stamps import to_ns
from psl_task.arm_model import ArmModel
from psl_task.joint_selection import JointSelection
from psl_task.reward_geometry import RewardGeometry
from psl_task.safety_check import tracking_abort
from psl_task.task import TaskError, load_task
# [s] rest of the taking thread after each wake-up: the evaluator is not on the lockstep path,
# so the loop's states queue up in the middleware meanwhile (WHOLE_EPISODE keeps them all) and
# are taken with one wake-up instead of one each: 38 % less CPU per episode
# (docs/benchmarks.md), an evaluation at most this much later
TAKE_PAUSE = 0.005
BUFFER = 400_000    # states kept at most (an episode of 600 s at 500 Hz is 300,000)
KEEP_BEFORE = 100_000_000   # ns of states kept before an episode's start (interpolation)
MAX_GAP = 300_000_000       # ns: a longer gap in a robot's states spoils the episode
PATIENCE = 10.0     # s the evaluator waits for the states of an episode's end beyond its length


class RewardEvaluator(Node):

    def __init__(self):
        super().__init__('reward_evaluator')
        self._rewards: dict[str, Reward] = {}       # by task id
        self._selections: dict[str, JointSelection] = {}    # by task id
        self._warned_effort = False
        self._cv = threading.Condition()            # guards the states
        self.states: dict[int, JointState] = {}     # by stamp [ns]
        self.newest = -1                            # the newest state's stamp [ns]
        # observed bodies: name -> {stamp [ns]: pose (7,)}, each body's newest stamp
        self.poses: dict[str, dict[int, np.ndarray]] = {}
        self.newest_pose: dict[str, int] = {}
        self._pose_group = ReentrantCallbackGroup()   # not behind an evaluation's wait
        self.matches = MatchReport(self)        # what the loop's endpoints matched
        self.pub = self.matches.create_publisher(RolloutEvaluation, names.ROLLOUT_EVALUATION,
                                                 WHOLE_EPISODE)
        create_service(self, EvaluateEpisode, '~/evaluate', self.on_evaluate)
        self.hot_path = HotPath(self, pause=TAKE_PAUSE)
        self.matches.subscribe(self.hot_path, TaskInstance, names.TASK_INSTANCE, self.on_task,
                               LATCHED)
        self.matches.subscribe(self.hot_path, JointState, names.JOINT_STATES, self.on_state,
                               WHOLE_EPISODE)
        self.hot_path.start()
        self.get_logger().info('evaluating the episodes the executor asks for')

    def on_task(self, msg: TaskInstance) -> None:
        """An episode begins: the states from a little before its start on are kept; the
        bodies its task observes are listened to from now on."""
        try:
            self._observe(load_task(msg.task).reward.observe)
        except (TaskError, ValueError) as exc:      # said again when it is to be evaluated
            self.get_logger().warning(f'task {msg.task!r}: {exc}', throttle_duration_sec=5.0)
        if msg.homing:          # the executor drives the arm to the start: nothing to score
            return
        self._forget_before(to_ns(msg.stamp) - KEEP_BEFORE)

    def _observe(self, bodies) -> None:
        for body in bodies:
            if body not in self.poses:
                self.poses[body], self.newest_pose[body] = {}, -1
                self.create_subscription(
                    PoseStamped, names.world_pose(body),
                    lambda msg, body=body: self.on_pose(body, msg), WORLD_POSES,
                    callback_group=self._pose_group)

    def on_pose(self, body: str, msg: PoseStamped) -> None:
        t = to_ns(msg.header.stamp)
        p, o = msg.pose.position, msg.pose.orientation
        with self._cv:
            poses = self.poses[body]
            poses[t] = np.array([p.x, p.y, p.z, o.w, o.x, o.y, o.z])
            self.newest_pose[body] = max(self.newest_pose[body], t)
            if len(poses) > BUFFER:
                del poses[min(poses)]
            self._cv.notify_all()

    def _forget_before(self, t_ns: int) -> None:
        with self._cv:
            for t in [t for t in self.states if t < t_ns]:
                del self.states[t]
            for poses in self.poses.values():
                for t in [t for t in poses if t < t_ns]:
                    del poses[t]

    def on_state(self, msg: JointState) -> None:
        t = to_ns(msg.header.stamp)
        with self._cv:
            self.states[t] = msg
            self.newest = max(self.newest, t)
            if len(self.states) > BUFFER:
                del self.states[min(self.states)]
            self._cv.notify_all()

    def on_evaluate(self, request: EvaluateEpisode.Request, response: EvaluateEpisode.Response):
        ep = request.episode
        try:
            response.evaluation = self._evaluate(request)
        except (TaskError, ValueError, TimeoutError) as exc:    # EpisodeGap too
            response.success, response.message = False, (
                f'cannot evaluate the episode of {ep.task!r} at {to_ns(ep.stamp)} ns: {exc}')
            self.get_logger().error(response.message)
            return response
        self.pub.publish(response.evaluation)
        response.success, response.message = True, 'evaluated'
        return response

    def _episode_states(self, ep: TaskInstance) -> list[JointState]:
        """The episode's states on the control grid (the states themselves when the robot
        stamps on it, else interpolated); TimeoutError when the end does not come."""
        t0, period = to_ns(ep.stamp), int(round(ep.control_period * 1e9))
        times = grid(t0, period, ep.num_steps)
        end = int(times[-1])
        deadline = time.monotonic() + ep.num_steps * ep.control_period + PATIENCE
        with self._cv:
            while self.newest < end:
                if not self._cv.wait(timeout=max(0.0, deadline - time.monotonic())):
                    inside = sum(1 for t in self.states if t0 <= t <= end)
                    raise TimeoutError(f'no joint state of its end came: {inside} of '
                                       f'{ep.num_steps + 1} states within the episode')
            if all(int(t) in self.states for t in times):
                states = [self.states[int(t)] for t in times]
            else:
                states = self._interpolated(ep, times)
            for t in [t for t in self.states if t < end]:
                del self.states[t]          # the state at the end may start the next episode
        return states

    def _episode_world(self, ep: TaskInstance, bodies) -> dict[str, np.ndarray]:
        """The observed bodies' poses on the episode's control grid, {body: (1, T, 7)}
        (the poses themselves when published on it, else interpolated: `on_grid`, the
        quaternion normalised); TimeoutError when a body's poses of the end do not come."""
        self._observe(bodies)
        t0, period = to_ns(ep.stamp), int(round(ep.control_period * 1e9))
        times = grid(t0, period, ep.num_steps)
        end = int(times[-1])
        deadline = time.monotonic() + PATIENCE
        world = {}
        with self._cv:
            for body in bodies:
                while self.newest_pose[body] < end:
                    if not self._cv.wait(timeout=max(0.0, deadline - time.monotonic())):
                        raise TimeoutError(f'no pose of {body!r} of the episode\'s end came on '
                                           f'{self.resolve_topic_name(names.world_pose(body))}')
                poses = self.poses[body]
                if all(int(t) in poses for t in times):
                    rows = np.array([poses[int(t)] for t in times])
                else:
                    stamps = np.array(sorted(poses), dtype=np.int64)
                    rows = on_grid(stamps, np.array([poses[t] for t in stamps]), times, MAX_GAP)
                    rows[:, 3:] /= np.linalg.norm(rows[:, 3:], axis=1, keepdims=True)
                world[body] = rows[None]
                for t in [t for t in poses if t < end]:
                    del poses[t]
        return world

    def _interpolated(self, ep: TaskInstance, times: np.ndarray) -> list[JointState]:
        """The episode's states on the control grid, interpolated from the robot's stamps
        (`episode_grid.on_grid`), as JointStates of the task's joints (under _cv)."""
        select = self._selection(ep.task)
        stamps = np.array(sorted(self.states), dtype=np.int64)
        messages = [self.states[t] for t in stamps]
        fields = {}
        for field in ('position', 'velocity', 'effort'):
            rows = [select.pick(m.name, getattr(m, field)) for m in messages]
            if any(r.size == 0 for r in rows):
                if field == 'effort' and not self._warned_effort:
                    self._warned_effort = True
                    self.get_logger().warning('the robot reports no effort: episodes are '
                                              'scored with zero torque')
                rows = [np.zeros(len(select.joints)) for _ in rows]
            fields[field] = on_grid(stamps, np.array(rows), times, MAX_GAP)
        return [JointState(name=list(select.joints), position=fields['position'][k].tolist(),
                           velocity=fields['velocity'][k].tolist(),
                           effort=fields['effort'][k].tolist()) for k in range(len(times))]

    def _selection(self, task: str) -> JointSelection:
        if task not in self._selections:
            self._selections[task] = JointSelection(ArmModel(load_task(task)).joint_names)
        return self._selections[task]

    def _evaluate(self, request: EvaluateEpisode.Request) -> RolloutEvaluation:
        ep = request.episode
        if ep.task not in self._rewards:
            task = load_task(ep.task)
            self._rewards[ep.task] = Reward(task, RewardGeometry(ArmModel(task)))
        reward = self._rewards[ep.task]
        select = self._selection(ep.task)
        reference = reference_on_grid(request.trajectory, select.joints, ep)
        states = self._episode_states(ep)
        if list(states[0].name) != list(select.joints):     # the robot's order, extra joints
            states = [JointState(header=s.header, name=list(select.joints),
                                 position=select.pick(s.name, s.position).tolist(),
                                 velocity=select.pick(s.name, s.velocity).tolist(),
                                 effort=select.pick(s.name, s.effort).tolist())
                      for s in states]
        q = np.array([[s.position for s in states]])             # a population of one
        qd = np.array([s.velocity for s in states])
        torque = np.array([[s.effort if len(s.effort) else np.zeros(len(select.joints))
                            for s in states]])
        q_ref, qd_ref, u_ffwd = reference
        taus = np.asarray(ep.tau)[None]
        changed = request.goal_change_time >= 0.0 and len(request.goal_change) > 0
        goal_position, goal_rotation = (reward.goal_of(np.asarray(request.goal_change))
                                        if changed else (reward.goals(taus)[0][0], None))
        observed = reward.task.reward.observe
        world = self._episode_world(ep, observed) if observed else None
        result = reward.evaluate_replayed(
            q, torque, q_ref[None], taus, goal_position[None],
            None if goal_rotation is None else goal_rotation[None], world=world)[0]
        names_, values = list(result.components), list(result.components.values())
        score, fulfilled = result.reward, result.fulfilled
        if request.path_tolerance > 0.0:    # the controller aborted it: the penalty
            verdict = tracking_abort(q[0], q_ref, request.path_tolerance, select.joints,
                                     ep.control_period)
            task = reward.task
            score, fulfilled = verdict.penalty(task.safety.penalty), False
            names_, values = ['tracking_abort'], [verdict.violation]
        return RolloutEvaluation(
            stamp=ep.stamp, task=ep.task, tau=list(ep.tau), reward=score,
            fulfilled=fulfilled, component_names=names_, component_values=values,
            tracking_error=result.components.get('tracking_error', float('nan')),
            failure=result.failure, num_steps=ep.num_steps,
            goal_position=np.asarray(goal_position).tolist(),
            goal_change_time=request.goal_change_time if changed else -1.0,
            control_period=ep.control_period, joint_names=list(select.joints),
            position=q[0].ravel().tolist(), velocity=qd.ravel().tolist(),
            effort=torque[0].ravel().tolist(), reference_position=q_ref.ravel().tolist(),
            reference_velocity=qd_ref.ravel().tolist(),
            reference_effort=u_ffwd.ravel().tolist(),
            observed_bodies=list(world or {}),
            observed_poses=(np.concatenate([w[0].ravel() for w in world.values()]).tolist()
                            if world else []))

    def destroy_node(self):
        self.hot_path.stop()
        super().destroy_node()


def reference_on_grid(trajectory, joints: list[str], ep: TaskInstance) -> tuple[np.ndarray, ...]:
    """The reference (q, qd, u_ffwd), each (num_steps + 1, n) in `joints` order, of a
    JointTrajectory sampled at the episode's control grid (`SampledTrajectory`: a point per
    control period gives the points themselves); ValueError for a trajectory that does not
    fit."""
    names_ = list(trajectory.joint_names)
    if sorted(names_) != sorted(joints) or not trajectory.points:
        raise ValueError(f'the trajectory of joints {names_} does not fit the task\'s {joints}')
    order = [names_.index(j) for j in joints]
    points = trajectory.points

    def column(field):
        rows = [getattr(p, field) for p in points]
        if any(len(r) != len(names_) for r in rows):
            return None
        return np.asarray(rows, dtype=float)[:, order]
    times = np.array([to_ns(p.time_from_start) for p in points], dtype=np.int64)
    sampled = SampledTrajectory(times, column('positions'), column('velocities'),
                                column('effort'))
    period = int(round(ep.control_period * 1e9))
    samples = [sampled.sample(k * period) for k in range(ep.num_steps + 1)]
    return tuple(np.array([getattr(s, f) for s in samples])
                 for f in ('positions', 'velocities', 'effort'))


def main(args=None):
    run_node(RewardEvaluator, args, threads=2)   # an evaluation waits for the episode's states


if __name__ == '__main__':
    main()
