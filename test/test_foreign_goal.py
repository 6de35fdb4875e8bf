"""A goal that is not psl's, sent to the robot's controller while psl runs episodes (issue 46):
it must not strand the robot, and a session must survive it.

A. An arm outside its joint ranges (where such a goal can leave it) is homed back inside by
   ``psl rollout``, which says so in one line (the executor's log and the command's stderr).
   The arm is put there by psl's simulator itself: a task of the test's own, the same arm with
   wider ranges (its hard stops), teleports it to joint2 = -OUT (the embedded task's limit is
   -3); the rollout is of the embedded task, driven (a copy whose homing section says drive).
   Nothing sends a goal outside the ranges, so this holds whatever the controllers refuse.
B. A foreign client sends the robot's controller a goal of its own (inside the ranges) in the
   middle of psl's episodes during ``psl learn --mode graph``: each preempted episode is one
   line in the executor's and the learner's logs, counted in metrics.json (``preempted``) and
   said by ``psl learn``, and the session goes on and completes. On psl's lockstep simulator
   the session is the one batch mode learns (a preempted rollout ran again and got the
   candidate's own reward, not the foreign goal's); on psl's standard robot (wall clock) it
   completes.

Every graph and client ends in a finally; every wait is on an event with a deadline.
"""
import json
import re
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from control_msgs.action import FollowJointTrajectory
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from psl_controller.follow_joint_trajectory import ACTION
from psl_msgs.msg import TaskInstance
from psl_msgs.srv import ResetTask
from psl_ros import names
from psl_ros.action_client import ActionClient
from psl_ros.client import RosClient, send_goal, wait_for_service
from psl_ros.futures import wait_for
from psl_ros.graph import Graph, pid_alive
from psl_ros.qos import LATCHED
from psl_ros.stamps import duration_msg, to_ns
from psl_task.arm_model import joint_names_of
from psl_task.task import EMBEDDED_TASKS, load_task

PSL = [sys.executable, '-m', 'psl_cli.main']
TASK = 'reach_over_obstacle'        # its joints' ranges: +-3 rad
OUT = 3.08                          # rad: |joint2| outside its range (the issue saw 3.03)
HARD_STOP = 3.5                     # rad: the wider ranges of the test's own arm
FOREIGN_TARGET = 2.9                # rad: joint3 of the foreign goal, inside the range
INTO_EPISODE = 0.2                  # s of an episode before the foreign goal is sent
ATTACKS = 2                         # episodes the foreign client attacks
SESSION = ['--tasks', '1', '--budget', '8', '--seed', '3', '--test-tasks', '1']
TIMEOUT = 300.0                     # s for a command or a session


