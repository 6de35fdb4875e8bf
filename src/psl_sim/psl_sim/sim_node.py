"""The simulator node: a task's MuJoCo model behind standard robot topics.

A robot with extras (DESIGN.md 3b): it publishes ``joint_states`` (sensor_msgs/JointState,
effort = torque applied in the step that led to the state), ``ee_pose``
(geometry_msgs/PoseStamped), ``/clock`` and ``scene`` (visualization_msgs/MarkerArray, latched:
see below), and applies ``effort_command`` (std_msgs/Float64MultiArray, the
forward_command_controller convention) clipped to the model's torque limits; its controller is
psl's ``pd_controller``. The extras are ``~/reset`` (psl_msgs/ResetTask): teleport the arm to the
start posture (or leave it where it is: ``drive``), place the task instance, and run an episode
of a given length (``probe``: say the state, run nothing); between episodes the simulation is
paused. A reset may name another task of the same robot (the same actuated joints); one of
another robot is refused, since the controller and every other node of the graph are set up
for the joints of the robot the simulator started with. The simulator announces nothing: the
executor owns the episode and announces it (``task_instance``).

``scene``: the model's visible geoms at their current poses (`psl_sim.scene`: the arm, the
obstacles, the static geoms; a capsule is a cylinder and two spheres) and the end-effector path
executed so far in the episode (LINE_STRIP, sampled at the scene rate), in the frame ``world``,
one marker per (namespace, id) that stays the same, so viewers update markers in place.
Published when the simulator starts (the arm in the posture it starts in, the model's
default, where a probe finds it, and the world before any instance is placed), at every reset
and at the end of every episode, and in between every ``1 / scene_rate`` seconds of simulated
time while someone subscribes, so that the lockstep loop pays for it only when watched.
Latched: a viewer that joins before the first episode or between episodes gets the scene as
it is. When a reset switches to a model with other geoms the array starts with DELETEALL.

Modes:
- ``lockstep``: after publishing a state the simulation waits for the command that answers it,
  then advances one control period. Deterministic; as fast as the loop allows.
- ``realtime``: the simulation advances on the wall clock; each period it applies the latest
  command. A period whose answer has not arrived in time is a deadline miss; misses are
  counted and published on ``/diagnostics`` at the end of each episode.
"""
from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import Marker, MarkerArray

from psl_msgs.srv import ResetTask
from psl_task.arm_model import ArmModel
from psl_sim.sim_parameters import SimParameters
from psl_sim.scene import PATH_SHAPE, Scene, Shape, ShapeKind
from psl_ros import names
from psl_ros.realtime import raise_priority, sleep_until
from psl_ros.hot_path import HotPath
from psl_ros.matching import MatchReport
from psl_ros.node_main import run_node
from psl_ros.parameters import check_update, declare
from psl_ros.qos import LATCHED, RELIABLE, WORLD_POSES
from psl_ros.service import create_service
from psl_ros.stamps import NS_PER_S, time_msg
from psl_ros.step_timing import StepTiming
from psl_task.schema import RESETS
from psl_task.task import TaskError, load_task

RESET_MODES = (*RESETS, 'probe')     # ResetTask.mode: an episode's resets, and a probe
CONTROLLER = 'pd_controller'     # the node whose effort_command an episode takes
UNKNOWN_NODE = '_UNKNOWN_'       # rmw's node name of an endpoint whose node is not known yet
NAME_PATIENCE = 2.0              # s to wait for it
# phases of a lockstep step: the wait from sending a state to its answer's callback (the
# controller and both transports; of it, the command's way from the controller's publish to
# the callback, as far as it lies within the wait), the physics, building and sending the
# state, then the rest (clock, pose, scene, status: done while the controller works)
STEP_PHASES = ('wait', 'command_transport', 'physics', 'state', 'extras')

