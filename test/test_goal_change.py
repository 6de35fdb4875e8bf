"""A new goal during a rollout, through the graph's processes in lockstep: known before the
start (the action goal's new_goal) and live (psl_msgs/GoalUpdate on goal_update while the
episode runs). The arm ends at the new goal, the evaluator scores against it, the controller's
reference has no jump and is the policy's reference with the goal change, bit for bit."""
import json
import shutil
import subprocess
import sys
import threading

import mujoco
import numpy as np
import pytest
import yaml
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from psl_controller.policy import policy_for
from psl_task.arm_model import joint_names_of
from psl_task.task import EMBEDDED_TASKS, load_task, task_id

TASK = 'reach_over_obstacle'
NEW_GOAL = np.array([0.539, -0.395, -1.395])   # rad: the goal posture moved by 0.1-0.15 rad
SWITCH = 0.5                    # s from the episode start
POSTURE_TOLERANCE = 0.01        # rad, final joint angles to the goal posture
FK_TOLERANCE = 1e-9             # m, the evaluator's geometry against MuJoCo's own here
Q_TOLERANCE = 1e-9              # rad, graph against batch (as in conftest)
DELIVERY_TIMEOUT = 10.0         # s, for messages already published to reach the test
SETTLE = 1.5                    # s the arm needs after a goal change to reach the new goal
ROLLOUT_WAIT = 60.0             # s for a rollout of the live change to end


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


def hand(task, q) -> np.ndarray:
    """MuJoCo's own forward kinematics: the end-effector site at joint angles q."""
    model = mujoco.MjModel.from_xml_path(str(task.model_path))
    data = mujoco.MjData(model)
    for name, angle in zip(joint_names_of(task), q):
        data.qpos[model.joint(name).qposadr[0]] = angle
    mujoco.mj_kinematics(model, data)
    return data.site(task.end_effector_site).xpos.copy()


def stamp_ns(stamp) -> int:
    return stamp.sec * 10**9 + stamp.nanosec


class Recorder:
    """joint_states and the controller's reference (its controller_state) of the rollouts, by
    stamp [ns]; task_instance as it comes."""

    def __init__(self, client, wait_until, controller: str = 'pd_controller'):
        from control_msgs.msg import JointTrajectoryControllerState
        from psl_msgs.msg import TaskInstance
        from psl_ros.names import CONTROLLER_STATE
        from sensor_msgs.msg import JointState

        self.client, self.wait_until = client, wait_until
        self.streams = {'joint_states': {}, 'reference': {}}
        self.episodes: list[int] = []
        self.new_episode = threading.Event()
        qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
        states, references = self.streams['joint_states'], self.streams['reference']
        self.subscriptions = [
            client.node.create_subscription(
                JointState, 'joint_states',
                lambda m: states.__setitem__(stamp_ns(m.header.stamp), m.position), qos),
            client.node.create_subscription(
                JointTrajectoryControllerState, f'{controller}/{CONTROLLER_STATE}',
                lambda m: references.__setitem__(stamp_ns(m.header.stamp),
                                                 m.reference.positions), qos)]
        self.subscriptions.append(client.node.create_subscription(
            TaskInstance, 'task_instance', self.on_task,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)))
        client.wait_for_subscribers(['joint_states', f'{controller}/{CONTROLLER_STATE}',
                                     'task_instance'], subscriptions=self.subscriptions)

    def on_task(self, msg) -> None:
        self.episodes.append(stamp_ns(msg.stamp))
        self.new_episode.set()

    def episode(self, evaluation, task) -> tuple[np.ndarray, np.ndarray]:
        """Measured q and reference q_ref (N+1, n) of the episode of an evaluation."""
        q, q_ref, _ = self.robot_episode(evaluation, task, every=True)
        return q, q_ref

    def robot_episode(self, evaluation, task, every: bool = False):
        """(q, q_ref, steps) of the episode of an evaluation at the steps (of 0..N) whose
        states came: every one from psl's simulator; from a robot on the wall clock those it
        did not skip (a stalled loop skips periods), its last at least."""
        t0 = stamp_ns(evaluation.stamp)
        times = [t0 + k * task.control_period_ns for k in range(evaluation.num_steps + 1)]
        wanted = times if every else times[-1:]
        assert self.wait_until(lambda: all(t in s for s in self.streams.values() for t in wanted),
                               DELIVERY_TIMEOUT)
        steps = [k for k, t in enumerate(times) if all(t in s for s in self.streams.values())]
        return (*(np.array([self.streams[name][times[k]] for k in steps])
                  for name in ('joint_states', 'reference')), steps)

    def close(self) -> None:
        for subscription in self.subscriptions:
            self.client.node.destroy_subscription(subscription)