def task_variant(folder: Path, name: str, **changes) -> Path:
    """The embedded task's YAML with `changes` (top-level keys) and its model beside it; the
    model's joint ranges widened to +-HARD_STOP when `wide`."""
    data = yaml.safe_load((EMBEDDED_TASKS / f'{TASK}.yaml').read_text())
    wide = changes.pop('wide', False)
    data.update(changes, name=name)
    model = (EMBEDDED_TASKS / data['model']).read_text()
    if wide:
        assert model.count('range="-3.0 3.0"') == 1
        model = model.replace('range="-3.0 3.0"', f'range="-{HARD_STOP} {HARD_STOP}"')
    data['model'] = f'{name}.xml'
    (folder / data['model']).write_text(model)
    path = folder / f'{name}.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    """psl's lockstep simulator with the whole loop and a learner (teleport resets: the
    embedded task's default)."""
    runs = tmp_path_factory.mktemp('runs')
    g = Graph(task=TASK, log_dir=tmp_path_factory.mktemp('graph_logs'),
              extra_params={'learner': {'output_root': str(runs)}})
    try:
        g.start()
        g.wait_ready(timeout=60)
        yield g
    finally:
        g.stop()
        assert not [p.name for p in g.processes if pid_alive(p.pid)]


def log(graph: Graph, node: str) -> str:
    return (graph.log_dir / f'{node}.log').read_text(errors='replace')


# -- A: homed back inside ---------------------------------------------------------------------
def test_psl_rollout_homes_an_arm_outside_its_range_back_inside(graph, tmp_path):
    """Before issue 46: exit 1, "homing refused by the safety check: joint 'joint2' at -3.08
    is below its limit -3", and so every rollout after."""
    task = load_task(TASK)
    start = [float(x) for x in task.start_posture]
    outside = [start[0], -OUT, start[2]]      # joint2 starts at -2.1: a short homing
    wide = task_variant(tmp_path, 'wide_arm', wide=True, start_posture=outside,
                        demonstration={'times': [0.0, 1.5], 'positions': [
                            outside, [float(x) for x in task.goal_posture]]})
    driven = task_variant(tmp_path, 'driven', homing={'reset': 'drive'})
    with RosClient() as client:
        # an episode of one control period: whatever the controller holds (after a session:
        # its last goal's end) acts on the arm for 2 ms only, not for the task's 2 s
        assert wait_for_service(client.reset_client, 30.0)
        placed = wait_for(client.reset_client.call_async(ResetTask.Request(
            task=str(wide), tau=list(load_task(str(wide)).tau_default),
            duration=task.control_period)), 30.0, 'sim/reset')
        assert placed.success and placed.num_steps == 1, placed.message
        out = subprocess.run(PSL + ['rollout', '--json', '--task', str(driven)],
                             capture_output=True, text=True, timeout=TIMEOUT)
        # the state between episodes, as it is
        state = wait_for(client.reset_client.call_async(
            ResetTask.Request(task=str(driven), tau=list(task.tau_default), mode='probe')),
            30.0, 'sim/reset')
    assert out.returncode == 0, out.stderr
    said = [line for line in out.stderr.splitlines() if 'outside its joint ranges' in line]
    assert len(said) == 1, out.stderr
    # where the arm was when homing began: one control period after it was placed
    where = re.search(r"joint 'joint2' at (\S+) rad, below its limit -3 by", said[0])
    assert where and abs(float(where[1]) + OUT) < 0.01, said
    assert 'homing brings it back inside' in said[0]
    assert log(graph, 'dmp_executor').count('homing brings it back inside') == 1
    assert json.loads(out.stdout)['num_steps'] == task.num_steps
    # after its episode, the arm is where the primitive left it, inside the ranges
    assert state.success and np.all(np.abs(state.position) <= 3.0), state.position


# -- B: a foreign goal during a session -------------------------------------------------------
class ForeignClient:
    """A client that is not psl's: at the first `attacks` primitive episodes psl announces
    (task_instance, not homing), once the robot's state INTO_EPISODE s into the episode has
    come, it sends the robot's controller a goal of its own: joint3 to FOREIGN_TARGET, the
    others where they are, inside every range. Sends from a thread of its own."""

    def __init__(self, controller: str, joint_names: list[str], attacks: int = ATTACKS):
        self.client = RosClient(name='foreign_client')
        node = self.client.node
        self.joints, self.attacks = joint_names, attacks
        self.action = ActionClient(node, FollowJointTrajectory, f'/{controller}/{ACTION}')
        self.lock = threading.Lock()
        self.episode: int | None = None     # the start stamp of the episode to attack
        self.latest: JointState | None = None
        self.due = threading.Event()
        self.sent: list[str] = []           # what became of each goal sent (accepted or why not)
        self.stop = threading.Event()
        node.create_subscription(TaskInstance, names.TASK_INSTANCE, self._on_instance, LATCHED)
        node.create_subscription(JointState, names.JOINT_STATES, self._on_state,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _on_instance(self, msg: TaskInstance) -> None:
        with self.lock:
            if not msg.homing and len(self.sent) < self.attacks:
                self.episode = to_ns(msg.stamp)

    def _on_state(self, msg: JointState) -> None:
        with self.lock:
            self.latest = msg
            if self.episode is not None and \
                    to_ns(msg.header.stamp) >= self.episode + int(INTO_EPISODE * 1e9):
                self.episode = None
                self.due.set()

    def _run(self) -> None:
        while not self.stop.is_set():
            if not self.due.wait(0.1):
                continue
            self.due.clear()
            with self.lock:
                state = self.latest
            position = dict(zip(state.name, state.position))     # the robot's order, extras
            target = np.array([position[j] for j in self.joints])
            target[self.joints.index('joint3')] = FOREIGN_TARGET
            goal = FollowJointTrajectory.Goal(trajectory=JointTrajectory(
                joint_names=self.joints, points=[JointTrajectoryPoint(
                    positions=target.tolist(), velocities=[0.0] * len(self.joints),
                    time_from_start=duration_msg(300_000_000))]))
            try:
                send_goal(self.action, goal, 10.0, 'the foreign goal')
                self.sent.append('accepted')
            except (TimeoutError, RuntimeError) as exc:
                self.sent.append(str(exc))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5.0)
        self.action.destroy()
        self.client.close()


def learn_with_a_foreign_client(graph: Graph, controller: str, out: Path, wait_until):
    """`psl learn --mode graph` (the session in the learner node) while a ForeignClient
    attacks; (the command's result, what the client sent, metrics.json)."""
    task = load_task(TASK)
    foreign = ForeignClient(controller, joint_names_of(task))
    try:
        assert wait_until(lambda: foreign.action.server_is_ready(), 30.0)
        learn = subprocess.run(PSL + ['learn', '--mode', 'graph', *SESSION, '--out', str(out)],
                               capture_output=True, text=True, timeout=TIMEOUT)
    finally:
        foreign.close()
    metrics = json.loads((out / 'metrics.json').read_text()) \
        if (out / 'metrics.json').is_file() else None
    return learn, foreign.sent, metrics


def check_said_and_counted(graph: Graph, learn, sent, metrics) -> int:
    """The session completed; every preemption is one line in the executor's and the
    learner's logs, counted in metrics.json, and psl learn says the count. The number."""
    assert learn.returncode == 0, learn.stderr
    assert sent and all(s == 'accepted' for s in sent), sent
    assert metrics is not None and metrics['complete'], metrics
    preempted = sum(t['preempted'] for t in metrics['tasks'])
    executor = log(graph, 'dmp_executor').count("rollout preempted: the ")
    learner = log(graph, 'learner').count('the rollout runs again')
    assert preempted >= 1 and preempted == executor == learner, (preempted, executor, learner)
    assert f"psl learn: {preempted} episodes were preempted by goals that are not psl's" in \
        learn.stderr, learn.stderr
    return preempted


def test_a_session_on_the_simulator_says_counts_and_survives_a_foreign_goal(graph, tmp_path,
                                                                           wait_until):
    """Before issue 46: the session retried silently (nothing said, nothing counted)."""
    learn, sent, metrics = learn_with_a_foreign_client(graph, 'pd_controller',
                                                       tmp_path / 'graph', wait_until)
    check_said_and_counted(graph, learn, sent, metrics)
    batch = subprocess.run(PSL + ['learn', *SESSION, '--out', str(tmp_path / 'batch')],
                           capture_output=True, text=True, timeout=TIMEOUT)
    assert batch.returncode == 0, batch.stderr
    batch = json.loads((tmp_path / 'batch' / 'metrics.json').read_text())
    # the candidates' own rewards: the session batch mode learns
    assert [t['rollouts'] for t in metrics['tasks']] == [t['rollouts'] for t in batch['tasks']]
    assert [t['best_reward'] for t in metrics['tasks']] == pytest.approx(
        [t['best_reward'] for t in batch['tasks']], abs=1e-9)
    assert metrics['summary']['test_rewards'] == pytest.approx(
        batch['summary']['test_rewards'], abs=1e-9)


@pytest.mark.robot_on_the_wall_clock
def test_a_session_on_the_standard_robot_says_counts_and_survives_a_foreign_goal(tmp_path,
                                                                               wait_until):
    """Before issue 46: the session stopped after 0 of its tasks (the foreign goal left the
    arm outside its range, and homing was refused), or retried without a word."""
    g = Graph(task=TASK, robot='standard', log_dir=tmp_path / 'logs',
              extra_params={'learner': {'output_root': str(tmp_path / 'runs')}})
    try:
        g.start()
        g.wait_ready(timeout=60)
        learn, sent, metrics = learn_with_a_foreign_client(g, 'standard_robot',
                                                           tmp_path / 'robot', wait_until)
    finally:
        g.stop()
        assert not [p.name for p in g.processes if pid_alive(p.pid)]
    check_said_and_counted(g, learn, sent, metrics)