MARKER_TYPES = {ShapeKind.SPHERE: Marker.SPHERE, ShapeKind.CYLINDER: Marker.CYLINDER,
                ShapeKind.CUBE: Marker.CUBE, ShapeKind.TRIANGLE_LIST: Marker.TRIANGLE_LIST,
                ShapeKind.LINE_STRIP: Marker.LINE_STRIP}


def shape_marker(shape: Shape) -> Marker:
    """A Marker (frame ``world``, no lifetime) of a shape: everything but pose and stamp."""
    marker = Marker(ns=shape.namespace, id=shape.marker_id, type=MARKER_TYPES[shape.kind],
                    action=Marker.ADD)
    marker.header.frame_id = names.WORLD_FRAME
    marker.pose.orientation.w = 1.0
    marker.scale.x, marker.scale.y, marker.scale.z = shape.scale.tolist()
    marker.color.r, marker.color.g, marker.color.b, marker.color.a = shape.rgba.tolist()
    if shape.points is not None:
        marker.points = [Point(x=x, y=y, z=z) for x, y, z in shape.points.tolist()]
    return marker


class SceneMarkers:
    """The scene of one model as Marker messages, built once; `update` sets poses and stamps
    in place (only the poses change from one publish to the next)."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self.markers = [shape_marker(shape) for shape in scene.shapes]
        self.path = shape_marker(PATH_SHAPE)

    def update(self, data, stamp, path: list[np.ndarray]) -> list[Marker]:
        """The markers at data's poses (after a kinematics pass) and the path so far."""
        poses = self.scene.poses(data)
        for marker, position, (w, x, y, z) in zip(self.markers, poses.position.tolist(),
                                                  poses.orientation.tolist()):
            marker.header.stamp = stamp
            p, q = marker.pose.position, marker.pose.orientation
            p.x, p.y, p.z = position
            q.w, q.x, q.y, q.z = w, x, y, z
        self.path.header.stamp = stamp
        self.path.points = [Point(x=x, y=y, z=z) for x, y, z in path]
        return self.markers + [self.path]