@pytest.fixture(scope='module')
def recorder(client, wait_until):
    r = Recorder(client, wait_until)
    yield r
    r.close()


def components(evaluation) -> dict:
    return dict(zip(evaluation.component_names, evaluation.component_values))


def assert_scored_against(evaluation, task, q, goal_posture):
    """The evaluation's goal is the hand at goal_posture (MuJoCo here), and its goal error
    is the measured final hand's distance to it."""
    goal = hand(task, goal_posture)
    np.testing.assert_allclose(evaluation.goal_position, goal, rtol=0, atol=FK_TOLERANCE)
    assert components(evaluation)['goal_error'] == pytest.approx(
        np.linalg.norm(hand(task, q[-1]) - goal), abs=FK_TOLERANCE)


def assert_no_jump(q_ref, plain_q_ref, change):
    """No step of the reference exceeds the unchanged reference's largest step by more than
    the goal filter's fastest step (alpha_goal |g_new - g| dt)."""
    policy = policy_for(load_task(TASK))
    filter_step = policy.dmp.alpha_goal * np.abs(change) * policy.task.control_period
    assert np.all(np.abs(np.diff(q_ref, axis=0)).max(axis=0)
                  <= np.abs(np.diff(plain_q_ref, axis=0)).max(axis=0) + filter_step)


def test_a_goal_change_in_the_action_goal_ends_at_the_new_goal(client, recorder, task,
                                                                monkeypatch):
    policy = policy_for(task)
    theta, tau = policy.default_theta, task.tau_default
    result = client.rollout(TASK, tau, theta, new_goal=NEW_GOAL, new_goal_time=SWITCH)
    assert result.success, result.message
    ev = result.evaluation
    assert ev.goal_change_time == SWITCH
    q, q_ref = recorder.episode(ev, task)
    # the arm ends at the new goal posture, far from the old one
    assert np.abs(q[-1] - NEW_GOAL).max() < POSTURE_TOLERANCE
    assert np.abs(q[-1] - task.goal_posture).max() > 5 * POSTURE_TOLERANCE
    assert_scored_against(ev, task, q, NEW_GOAL)
    assert ev.fulfilled
    # the controller tracked the policy's reference with the change, bit for bit, no jump
    expected = policy.reference_with_new_goal(theta, tau, SWITCH, NEW_GOAL)
    np.testing.assert_array_equal(q_ref, expected.q)
    assert_no_jump(q_ref, policy.reference(theta, tau).q, NEW_GOAL - task.goal_posture)
    # lockstep is deterministic: batch mode with the same reference and goal agrees
    from psl_optimizer.batch_rollout import BatchRollouts
    batch = BatchRollouts(task)
    monkeypatch.setattr(batch.policy, 'references', lambda thetas, taus: [expected] * len(thetas))
    q_batch = batch.run(theta[None], tau)[0].q
    assert np.abs(q - q_batch).max() < Q_TOLERANCE


def test_the_next_rollout_has_its_own_goal_again(client, task):
    theta = policy_for(task).default_theta
    changed = client.rollout(TASK, task.tau_default, theta, new_goal=NEW_GOAL,
                             new_goal_time=SWITCH)
    assert changed.success and changed.evaluation.goal_change_time == SWITCH
    result = client.rollout(TASK, task.tau_default, theta)
    assert result.success, result.message
    assert result.message == 'rollout done'
    assert result.evaluation.goal_change_time == -1.0
    np.testing.assert_allclose(result.evaluation.goal_position, hand(task, task.goal_posture),
                               rtol=0, atol=FK_TOLERANCE)
    assert result.evaluation.fulfilled


