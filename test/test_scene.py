"""The simulator's ``scene`` topic (visualization_msgs/MarkerArray) through the running graph:
markers in the frame ``world`` with stable ids, published throttled while watched, poses that
follow the episode and agree with the scene of a batch-mode rollout, latched for late
viewers, and published at the end of an episode even when nobody watches."""
import threading
import time

import mujoco
import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from visualization_msgs.msg import MarkerArray

from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_ros import names
from psl_ros.stamps import NS_PER_S, to_ns
from psl_task.arm_model import ArmModel
from psl_sim.scene import ARM, END_EFFECTOR_PATH, OBSTACLES, Scene
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
SCENE_RATE = 30.0                   # Hz of simulated time, the simulator's default
POSE_TOLERANCE = 1e-8               # m, graph-mode poses against batch mode's final state
MOVED = 0.1                         # m, the hand moves at least this far in the episode


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


@pytest.fixture(scope='module')
def tau(task):
    return task.tau_high


@pytest.fixture(scope='module')
def theta(task):
    return policy_for(task).default_theta


class Collector:
    """A subscription to ``scene`` on the client's node that keeps what arrives."""

    def __init__(self, client, latched: bool = False):
        self.client, self.arrays, self.lock = client, [], threading.Lock()
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                         durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                     else DurabilityPolicy.VOLATILE))
        self.sub = client.node.create_subscription(MarkerArray, names.SCENE, self._keep, qos)

    def _keep(self, msg: MarkerArray) -> None:
        with self.lock:
            self.arrays.append(msg)

    def wait(self, done, timeout: float = 10.0) -> list[MarkerArray]:
        """What has arrived once `done(arrays)` is true; AssertionError after `timeout` s."""
        deadline = time.monotonic() + timeout
        while True:
            with self.lock:
                arrays = list(self.arrays)
            if done(arrays):
                return arrays
            assert time.monotonic() < deadline, f'{len(arrays)} scene arrays, not done'
            time.sleep(0.01)

    def close(self) -> None:
        self.client.node.destroy_subscription(self.sub)


def stamp_of(array: MarkerArray) -> int:
    stamps = {to_ns(m.header.stamp) for m in array.markers}
    assert len(stamps) == 1
    return stamps.pop()


def positions(array: MarkerArray, namespace: str) -> dict[int, np.ndarray]:
    return {m.id: np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z])
            for m in array.markers if m.ns == namespace}


@pytest.fixture(scope='module')
def episode(client, task, tau, theta):
    """One rollout watched on ``scene``: (result, arrays received during it, up to the
    episode's end, which comes last: one reliable writer's messages arrive in order)."""
    collector = Collector(client)
    try:
        client.wait_for_subscribers([names.SCENE], subscriptions=[collector.sub])
        result = client.rollout(TASK, tau, theta)
        assert result.success, result.message
        end = to_ns(result.evaluation.stamp) + task.num_steps * task.control_period_ns
        arrays = collector.wait(lambda got: any(stamp_of(a) == end for a in got))
    finally:
        collector.close()
    return result, arrays


def test_markers_are_in_the_world_frame_with_stable_ids(episode, task):
    _, arrays = episode
    assert len(arrays) > 1
    expected = {(s.namespace, s.marker_id) for s in Scene(ArmModel(task).model).shapes}
    expected.add((END_EFFECTOR_PATH, 0))
    for array in arrays:
        assert {m.header.frame_id for m in array.markers} == {names.WORLD_FRAME}
        keys = [(m.ns, m.id) for m in array.markers]
        assert len(keys) == len(set(keys)) and set(keys) == expected


def test_the_scene_is_throttled_to_its_rate_from_reset_to_the_end(episode, task):
    result, arrays = episode
    t0 = to_ns(result.evaluation.stamp)                 # the episode's first state
    stamps = [stamp_of(a) for a in arrays]
    assert stamps == sorted(stamps)
    assert stamps[0] == t0 and stamps[-1] == t0 + task.num_steps * task.control_period_ns
    duration = task.num_steps / task.control_rate
    most = int(duration * SCENE_RATE) + 2                # ticks, the reset and the end
    # the reset, ticks and the end (the writer keeps one array: a slow reader may skip some)
    assert 3 <= len(arrays) <= most
    # between reset and end (which is published whenever it comes) at most at the rate
    assert min(np.diff(stamps[:-1])) >= NS_PER_S / SCENE_RATE


def test_poses_follow_the_episode_and_agree_with_batch_mode(episode, task, tau, theta):
    _, arrays = episode
    first, last = positions(arrays[0], ARM), positions(arrays[-1], ARM)
    assert max(np.linalg.norm(last[i] - first[i]) for i in first) > MOVED
    # the final scene is that of batch mode's final state (graph == batch, conftest)
    arm = ArmModel(task)
    q_final = BatchRollouts(task).run(theta[None], tau)[0].q[-1]
    data = mujoco.MjData(arm.model)
    arm.move_bodies(tau, data)
    data.qpos[arm.qpos_adr] = q_final
    mujoco.mj_forward(arm.model, data)
    scene = Scene(arm.model)
    poses = scene.poses(data)
    for namespace in (ARM, OBSTACLES):
        received = positions(arrays[-1], namespace)
        for k, shape in enumerate(scene.shapes):
            if shape.namespace == namespace:
                np.testing.assert_allclose(received[shape.marker_id], poses.position[k],
                                           atol=POSE_TOLERANCE)
    # the executed path: one point per scene tick, ending at the end effector
    path = [m for m in arrays[-1].markers if m.ns == END_EFFECTOR_PATH][0]
    assert len(path.points) >= len(arrays)
    end = path.points[-1]
    np.testing.assert_allclose([end.x, end.y, end.z],
                               data.site_xpos[arm.ee_site], atol=POSE_TOLERANCE)


def test_the_end_of_an_unwatched_episode_is_latched_for_late_viewers(episode, client, task,
                                                                     theta):
    result = client.rollout(TASK, task.tau_low, theta)   # nobody subscribes to scene now
    assert result.success, result.message
    late = Collector(client, latched=True)
    try:
        arrays = late.wait(lambda got: len(got) >= 1)
    finally:
        late.close()
    assert len(arrays) == 1
    end = to_ns(result.evaluation.stamp) + task.num_steps * task.control_period_ns
    assert stamp_of(arrays[0]) == end
    obstacle_top = max(positions(arrays[0], OBSTACLES).values(), key=lambda p: p[2])
    assert obstacle_top[0] == pytest.approx(task.tau_low[0])