class SimNode(Node):

    def __init__(self):
        super().__init__('sim')
        # every update (and declaration) checked by SimParameters (one place)
        self.add_on_set_parameters_callback(lambda params: check_update(self, SimParameters,
                                                                        params))
        self.parameters = declare(self, SimParameters)
        self.mode = self.parameters.mode
        self._lock = threading.Lock()
        self._arms: dict[Path, ArmModel] = {}      # by task YAML
        self.arm = self._arm(self.parameters.task)
        # simulation time, monotonic over episodes; it starts one control period in, since a
        # stamp of zero means "the next episode / the next state" to the controller and the
        # evaluator (the first episode's replacement trajectories and goal changes need its
        # start to be a real time)
        self.t_ns = self.arm.task.control_period_ns
        self.steps_left = 0           # control periods left in the episode; 0 = paused
        self.applied = np.zeros(len(self.arm.joint_names))
        self.pending: np.ndarray | None = None   # command answering the last state
        self.episode = {}
        self._scenes: dict[Path, SceneMarkers] = {}     # by task YAML, like the arms
        self._scene_shown: SceneMarkers | None = None   # what the last scene message drew
        self._scene_due_ns = 0                          # next throttled scene publish
        self._ee_path: list[np.ndarray] = []            # end effector at the scene ticks

        self.matches = MatchReport(self)        # what the endpoints below matched
        self.pub_joints = self.matches.create_publisher(JointState, names.JOINT_STATES, RELIABLE)
        self._joint_state = JointState()
        self.pub_pose = self.matches.create_publisher(PoseStamped, names.EE_POSE, RELIABLE)
        self.pub_clock = self.matches.create_publisher(Clock, names.CLOCK, RELIABLE)
        self.pub_diag = self.matches.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 10)
        self.pub_scene = self.matches.create_publisher(MarkerArray, names.SCENE, LATCHED)
        # the bodies the current task observes: name -> (body id, publisher), made once
        self._world_publishers: dict[str, object] = {}
        self._rng = np.random.default_rng()     # the motion capture's noise (world_pose_noise)
        for body in self.arm.task.reward.observe:      # there from the start (psl record)
            self._world_publisher(body)
        self._scene_tick(always=True)       # the scene as it starts, latched (see above)
        self.hot_path = HotPath(self)
        # a command answers the state published last (lockstep) or one of this episode's
        # (realtime): one the controller published before that state answers an older one
        # (e.g. the last state of the episode before, delivered late under load) and is
        # dropped, by the publisher's source timestamp (the same wall clock on this machine)
        self._state_wall_ns = self._episode_wall_ns = 0
        self.stale_commands = 0
        self.foreign_refusals = 0   # resets refused: someone besides the controller commanded
        # where each lockstep step's time goes, reported with the episode's end (StepTiming)
        self.timing = StepTiming(STEP_PHASES)
        self._published_ns = 0      # perf_counter_ns when the last state was sent
        self.episodes = 0           # episodes started since the node started (resets)
        self.matches.subscribe(self.hot_path, Float64MultiArray, names.EFFORT_COMMAND,
                               self.on_command, RELIABLE, info=True)
        self.hot_path.start()
        create_service(self, ResetTask, '~/reset', self.on_reset)
        if self.mode == 'realtime':
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._realtime_loop, daemon=True)
            self._thread.start()
        self.get_logger().info(
            f'{self.mode} simulation of task {self.arm.task.name!r} '
            f'({len(self.arm.joint_names)} joints, {self.arm.task.control_rate:g} Hz'
            + (f'; passive: {", ".join(self.arm.passive_joints)}'
               if self.arm.passive_joints else '')
            + f'); waiting for {self.resolve_service_name("~/reset")}')

    def _arm(self, task_name: str) -> ArmModel:
        task = load_task(task_name)
        if task.path not in self._arms:
            arm = ArmModel(task)
            robot = getattr(self, 'arm', arm)       # the robot of the task loaded at start
            if arm.joint_names != robot.joint_names:
                raise TaskError(
                    f'task {task.name!r} drives the joints {arm.joint_names}; this simulator '
                    f'runs the robot of task {robot.task.name!r} with the joints '
                    f'{robot.joint_names}: start a graph for it (psl up --task ...)')
            self._arms[task.path] = arm
        return self._arms[task.path]

    # -- services -----------------------------------------------------------------------
    def episode_steps(self, requested: float, arm: ArmModel, tau: np.ndarray) -> int:
        """Control periods of an episode of `requested` seconds (0: the episode_duration
        parameter, whose 0 means the task's duration plus its settle time). Raises TaskError
        for a duration that is not finite, negative, shorter than one period or longer than
        max_episode_duration."""
        longest = self.get_parameter('max_episode_duration').value
        if not (math.isfinite(requested) and requested >= 0.0):
            raise TaskError(f'duration must be a finite number of seconds >= 0 (0: the '
                            f"task's), got {requested}")
        duration = requested or self.get_parameter('episode_duration').value
        if duration > longest:
            raise TaskError(f'an episode of {duration:g} s is longer than max_episode_duration '
                            f'({longest:g} s)')
        if duration == 0.0:
            return arm.task.num_steps_of(tau)
        steps = int(round(duration * arm.task.control_rate))
        if steps < 1:
            raise TaskError(f'an episode of {duration:g} s is shorter than one control period '
                            f'({arm.task.control_period:g} s)')
        return steps

    def foreign_commanders(self, patience: float = NAME_PATIENCE) -> list[str]:
        """The nodes besides this namespace's pd_controller that publish on effort_command.
        ROS 2 has no access control on topics (DDS Security, SROS2, would add it): anyone may
        publish torques, and a message does not say who sent it, so the simulator refuses to
        start an episode while anyone else publishes them."""
        topic = self.resolve_topic_name(names.EFFORT_COMMAND)
        mine = self.get_namespace().rstrip('/') + '/' + CONTROLLER
        # DDS announces an endpoint before ROS says whose node it is: wait up to `patience` s
        deadline = time.monotonic() + patience
        while True:
            found = {(i.node_namespace.rstrip('/') + '/' + i.node_name)
                     for i in self.get_publishers_info_by_topic(topic)}
            if not any(UNKNOWN_NODE in name for name in found) or time.monotonic() > deadline:
                return sorted(found - {mine})
            time.sleep(0.01)

    def on_reset(self, request: ResetTask.Request, response: ResetTask.Response):
        mode = request.mode or 'teleport'
        with self._lock:
            try:
                foreign = self.foreign_commanders()
                if foreign and mode != 'probe':
                    self.foreign_refusals += 1
                    raise TaskError(f'{", ".join(foreign)} publish(es) on '
                                    f'{self.resolve_topic_name(names.EFFORT_COMMAND)} besides '
                                    'the controller: no episode starts while anyone else '
                                    'may command the torques')
                if mode not in RESET_MODES:
                    raise TaskError(f'reset mode must be one of {", ".join(RESET_MODES)}, got '
                                    f'{mode!r}')
                if mode != 'teleport' and self.steps_left > 0:
                    raise TaskError('an episode is running: drive and probe start from the '
                                    'state between episodes')
                arm = self._arm(request.task)
                # before anything changes: the episode's length
                num_steps = self.episode_steps(request.duration, arm,
                                               arm.task.validate_tau(request.tau))
                if mode == 'teleport':          # refuses a bad tau before changing anything
                    tau = arm.reset(request.tau)
                else:                           # the arm stays where it is
                    tau = arm.task.validate_tau(request.tau)
                    if arm is not self.arm:
                        arm.take_state(self.arm)
                    if mode == 'drive':
                        arm.place(tau)
            except TaskError as exc:
                response.success, response.message = False, str(exc)
                self.get_logger().warning(f'reset refused: {exc}')
                return response
            response.joint_names = list(arm.joint_names)
            response.position, response.velocity = arm.q.tolist(), arm.qd.tolist()
            if mode == 'probe':
                response.success, response.message = True, 'the current state'
                response.stamp, response.num_steps = time_msg(self.t_ns), 0
                return response
            self.arm = arm
            self.episodes += 1
            self.applied = np.zeros(len(arm.joint_names))
            self.pending = None
            self.steps_left = num_steps
            self.episode = {'t0': self.t_ns, 'misses': 0, 'start': time.perf_counter(),
                            'steps': num_steps}
            self.timing.clear()
            self._publish_state()
            self._episode_wall_ns = self._state_wall_ns
            self._ee_path = []
            self._scene_tick(always=True)
            self._publish_status(0)        # the episode's start (and, realtime, its rate)
            # its start, read under the lock: once it is released the controller's answer to
            # the start state may step the episode before this response is sent
            began = self.t_ns
        response.success, response.message = True, f'episode of {num_steps} steps started'
        response.stamp, response.num_steps = time_msg(began), num_steps
        return response

    # -- commands -----------------------------------------------------------------------
    def on_command(self, msg: Float64MultiArray, info: dict | None = None) -> None:
        # both clocks read at once: the transport (wall clock, from the controller's source
        # timestamp) is a part of the wait (monotonic, from the state's publication); read
        # after the lock, a busy machine made the transport longer than the wait
        arrived, arrived_wall = time.perf_counter_ns(), time.time_ns()
        command = np.asarray(msg.data, dtype=float)
        n = len(self.arm.joint_names)
        if command.shape != (n,) or not np.isfinite(command).all():
            self.get_logger().warning(
                f'refused effort_command: expected {n} finite torques, got '
                f'{len(command)} value(s){"" if np.all(np.isfinite(command)) else " with NaN/inf"}',
                throttle_duration_sec=1.0)
            return
        with self._lock:
            if self.steps_left == 0:
                return                 # paused between episodes
            published = (info or {}).get('source_timestamp', 0)
            since = self._state_wall_ns if self.mode == 'lockstep' else self._episode_wall_ns
            if published and published < since:
                self.stale_commands += 1            # an answer to an earlier state
                return
            if self.mode == 'lockstep':
                wait = arrived - self._published_ns
                self.timing.add('wait', wait)
                if published:
                    # the part of the wait the command spent on its way: the controller may
                    # answer before this node's publish call has returned (the state reached
                    # it first), and that overlap is the state's sending, not the wait
                    self.timing.add('command_transport', min(arrived_wall - published, wait))
                self._advance(command)
            else:
                self.pending = command

    def _advance(self, command: np.ndarray) -> None:
        """One control period with the given torques, then publish the new state."""
        start = time.perf_counter_ns()
        self.applied = self.arm.step(command)
        self.timing.add('physics', time.perf_counter_ns() - start)
        self.t_ns += self.arm.task.control_period_ns
        self.steps_left -= 1
        self._publish_state()
        if self.steps_left == 0 or self.t_ns >= self._scene_due_ns:
            self._scene_tick(always=self.steps_left == 0)
        done = self.episode['steps'] - self.steps_left
        self.timing.add('extras', time.perf_counter_ns() - self._published_ns)
        if self.steps_left == 0 or done % max(1, self.episode['steps'] // 10) == 0:
            self._publish_status(done)

    def _realtime_loop(self) -> None:
        scheduling = raise_priority(self.parameters.realtime_priority)
        self.get_logger().info(f'realtime loop: {scheduling}')
        margin = self.parameters.spin_margin
        next_tick = time.perf_counter()
        while not self._stop.is_set():
            with self._lock:
                period = self.arm.task.control_period
                if self.steps_left > 0:
                    if self.pending is None:
                        self.episode['misses'] += 1
                        command = self.applied
                    else:
                        command = self.pending
                    self.pending = None
                    self._advance(command)
            next_tick += period
            if next_tick - time.perf_counter() < -period:   # fell behind by more than a
                next_tick = time.perf_counter()             # period: don't burst
            else:
                sleep_until(next_tick, margin)

    def _publish_status(self, done: int) -> None:
        """Episode progress on /diagnostics: about every tenth of the episode and at its end
        (steps done, deadline misses, wall time, steps per second)."""
        ep = self.episode
        wall = time.perf_counter() - ep['start']
        # at the start: the rate the realtime loop keeps (lockstep's is not known yet)
        rate = (done / wall if done else
                self.arm.task.control_rate if self.mode == 'realtime' else 0.0)
        status = DiagnosticStatus(
            level=DiagnosticStatus.OK, name=f'{self.get_fully_qualified_name()}: episode',
            message=f'{done}/{ep["steps"]} steps, {ep["misses"]} deadline misses',
            hardware_id=str(ep['t0']),
            values=[KeyValue(key=k, value=str(v)) for k, v in (
                ('mode', self.mode), ('task', self.arm.task.name), ('episode_start_ns', ep['t0']),
                ('steps_done', done), ('steps', ep['steps']), ('episodes', self.episodes),
                ('deadline_misses', ep['misses']), ('stale_commands', self.stale_commands),
                ('foreign_refusals', self.foreign_refusals),
                ('foreign_commanders', ' '.join(self.foreign_commanders(patience=0.0))),
                ('wall_time_s', f'{wall:.6f}'),
                ('steps_per_second', f'{rate:.1f}'))]
            + ([KeyValue(key=f'step_{phase}_us', value=f'{us:.1f}')
                for phase, us in self.timing.medians_us().items()] if done == ep['steps'] else []))
        diag = DiagnosticArray(status=[status])
        diag.header.stamp = time_msg(self.t_ns)
        self.pub_diag.publish(diag)

    # -- state --------------------------------------------------------------------------
    def _publish_state(self) -> None:
        start = time.perf_counter_ns()
        t = time_msg(self.t_ns)
        arm = self.arm
        js = self._joint_state              # one message, refilled (publish copies it)
        js.header.stamp = t
        js.name = arm.joint_names
        js.position = arm.q.tolist()
        js.velocity = arm.qd.tolist()
        js.effort = self.applied.tolist()
        # the state first: the controller answers it while the clock and the pose (a bag
        # records them) are built and sent
        self._state_wall_ns = time.time_ns()
        self.pub_joints.publish(js)
        self._published_ns = time.perf_counter_ns()
        if self.steps_left < self.episode.get('steps', 0):     # not the episode's first state
            self.timing.add('state', self._published_ns - start)
        # building and serialising a message costs more than asking whether anyone listens
        if self.pub_clock.get_subscription_count():
            self.pub_clock.publish(Clock(clock=t))
        if self.pub_pose.get_subscription_count():
            pos, quat = arm.end_effector_pose()
            self.pub_pose.publish(pose_stamped(t, np.concatenate([pos, quat])))
        # the observed bodies, as a motion capture sees them (every state: the evaluator
        # scores with them, and keeps what it missed while joining: WORLD_POSES)
        noise = self.get_parameter('world_pose_noise').value
        for body in arm.task.reward.observe:
            pose = arm.body_pose(arm.body(body))
            if noise > 0.0:
                pose[:3] += self._rng.normal(0.0, noise, 3)
            self._world_publisher(body).publish(pose_stamped(t, pose))

    def _world_publisher(self, body: str):
        if body not in self._world_publishers:
            self._world_publishers[body] = self.create_publisher(
                PoseStamped, names.world_pose(body), WORLD_POSES)
        return self._world_publishers[body]

    def _scene_tick(self, always: bool) -> None:
        """A scene sample: note the end effector on the path, schedule the next sample, and
        publish the scene if `always` (reset, episode end) or someone subscribes."""
        rate = self.get_parameter('scene_rate').value
        self._scene_due_ns = (self.t_ns + int(round(NS_PER_S / rate)) if rate > 0
                              else np.iinfo(np.int64).max)
        path = self.arm.task.path
        if path not in self._scenes:
            self._scenes[path] = SceneMarkers(Scene(self.arm.model))
        scene = self._scenes[path]
        state = scene.scene.forward(self.arm.data)     # poses of this state, not the last
        self._ee_path.append(state.site_xpos[self.arm.ee_site].copy())
        if not (always or self.pub_scene.get_subscription_count()):
            return
        markers = scene.update(state, time_msg(self.t_ns), self._ee_path)
        if self._scene_shown is not None and self._scene_shown is not scene:
            clear = Marker(action=Marker.DELETEALL)                  # another model's geoms
            clear.header.frame_id, clear.header.stamp = names.WORLD_FRAME, time_msg(self.t_ns)
            markers = [clear] + markers
        self._scene_shown = scene
        self.pub_scene.publish(MarkerArray(markers=markers))

    def destroy_node(self):
        self.hot_path.stop()
        if self.mode == 'realtime':
            self._stop.set()
            self._thread.join(timeout=1.0)
        super().destroy_node()


def pose_stamped(stamp, pose: np.ndarray) -> PoseStamped:
    """A PoseStamped in the world frame of a pose (7,): position, quaternion (w, x, y, z)."""
    msg = PoseStamped()
    msg.header.stamp, msg.header.frame_id = stamp, names.WORLD_FRAME
    p, o = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z, o.w, o.x, o.y, o.z = pose.tolist()
    return msg


def main(args=None):
    run_node(SimNode, args)


if __name__ == '__main__':
    main()