def test_bad_goal_changes_get_clear_errors(client, task):
    theta = policy_for(task).default_theta
    for new_goal, time, words in (([0.1, 0.2], SWITCH, ['needs 3 values', 'got 2']),
                                  ([0.1, float('nan'), 0.2], SWITCH, ['finite']),
                                  (NEW_GOAL, -1.0, ['goal change time'])):
        result = client.rollout(TASK, task.tau_default, theta, new_goal=new_goal,
                                new_goal_time=time)
        assert not result.success
        for word in words:
            assert word in result.message, result.message


LIVE_NS = 'live'        # the worker of the live change: a standard robot


@pytest.fixture(scope='module')
def long_task(tmp_path_factory):
    """The default task with 2 s more settling, 5 s in all (same robot: the simulator runs
    it), so that a live change late by a second still leaves the arm time to settle."""
    folder = tmp_path_factory.mktemp('long_episode')
    data = yaml.safe_load((EMBEDDED_TASKS / f'{TASK}.yaml').read_text())
    data['name'], data['settle_time'] = 'reach_over_obstacle_long', 3.5
    shutil.copy(EMBEDDED_TASKS / data['model'], folder / data['model'])
    (folder / 'long.yaml').write_text(yaml.safe_dump(data))
    return load_task(str(folder / 'long.yaml'))


@pytest.mark.robot_on_the_wall_clock
def test_a_live_goal_update_moves_the_goal_of_the_running_rollout(long_task, tmp_path,
                                                                   wait_until):
    """On psl's standard robot, on the wall clock as a robot runs (in lockstep the loop
    outruns the executor by a margin that depends on the machine's load; its controller runs
    inside its loop, so a loaded machine delays the states, not the control). The update is
    sent as soon as the episode is announced; the executor starts the change at SWITCH or, if
    the episode might already be close to it, a little later, and says when. Whatever that
    time, the reference is the policy's with the change at it, bit for bit."""
    from psl_ros.client import RosClient
    from psl_ros.graph import Graph
    task = long_task
    policy = policy_for(task)
    theta, tau = policy.default_theta, task.tau_default
    g = Graph(task=str(task.path), robot='standard', namespace=LIVE_NS,
              log_dir=tmp_path / 'logs')
    try:
        g.start()
        g.wait_ready(timeout=60)
        with RosClient(LIVE_NS) as client:
            recorder = Recorder(client, wait_until, controller='standard_robot')
            try:
                client.update_goal(NEW_GOAL, SWITCH)      # no rollout runs: ignored
                recorder.new_episode.clear()
                before = len(recorder.episodes)
                results = []
                rollout = threading.Thread(target=lambda: results.append(
                    client.rollout(task_id(task), tau, theta, timeout=ROLLOUT_WAIT)),
                    daemon=True)
                rollout.start()
                try:
                    assert recorder.new_episode.wait(30.0) and len(recorder.episodes) > before
                    client.update_goal(NEW_GOAL, SWITCH, episode_ns=recorder.episodes[-1])
                finally:
                    rollout.join(timeout=ROLLOUT_WAIT + 10.0)
                assert results, f'the rollout did not end within {ROLLOUT_WAIT} s'
                result, = results
                assert result.success, result.message
                ev = result.evaluation
                q, q_ref, steps = recorder.robot_episode(ev, task)
            finally:
                recorder.close()
    finally:
        g.stop()
    assert 'goal changed at' in result.message, result.message
    # the change came early enough for the arm to settle at the new goal
    assert SWITCH <= ev.goal_change_time <= task.duration + task.settle_time - SETTLE, \
        result.message
    assert np.abs(q[-1] - NEW_GOAL).max() < POSTURE_TOLERANCE
    assert_scored_against(ev, task, q, NEW_GOAL)
    expected = policy.reference_with_new_goal(theta, tau, ev.goal_change_time, NEW_GOAL)
    # a loaded machine stalls the loop, which then skips periods: whatever it skipped, the
    # states compared run from before the change to the episode's last step
    change_step = round(ev.goal_change_time / task.control_period)
    assert steps[0] < change_step < steps[-1] == len(expected.q) - 1, (steps[0], steps[-1])
    np.testing.assert_array_equal(q_ref, expected.q[steps])
    assert_no_jump(expected.q, policy.reference(theta, tau).q, NEW_GOAL - task.goal_posture)


