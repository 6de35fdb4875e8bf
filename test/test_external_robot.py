"""psl against robots it does not simulate, on the wall clock. Each robot is a process of the
tests (not psl's), started before psl's graph and ended by its process group:

A. test/minimal_robot.py takes raw torques on /effort_controller/commands and publishes
   /joint_states (its own joint order, an extra joint, noise, masses not the model's, a
   period of latency); psl's pd_controller commands it, with its default watchdog. A
   learning session in graph mode completes and the states stay continuous across its
   episodes (psl homes the arm, it never teleports it); states lost mid-episode fail the
   rollout with the reason, the controller commands zero torque until they come back, and
   the next rollout succeeds.
B. test/jtc_robot.py on the effort interface (its own JointTrajectoryController, its joint
   order reversed, an extra joint, masses +30 %, noise, a period of latency): psl starts no
   controller (``Graph(robot='external', controller='/arm_controller')``), a learning session
   completes, the robot's controller accepted every goal and aborted none, and nothing of
   psl's publishes a torque; ``psl check`` says the controller runs a task that learns a
   feed-forward torque.
C. test/jtc_robot.py on the position interface: a kinematic task's rollout succeeds; a task
   that learns a feed-forward torque is refused with one line naming the position interface,
   by ``psl up`` before it starts anything and by a running graph before anything moves.

Nothing here measures a duration on the test's clock: the tests wait for events (each wait with
a deadline) and judge what happened by the robots' stamps and the order in which the
publishers sent their messages.
"""
import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from psl_controller.parameters import STATE_TIMEOUT
from psl_controller.robot_link import STALE
from psl_optimizer.metrics import read_metrics
from psl_ros.client import RosClient
from psl_ros.graph import NODES, Graph, pid_alive
from psl_ros.hot_path import HotPath
from psl_ros.qos import WHOLE_EPISODE
from psl_task.arm_model import joint_names_of
from psl_task.task import load_task

pytestmark = pytest.mark.robot_on_the_wall_clock

HERE = Path(__file__).parent
TASK = 'reach_over_obstacle'            # kinematic: gravity off, no feed-forward
FEEDFORWARD_TASK = 'payload_transport'  # its policy learns a feed-forward torque
PAYLOAD = 'payload:0'   # ... and its tau[0] is the mass of its body 'payload'
CONTROLLER = 'arm_controller'           # the JTC robot's controller node
EXTRA_JOINT = 'gripper_finger'          # a joint of the robots that no task drives
OFF_START = 0.3         # rad in every joint: the robots start away from the task's start
MASS_SCALE = 1.3        # the JTC robot's masses and inertias, times the model's
NOISE_POSITION = 1e-3   # rad: sigma of the JTC robot's measured positions
NOISE_VELOCITY = 1e-2   # rad/s
SILENCE = 3.0           # s the minimal robot's states stop for (SIGUSR1): many times the
                        # controller's watchdog (STATE_TIMEOUT) and the executor's STALE
MID_EPISODE = 0.3       # of the primitive's episode (its motion: 0 to 0.75): the states stop
MAX_SPEED = 20.0        # rad/s: a jump faster than this between two states is a teleport
REST_STATES = 250       # states averaged for a posture: "nothing moved" compares two means,
# whose difference has a standard deviation of NOISE_POSITION * sqrt(2 / REST_STATES)
# (0.09 mrad) when the arm stands still; six of those (0.5 mrad) is far below any motion of
# a goal (homing alone moves every joint OFF_START)
STILL = 6 * NOISE_POSITION * np.sqrt(2 / REST_STATES)
# pd_controller's gains on the minimal robot: a third of the task's. A Python robot, controller
# and evaluator on a loaded 2-core machine answer a state several periods late at times, and
# the task's gains, tuned for lockstep, then make the arm oscillate (seen: a joint wound to
# -27 rad); as on hardware, gains are set for the robot's latency (pd_controller kp, kd)
GAINS = {'kp': '[100.0,66.0,33.0]', 'kd': '[6.0,4.0,1.6]'}
# ... and as on hardware, its loop answers the states with real-time scheduling where the
# machine allows it (pd_controller realtime_priority; below the robot's loop, 50): on a loaded
# machine either Python process of the loop went unanswered for 0.1-0.4 s at times (the robot
# then applies zero torque), and the homing did not settle
CONTROLLER_PRIORITY = 40
MINIMAL_TOPICS = {'joint_states': '/joint_states', 'effort_command': '/effort_controller/commands'}
START_TIMEOUT = 60.0    # s for a robot's endpoints or a graph to come up
ROLLOUT_TIMEOUT = 120.0  # s for one rollout on the wall clock (about 6 s each here)
SESSION_TIMEOUT = 300.0  # s for a learning session of a few rollouts
CLI_TIMEOUT = 60.0      # s for a psl command that asks a controller and ends
# the nodes a rollout needs on a robot with its own controller (no learner, no memory)
ROLLOUT_NODES = tuple(n for n in NODES if n[0] in ('dmp_executor', 'reward_evaluator'))