def test_a_jumping_replacement_and_an_update_without_a_rollout_change_nothing(
        client, graph, task, wait_until):
    """A FollowJointTrajectory goal stamped with the start of the episode the controller ran,
    that leaves the reference it served last, is not run (OLD_HEADER_TIMESTAMP: the start has
    passed and it would jump); a goal update while no rollout runs is ignored by the
    executor; the next rollout is as before."""
    from control_msgs.action import FollowJointTrajectory

    from psl_controller.robot_link import trajectory_msg
    from psl_ros.action_client import ActionClient
    from psl_ros.client import send_goal, wait_for_result

    theta = policy_for(task).default_theta
    first = client.rollout(TASK, task.tau_default, theta)
    assert first.success, first.message
    reference = policy_for(task).reference_with_new_goal(theta, None, SWITCH, NEW_GOAL)
    goal = FollowJointTrajectory.Goal(trajectory=trajectory_msg(     # ends elsewhere: a jump
        joint_names_of(task), reference, stamp_ns(first.evaluation.stamp), effort=True))
    action = ActionClient(client.node, FollowJointTrajectory,
                          'pd_controller/follow_joint_trajectory')
    try:
        handle = send_goal(action, goal, 10.0, 'pd_controller')
        answer = wait_for_result(action, handle, 10.0, 'pd_controller')
    finally:
        action.destroy()
    assert answer.error_code == FollowJointTrajectory.Result.OLD_HEADER_TIMESTAMP, \
        answer.error_string
    logs = {p.name: p.log_path for p in graph.processes}
    ignored = 'goal update ignored: no rollout runs'
    before = logs['dmp_executor'].read_text().count(ignored)
    client.update_goal(NEW_GOAL, SWITCH)
    assert wait_until(lambda: logs['dmp_executor'].read_text().count(ignored) > before,
                      DELIVERY_TIMEOUT)
    again = client.rollout(TASK, task.tau_default, theta)
    assert again.success, again.message
    assert list(again.evaluation.component_values) == list(first.evaluation.component_values)


def test_an_evaluation_of_a_trajectory_of_other_joints_is_refused_at_once(client, task):
    """The evaluator scores the episode against the trajectory the executor says ran: one
    of other joints gets the reason, and the graph serves on."""
    from psl_msgs.msg import TaskInstance
    from psl_msgs.srv import EvaluateEpisode
    from psl_ros.names import EVALUATE
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    service = client.node.create_client(EvaluateEpisode, EVALUATE)
    try:
        assert service.wait_for_service(timeout_sec=10.0)
        answer = client.wait(service.call_async(EvaluateEpisode.Request(
            episode=TaskInstance(task=TASK, tau=task.tau_default.tolist(), num_steps=1,
                                 control_period=task.control_period),
            trajectory=JointTrajectory(joint_names=['a', 'b', 'c'], points=[
                JointTrajectoryPoint(positions=[0.0, 0.0, 0.0])]))), 10.0, 'evaluate')
    finally:
        client.node.destroy_client(service)
    assert not answer.success and "does not fit the task's" in answer.message, answer.message
    result = client.rollout(TASK, task.tau_default, policy_for(task).default_theta)
    assert result.success and result.evaluation.goal_change_time == -1.0, result.message


def test_psl_rollout_changes_the_goal_through_the_action(graph, task):
    out = subprocess.run([sys.executable, '-m', 'psl_cli.main', 'rollout', '--json',
                          '--new-goal-at', str(SWITCH), '--new-goal', *map(str, NEW_GOAL)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    ev = json.loads(out.stdout)
    assert ev['goal_change_time'] == SWITCH
    np.testing.assert_allclose(ev['goal_position'], hand(task, NEW_GOAL), atol=FK_TOLERANCE)


@pytest.mark.parametrize('args, words', [
    (['--new-goal-at', '0.5', '--new-goal', '0.1', '0.2'], ['needs 3 values', 'got 2']),
    (['--new-goal-at', '0.5', '--new-goal', '0.1', 'nan', '0.2'], ['finite']),
    (['--new-goal', '0.1', '0.2', '0.3'], ['go together']),
])
def test_psl_rollout_refuses_bad_goal_changes_in_one_line(args, words):
    out = subprocess.run([sys.executable, '-m', 'psl_cli.main', 'rollout', *args],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert len(out.stderr.strip().splitlines()) == 1, out.stderr
    for word in words:
        assert word in out.stderr