# -- the robots and psl's graph ---------------------------------------------------------------
def robot_setup(task_name: str):
    """The task, the robot's joint order (the task's reversed), its start posture (OFF_START
    from the task's) and the task's gains, in that order."""
    task = load_task(task_name)
    names = joint_names_of(task)
    order = list(reversed(names))
    index = [names.index(j) for j in order]
    start = np.asarray(task.start_posture)[index] + OFF_START
    return (task, order, start, np.asarray(task.controller.kp)[index],
            np.asarray(task.controller.kd)[index])


def minimal_robot_args() -> list[str]:
    task, order, start, _, _ = robot_setup(TASK)
    return ['--model', str(task.model_path), '--joints', *order, '--start', *map(str, start),
            '--silence', str(SILENCE)]


def jtc_robot_args(task_name: str, interface: str) -> list[str]:
    """test/jtc_robot.py on the task's model: its order, off the start, heavier, noisy, a
    period late, an extra joint; on the effort interface with the task's gains; on the
    feed-forward task's model its payload's mass from the announced instance."""
    task, order, start, kp, kd = robot_setup(task_name)
    args = ['--model', str(task.model_path), '--joints', *order, '--start', *map(str, start),
            '--interface', interface, '--controller', CONTROLLER,
            '--mass-scale', str(MASS_SCALE), '--noise-position', str(NOISE_POSITION),
            '--noise-velocity', str(NOISE_VELOCITY), '--latency-periods', '1',
            '--extra-joint', EXTRA_JOINT]
    if interface == 'effort':
        args += ['--kp', *map(str, kp), '--kd', *map(str, kd)]
    if task_name == FEEDFORWARD_TASK:
        args += ['--payload', PAYLOAD]
    return args


class RobotProcess:
    """A robot process in a session of its own, its output in a log file."""

    def __init__(self, script: str, args: list[str], log_path: Path):
        self.log_path = log_path
        self._log = open(log_path, 'wb')
        self.process = subprocess.Popen([sys.executable, str(HERE / script), *args],
                                        stdout=self._log, stderr=subprocess.STDOUT,
                                        start_new_session=True)

    @property
    def pid(self) -> int:
        return self.process.pid

    def log(self) -> str:
        return self.log_path.read_text(errors='replace')

    def end(self) -> None:
        end_group(self.process)
        self._log.close()


def end_group(process: subprocess.Popen) -> None:
    """SIGKILL to the process's group (its session), then reap it."""
    try:
        os.killpg(process.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    process.wait(timeout=10)


@contextlib.contextmanager
def robot_running(script: str, args: list[str], log_path: Path):
    robot = RobotProcess(script, args, log_path)
    try:
        yield robot
    finally:
        robot.end()


@contextlib.contextmanager
def graph_running(log_dir: Path, **options):
    """psl's graph (`Graph(**options)`), ready, and a client of it; ended by PID, and checked
    to leave no process behind, whatever happens."""
    graph = Graph(log_dir=log_dir, **options)
    try:
        graph.start()
        graph.wait_ready(timeout=START_TIMEOUT)
        with RosClient() as client:
            yield graph, client
    finally:
        graph.stop()
        left = [p.name for p in graph.processes if pid_alive(p.pid)]
        assert not left, f'processes left behind: {left}'


def until(condition, timeout: float, what: str, robot: RobotProcess | None = None) -> None:
    """Wait for `condition`; fail naming `what` after `timeout` s, or at once when the robot
    has ended."""
    deadline = time.monotonic() + timeout
    while not condition():
        if robot is not None and robot.process.poll() is not None:
            pytest.fail(f'the robot ended ({robot.process.returncode}) while waiting for '
                        f'{what}:\n{robot.log()[-3000:]}')
        if time.monotonic() > deadline:
            pytest.fail(f'{what}: not within {timeout:g} s')
        time.sleep(0.01)


def wait_for_robot(observer: RosClient, robot: RobotProcess, controller: str = '') -> None:
    """Until a joint state of the robot has come (only a running publisher sends one: the
    robot before it is ended and reaped) and, with `controller`, that controller's parameter
    services and action server are seen."""
    from sensor_msgs.msg import JointState
    services = ([f'/{controller}/get_parameters',
                 f'/{controller}/follow_joint_trajectory/_action/send_goal']
                if controller else [])
    came = threading.Event()
    sub = observer.node.create_subscription(JointState, '/joint_states',
                                            lambda _: came.set(), 10)
    try:
        def up() -> bool:
            offered = {name for name, _ in observer.node.get_service_names_and_types()}
            return came.is_set() and all(s in offered for s in services)
        until(up, START_TIMEOUT, 'the robot\'s joint states and controller', robot)
    finally:
        observer.node.destroy_subscription(sub)


def run_psl(*args: str) -> tuple[int, str, str]:
    """A psl command in a session of its own: (exit code, stdout, stderr); its group is
    ended whatever happens."""
    process = subprocess.Popen([sys.executable, '-m', 'psl_cli.main', *args],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    try:
        out, err = process.communicate(timeout=CLI_TIMEOUT)
    finally:
        end_group(process)
    return process.returncode, out, err


# -- what the test process receives -----------------------------------------------------------
class Recorder:
    """What the test process receives of the robot's joint states and, with `commands`, of the
    torques sent on its effort topic, each with its DDS source timestamp (when its publisher
    sent it: every process here reads the same system clock, so the messages of two
    publishers can be put in the order they were sent) and, for a state, its publication
    sequence number (the robot's count of the states it sent). A lean loop of its own takes
    what queued every 10 ms (`psl_ros.hot_path.HotPath`: an rclpy executor would fall
    behind the robot's 500 Hz on a loaded machine); `close` ends it."""

    def __init__(self, node, commands: bool = False):
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray
        self.lock = threading.Lock()
        self.states = []        # (sent [ns], stamp [ns], names, positions, sequence number)
        self.commands = []      # (sent [ns], torques, sequence number)
        self.path = HotPath(node, 'recorder', pause=0.01)
        self.path.subscribe(JointState, '/joint_states', self.on_state, WHOLE_EPISODE,
                            info=True)
        if commands:
            self.path.subscribe(Float64MultiArray, MINIMAL_TOPICS['effort_command'],
                                self.on_command, WHOLE_EPISODE, info=True)
        self.path.start()

    def close(self) -> None:
        self.path.stop()

    def on_state(self, msg, info) -> None:
        with self.lock:
            self.states.append((info['source_timestamp'],
                                msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec,
                                list(msg.name), np.array(msg.position),
                                info['publication_sequence_number']))

    def on_command(self, msg, info) -> None:
        with self.lock:
            self.commands.append((info['source_timestamp'], np.array(msg.data),
                                  info['publication_sequence_number']))

    def commands_through(self, t: int) -> list | None:
        """The commands received, in the order they were sent, once they are complete up to
        one sent after `t` (their publisher's sequence numbers without a hole from the first
        received on); None before. A command this reader missed comes again from its
        publisher's history on a later heartbeat, after newer ones (seen under load: the zero
        torques of a silence taken after the torques that followed it)."""
        with self.lock:
            commands = sorted(self.commands, key=lambda c: c[2])
        numbers = [c[2] for c in commands]
        if not numbers or max(c[0] for c in commands) <= t:
            return None
        if numbers != list(range(numbers[0], numbers[0] + len(numbers))):
            return None
        return sorted(((sent, u) for sent, u, _ in commands), key=lambda c: c[0])

    def count(self) -> int:
        with self.lock:
            return len(self.states)

    def silence(self) -> tuple[tuple[int, int], tuple[int, int]] | None:
        """(sent, sequence number) of the last state before the first pause of more than
        SILENCE / 2 in the robot's states, and of the first after it; None before one."""
        with self.lock:
            states = sorted((s[0], s[4]) for s in self.states)
        gaps = np.flatnonzero(np.diff([sent for sent, _ in states]) > SILENCE / 2 * 1e9)
        return (states[gaps[0]], states[gaps[0] + 1]) if len(gaps) else None

    def timeline(self, t0: int, t1: int, around: int = 5) -> str:
        """States and commands in the order they were sent, from `around` of each before
        `t0` to `around` after `t1` (for a failure's message)."""
        with self.lock:
            events = sorted([(s[0], f'state {s[4]}') for s in self.states]
                            + [(c[0], f'torque {np.round(c[1], 4).tolist()} #{c[2]}')
                               for c in self.commands])
        sent = [e[0] for e in events]
        lo = max(0, int(np.searchsorted(sent, t0)) - 2 * around)
        hi = int(np.searchsorted(sent, t1, side='right')) + 2 * around
        chosen = events[lo:hi]
        if len(chosen) > 60:
            chosen = chosen[:30] + [(chosen[30][0], '...')] + chosen[-30:]
        return '\n'.join(f'{(t - t0) * 1e-6:+10.3f} ms {what}' for t, what in chosen)

    def posture(self, first: int, joints: int) -> np.ndarray:
        """The mean position of REST_STATES states from the `first`-th, the robot's first
        `joints` joints."""
        with self.lock:
            chosen = self.states[first:first + REST_STATES]
        assert len(chosen) == REST_STATES
        return np.mean([s[3][:joints] for s in chosen], axis=0)


@pytest.fixture(scope='module')
def observer():
    """A node of the test's own that watches the robots (module-wide)."""
    with RosClient(name='robot_observer') as client:
        yield client


@pytest.fixture
def record(observer):
    """record(commands=False): a Recorder on the observer, closed after the test."""
    recorders = []

    def start(**kinds) -> Recorder:
        recorders.append(Recorder(observer.node, **kinds))
        return recorders[-1]
    try:
        yield start
    finally:
        for recorder in recorders:
            recorder.close()


def default_rollout(task):
    """The default policy's theta and the middle of the task's instances."""
    from psl_controller.policy import policy_for
    return policy_for(task).default_theta, (task.tau_low + task.tau_high) / 2


def learn(client: RosClient, out: Path, budget: int):
    """A learning session in graph mode: one instance, `budget` rollouts at most, one
    held-out instance (two episodes or more, each homed from where the last one left the
    arm); the rollouts it executed."""
    result = client.learn(timeout=SESSION_TIMEOUT, task=TASK, strategy='bootstrap',
                          num_tasks=1, max_rollouts_per_task=budget, seed=1, mode='graph',
                          output_dir=str(out), num_test=1)
    assert result.success, result.message
    metrics = read_metrics(Path(result.metrics_path).parent)
    return (metrics.summary.total_rollouts - sum(t.refused for t in metrics.tasks)
            + len(metrics.summary.test_rewards))


@contextlib.contextmanager
def announced(client: RosClient, observer: RosClient):
    """The task instances psl announces while the block runs, one per goal it sends (each
    homing, hold and primitive goal, each sent again after a late one: `Episode._start`), as
    the observer receives them (matched before the block begins)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from psl_msgs.msg import TaskInstance
    from psl_ros import names
    instances = []
    sub = observer.node.create_subscription(
        TaskInstance, '/' + names.TASK_INSTANCE, instances.append,
        QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.VOLATILE))
    try:
        topic = '/' + names.TASK_INSTANCE
        # both halves: this reader matched the executor's writer, and the writer every reader
        # the graph knows of (this one among them)
        until(lambda: sub.get_publisher_count() > 0 and not client.worker.unmatched(
            topic, observer.node.count_subscribers(topic)),
            START_TIMEOUT, 'the executor\'s task_instance publisher matched the observer')
        yield instances
    finally:
        observer.node.destroy_subscription(sub)


def resent(graph: Graph) -> int:
    """The goals psl's executor sent again because they reached the controller after their
    start (its log says each)."""
    return (graph.log_dir / 'dmp_executor.log').read_text(errors='replace').count(
        'sending it again')


def goals(robot: RobotProcess) -> dict[str, int]:
    """How often the JTC robot's log says each thing of its goals (it logs every goal it
    receives, accepts, ends)."""
    log = robot.log()
    return {what: log.count(line) for what, line in (
        ('received', 'Received new action goal'), ('accepted', 'Accepted new action goal'),
        ('reached', 'Goal successfully reached!'), ('aborted', 'Aborted due to'))}


# -- A: the minimal robot, psl's pd_controller on its torque topic ------------------------------
@pytest.fixture(scope='class')
def minimal(tmp_path_factory, observer):
    """The minimal robot and psl's graph on it (pd_controller in the robot's joint order,
    gains for its latency, the default watchdog)."""
    order = robot_setup(TASK)[1]
    folder = tmp_path_factory.mktemp('minimal')
    with robot_running('minimal_robot.py', minimal_robot_args(),
                       folder / 'robot.log') as robot:
        with graph_running(folder / 'graph', task=TASK, robot='external',
                           robot_topics=MINIMAL_TOPICS,
                           extra_params={'pd_controller': {
                               'command_joints': '[' + ','.join(order) + ']', **GAINS,
                               'realtime_priority': CONTROLLER_PRIORITY},
                               'learner': {'output_root': str(folder / 'runs')}}) \
                as (graph, client):
            wait_for_robot(observer, robot)
            yield robot, graph, client


class TestMinimalRobot:

    def test_a_learning_session_moves_the_arm_continuously(self, minimal, record, observer,
                                                           tmp_path):
        """A session in graph mode completes; across its episodes the joint states never
        jump (psl drives the arm from where it is to each start: no teleport), and every
        primitive starts with the arm homed: over the REST_STATES / 5 states before its
        announced start (the robot's clock) every joint stays within homing.tolerance of the
        start posture (the robot starts OFF_START away)."""
        robot, graph, client = minimal
        task = load_task(TASK)
        recorder = record()
        # one rollout, then the held-out one: what is shown here is the motion across the
        # episodes
        with announced(client, observer) as instances:
            executed = learn(client, tmp_path / 'session', budget=1)
        with recorder.lock:
            states = sorted(recorder.states, key=lambda s: s[1])
        _, order, _, _, _ = robot_setup(TASK)
        assert states[-1][2] == order + [EXTRA_JOINT]
        stamps = np.array([s[1] for s in states]) * 1e-9      # the robot's clock
        q = np.array([s[3] for s in states])
        # every rollout is at least an episode of the task's length
        assert stamps[-1] - stamps[0] > executed * task.duration
        # a jump: more than MAX_SPEED allows between two states, beyond ten times the noise
        jumps = np.abs(np.diff(q, axis=0)) - MAX_SPEED * np.diff(stamps)[:, None]
        assert jumps.max() < 0.01, f'a jump of {jumps.max():.3f} rad between two states'
        # homed before each primitive: the states of the last REST_STATES / 5 periods before
        # its start, in the task's joint order (the robot's is reversed; 1 mrad of noise
        # against a tolerance of 10)
        start = np.asarray(task.start_posture)
        primitives = [i for i in instances if not i.homing]
        assert len(primitives) >= executed, (len(primitives), executed)
        window = REST_STATES // 5
        for instance in primitives:
            at = instance.stamp.sec + instance.stamp.nanosec * 1e-9
            last = int(np.searchsorted(stamps, at, side='right'))
            assert last >= window, f'no states recorded before the primitive at {at:.3f} s'
            before = q[last - window:last, :task.n_joints][:, ::-1]
            off = np.abs(before - start).max()
            assert off <= task.homing.tolerance, (
                f'the primitive at {at:.3f} s started {off:.4f} rad from the start posture')

    def test_lost_states_fail_the_rollout_and_stop_the_torque(self, minimal, record):
        """The robot's states stop mid-episode (SIGUSR1: SILENCE s): the rollout fails with
        the reason; the controller's first zero torque was sent after the robot's last state
        and before its states came back, and it sent nothing but zero torque in between; the
        next rollout succeeds."""
        assert SILENCE > 2 * max(STATE_TIMEOUT, STALE)
        robot, graph, client = minimal
        task = load_task(TASK)
        theta, tau = default_rollout(task)
        recorder = record(commands=True)
        outcome, progress = [], []
        rolling = threading.Thread(target=lambda: outcome.append(client.rollout(
            TASK, tau, theta, timeout=ROLLOUT_TIMEOUT,
            feedback=lambda message: progress.append(message.feedback.progress))))
        rolling.start()
        try:
            # the primitive's episode runs (its progress, from the controller's feedback):
            # its states stop in the middle of the motion
            until(lambda: outcome or (progress and progress[-1] >= MID_EPISODE),
                  ROLLOUT_TIMEOUT, 'the primitive in the middle of its motion', robot)
            assert not outcome, outcome[0].message
            os.kill(robot.pid, signal.SIGUSR1)
        finally:
            rolling.join(timeout=ROLLOUT_TIMEOUT)
        assert outcome, 'the rollout did not end'
        result = outcome[0]
        assert not result.success and 'joint states stopped' in result.message, result.message
        until(lambda: recorder.silence() is not None, SILENCE + START_TIMEOUT,
              'the states back', robot)
        (last, last_seq), (back, back_seq) = recorder.silence()
        # the robot published no state between these two that this test did not receive
        assert back_seq == last_seq + 1, (
            f'the test lost states {last_seq + 1}..{back_seq - 1} of the robot at the silence')
        until(lambda: recorder.commands_through(back) is not None, START_TIMEOUT,
              "every command of the controller up to one after the states' return", robot)
        commands = recorder.commands_through(back)
        zero = next((sent for sent, u in commands if not np.any(u)), None)
        assert zero is not None, 'the controller never commanded zero torque'
        timeline = recorder.timeline(last, back)
        assert last < zero < back, (
            f'the first zero torque was not sent in the silence:\n{timeline}')
        # not before the watchdog's timeout had passed since the last state was sent (it was
        # received after that: both stamps are their publishers', on this machine's clock)
        assert zero - last >= STATE_TIMEOUT * 1e9, (
            f'zero torque {(zero - last) * 1e-9:.3f} s after the last state, before the '
            f'watchdog\'s {STATE_TIMEOUT} s:\n{timeline}')
        # no bound above: how late is the busy controller process's timer (its first look past
        # the timeout fires: src/psl_controller/test/test_watchdog.py)
        torque = [u for sent, u in commands if zero <= sent < back and np.any(u)]
        assert not torque, f'torque sent after the zero, in the silence:\n{timeline}'
        # the states are back: the session can go on
        again = client.rollout(TASK, tau, theta, timeout=ROLLOUT_TIMEOUT)
        assert again.success and not again.aborted, again.message


# -- B: the JTC robot on the effort interface ---------------------------------------------------
@pytest.fixture(scope='class')
def effort(tmp_path_factory, observer):
    """The JTC robot on the effort interface (the task's model) and psl's graph driving
    its controller: psl starts no robot and no controller."""
    folder = tmp_path_factory.mktemp('effort')
    with robot_running('jtc_robot.py', jtc_robot_args(TASK, 'effort'),
                       folder / 'robot.log') as robot:
        with graph_running(folder / 'graph', robot='external', controller=f'/{CONTROLLER}',
                           robot_topics={'joint_states': '/joint_states'},
                           extra_params={'learner': {'output_root': str(folder / 'runs')}}) \
                as (graph, client):
            wait_for_robot(observer, robot, CONTROLLER)
            yield robot, graph, client


class TestJtcRobotOnEffort:

    def test_a_learning_session_through_the_robots_controller(self, effort, observer, tmp_path):
        """A session completes; every goal psl sent was accepted and none aborted; psl runs
        no controller and nothing publishes a torque (no effort_command, no
        Float64MultiArray publisher anywhere)."""
        robot, graph, client = effort
        before = goals(robot)['received']
        with announced(client, observer) as instances:
            executed = learn(client, tmp_path / 'session', budget=2)
            until(lambda: len(instances) >= 2 * executed, 10.0, 'every announcement')
        seen = goals(robot)
        # every goal psl sent (announced), and none else, reached the robot's controller:
        # per executed rollout one primitive, besides homings and holds
        assert seen['received'] - before == len(instances), (seen, len(instances))
        primitives = sum(not i.homing for i in instances)
        assert primitives - resent(graph) <= executed <= primitives, (executed, primitives)
        assert seen['accepted'] == seen['received'] and seen['aborted'] == 0, seen
        assert {p.name for p in graph.processes} == {'dmp_executor', 'reward_evaluator',
                                                     'skill_memory', 'learner'}
        node = observer.node
        assert ('pd_controller', '/') not in node.get_node_names_and_namespaces()
        assert node.count_publishers('/effort_command') == 0
        torques = {topic: [f'{i.node_namespace}/{i.node_name}'
                           for i in node.get_publishers_info_by_topic(topic)]
                   for topic, types in node.get_topic_names_and_types()
                   if 'std_msgs/msg/Float64MultiArray' in types}
        assert not any(torques.values()), f'torques published: {torques}'


def test_psl_check_says_an_effort_controller_runs_a_feedforward_task(tmp_path, observer):
    """`psl check --controller` on the JTC robot (effort) of the feed-forward task's model:
    the controller runs it (exit 0)."""
    with robot_running('jtc_robot.py', jtc_robot_args(FEEDFORWARD_TASK, 'effort'),
                       tmp_path / 'robot.log') as robot:
        wait_for_robot(observer, robot, CONTROLLER)
        code, out, err = run_psl('check', '--task', FEEDFORWARD_TASK,
                                 '--controller', f'/{CONTROLLER}')
        assert code == 0, err
        assert f"controller /{CONTROLLER}: runs task '{FEEDFORWARD_TASK}'" in out, out
        assert goals(robot)['received'] == 0


# -- C: the JTC robot on the position interface -------------------------------------------------
def test_a_kinematic_rollout_on_the_position_interface(tmp_path, observer):
    """The position interface runs a kinematic task: the rollout succeeds, its goals (the
    homing and the primitive, without effort) accepted and reached."""
    task = load_task(TASK)
    theta, tau = default_rollout(task)
    with robot_running('jtc_robot.py', jtc_robot_args(TASK, 'position'),
                       tmp_path / 'robot.log') as robot:
        with graph_running(tmp_path / 'graph', robot='external', controller=f'/{CONTROLLER}',
                           robot_topics={'joint_states': '/joint_states'},
                           nodes=ROLLOUT_NODES) as (graph, client):
            wait_for_robot(observer, robot, CONTROLLER)
            with announced(client, observer) as instances:
                result = client.rollout(TASK, tau, theta, timeout=ROLLOUT_TIMEOUT)
                until(lambda: any(not i.homing for i in instances), 10.0,
                      'the primitive\'s announcement')
        assert result.success and not result.aborted, result.message
        seen = goals(robot)
        # the homing (the robot starts off the start posture) and the primitive, each
        # accepted and reached (a goal sent again after a late start: announced again)
        assert [i.homing for i in instances][0] and not instances[-1].homing, instances
        assert seen['received'] == len(instances), (seen, len(instances))
        assert seen['accepted'] == seen['received'] and seen['aborted'] == 0, seen
        assert seen['reached'] == sum(1 for i in instances) - resent(graph), seen


def test_a_feedforward_task_is_refused_on_the_position_interface(tmp_path, observer, record):
    """A task that learns a feed-forward torque on the position interface: `psl up` exits 2
    with one line naming it and starts nothing; a running graph's rollout fails with that
    line, the robot's controller receives no goal and the arm stays where it was (the mean of
    its states before and after within STILL)."""
    task = load_task(FEEDFORWARD_TASK)
    theta, tau = default_rollout(task)
    joints = len(joint_names_of(task))
    with robot_running('jtc_robot.py', jtc_robot_args(FEEDFORWARD_TASK, 'position'),
                       tmp_path / 'robot.log') as robot:
        recorder = record()
        wait_for_robot(observer, robot, CONTROLLER)
        logs = tmp_path / 'up_logs'
        code, out, err = run_psl('up', '--robot', 'external', '--controller', f'/{CONTROLLER}',
                                 '--task', FEEDFORWARD_TASK, '--log-dir', str(logs))
        lines = err.splitlines()
        assert code == 2 and len(lines) == 1, err
        assert 'commands position' in lines[0] and 'position interface' in lines[0], err
        assert 'started' not in out and not list(logs.glob('*.log')), out
        with graph_running(tmp_path / 'graph', robot='external', controller=f'/{CONTROLLER}',
                           robot_topics={'joint_states': '/joint_states'},
                           nodes=ROLLOUT_NODES) as (graph, client):
            until(lambda: recorder.count() >= REST_STATES, START_TIMEOUT, 'states', robot)
            before = recorder.count()           # the states before the rollout
            result = client.rollout(FEEDFORWARD_TASK, tau, theta, timeout=ROLLOUT_TIMEOUT)
            after = recorder.count()            # the states after it
            assert not result.success, result.message
            assert lines[0] == f'psl up: {result.message}'
            until(lambda: recorder.count() >= after + REST_STATES, START_TIMEOUT,
                  'states after the rollout', robot)
        moved = np.abs(recorder.posture(after, joints)
                       - recorder.posture(before - REST_STATES, joints)).max()
        assert moved < STILL, f'the arm moved {moved * 1e3:.2f} mrad'
        assert goals(robot)['received'] == 0, robot.log()
