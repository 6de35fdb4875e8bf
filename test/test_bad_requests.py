"""No single request takes the graph down, moves the arm past its limits or exhausts a node.

The whole graph (simulator, controller, executor, evaluator, skill memory, learner) runs as
processes; every case below is a request that once killed a node or was answered wrongly, and
a generated family of bad values for every numeric and string field of every psl_msgs
request. After each, every node still answers and still works (a rollout, a query)."""
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from psl_controller.policy import policy_for
from psl_msgs.srv import ResetTask
from psl_ros import names
from psl_ros.graph import pid_alive
from psl_ros.qos import RELIABLE, SERVICES
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
BAD_NUMBERS = (math.nan, math.inf, -math.inf, 1e308, -1e308, -1.0, 0.0, 1e-300)
BAD_STRINGS = ('', 'x' * 256, 'x' * 5000, '../../etc/passwd', '/dev/zero', 'a/b\\c d',
               'nö_ascii_✓')


MINE = 'psl-bad-requests'      # the files this module saves, in its memory folder


@pytest.fixture(scope='module')
def memory_dir(tmp_path_factory) -> Path:
    """The graph's memory folder (its skill_memory's memory_dir), the module's own: the saves
    by bare names below (generated ones among them: 'a/b\\c d') land there and nowhere else."""
    return tmp_path_factory.mktemp('memory')


@pytest.fixture(scope='module')
def graph_options(memory_dir):
    return {'extra_params': {'skill_memory': {'memory_dir': str(memory_dir)}}}


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


def call(client, srv_type, name: str, timeout: float = 20.0, **fields):
    service = client.node.create_client(srv_type, name, qos_profile=SERVICES)
    try:
        assert service.wait_for_service(timeout_sec=timeout), f'{name} is not served'
        return client.wait(service.call_async(srv_type.Request(**fields)), timeout, name)
    finally:
        client.node.destroy_client(service)


def assert_the_graph_serves(graph, client, task):
    """Every node of the graph runs, and answers: the memory its info, the loop a rollout."""
    dead = [p.name for p in graph.processes if not pid_alive(p.pid)]
    assert not dead, f'dead nodes: {dead}'
    assert client.memory('info', timeout=20).success
    result = client.rollout(TASK, task.tau_default, policy_for(task).default_theta, timeout=60)
    assert result.success and result.evaluation.fulfilled, result.message


# -- the probe's cases that killed a node --------------------------------------------------------
@pytest.mark.parametrize('duration, words', [
    (math.inf, 'finite'), (1e308, 'max_episode_duration'), (math.nan, 'finite'),
    (-1.0, 'finite number of seconds >= 0'), (1e-9, 'shorter than one control period'),
    (1e4, 'max_episode_duration')])
def test_a_reset_of_a_bad_duration_is_refused(graph, client, task, duration, words):
    response = call(client, ResetTask, names.RESET, task=TASK,
                    tau=task.tau_default.tolist(), duration=duration)
    assert not response.success and words in response.message, response.message
    assert_the_graph_serves(graph, client, task)


@pytest.mark.parametrize('name', ['a' * 256, 'a' * 5000, 'x/' * 300 + 'y.yaml'])
def test_a_long_task_name_is_refused_by_every_node_that_takes_one(graph, client, task, name,
                                                                  memory_dir):
    response = call(client, ResetTask, names.RESET, task=name, tau=task.tau_default.tolist())
    assert not response.success and response.message, response.message
    result = client.rollout(name, task.tau_default, policy_for(task).default_theta)
    assert not result.success and any(words in result.message for words in (
        'characters', 'File name too long', 'does not exist')), result.message
    learned = client.learn(timeout=60, task=name, strategy='bootstrap', num_tasks=1,
                           max_rollouts_per_task=2, seed=0, mode='batch',
                           output_dir=str(memory_dir / 'never'))
    assert not learned.success and learned.message, learned.message
    assert_the_graph_serves(graph, client, task)


@pytest.mark.parametrize('path', ['a' * 256, '{mine}-ok.npz/x.npz', 'a' * 5000, '\0'])
def test_a_memory_path_that_raises_is_refused(graph, client, task, path):
    assert client.memory('save', path=f'{MINE}-ok.npz').success
    path = path.format(mine=MINE)
    before = client.memory('info').message
    response = client.memory('load', path=path)
    assert not response.success and response.message, response.message
    assert client.memory('info').message == before
    assert_the_graph_serves(graph, client, task)


def test_a_session_into_a_folder_outside_the_memory_folder_is_refused_before_any_work(
        graph, client, task, tmp_path):
    outside = tmp_path / 'outside' / 'run'          # beside the memory folder, not in it
    before = client.memory('info').message
    result = client.learn(timeout=60, task=TASK, strategy='bootstrap', num_tasks=1,
                          max_rollouts_per_task=5, seed=0, mode='batch',
                          output_dir=str(outside))
    assert not result.success and 'outside the memory folder' in result.message, result.message
    assert not outside.parent.exists()
    assert client.memory('info').message == before            # no task ran, nothing added
    assert_the_graph_serves(graph, client, task)


def test_a_load_during_a_graph_mode_session_is_refused_and_the_skill_holds_its_samples(
        graph, client, task, memory_dir):
    import json

    from psl_memory.skill_memory import SkillMemory
    other = SkillMemory()
    other.create(TASK, task.tau_low, task.tau_high, policy_for(task).default_theta)
    other.add(TASK, task.tau_default, policy_for(task).default_theta)
    other.save(memory_dir / f'{MINE}-other.npz')
    feedback = threading.Event()
    handle = client.send_learn_goal(feedback=lambda _: feedback.set(), task=TASK,
                                    strategy='bootstrap', num_tasks=2, max_rollouts_per_task=12,
                                    seed=3, num_test=2, mode='graph',
                                    output_dir=str(memory_dir / 'session'))
    try:
        assert feedback.wait(60), 'the session sent no feedback'
        for replace in (False, True):
            response = client.memory('load', path=f'{MINE}-other.npz', replace=replace)
            assert not response.success, response.message
            assert 'being learned by /learner' in response.message, response.message
        response = client.memory('add_sample', skill=TASK, tau=task.tau_default.tolist(),
                                 theta=policy_for(task).default_theta.tolist())
        assert not response.success and 'being learned' in response.message, response.message
    finally:
        result = client.learner.result(handle, timeout=300)
    assert result.success, result.message
    metrics = json.loads(open(result.metrics_path).read())
    held = json.loads(client.memory('info').message)[TASK]['num_samples']
    assert held == sum(r['fulfilled'] for r in metrics['tasks'])
    # the claim ended with the session: the load goes through now, saying what it replaced
    response = client.memory('load', path=f'{MINE}-other.npz', replace=True)
    assert response.success and f"replaced '{TASK}'" in response.message, response.message
    assert_the_graph_serves(graph, client, task)


# -- a live goal change: the safety check, and times outside the episode --------------------------
def live_update(client, task, goal, time_from_start):
    """A rollout of the default theta, with a goal update sent as soon as its episode is
    announced; (result, the references the controller tracked during it: its
    controller_state)."""
    from control_msgs.msg import JointTrajectoryControllerState
    from psl_msgs.msg import TaskInstance
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    references, episodes, announced = [], [], threading.Event()
    sub = client.node.create_subscription(
        JointTrajectoryControllerState, names.PSL_CONTROLLER_STATE,
        lambda m: references.append(list(m.reference.positions)),
        QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE))
    # the simulator's time now: the rollout's episode is the first announced at or after it
    # (the latched announcement of an earlier episode, if any, is older)
    now = call(client, ResetTask, names.RESET, task=TASK, mode='probe',
               tau=task.tau_default.tolist()).stamp
    now_ns = now.sec * 10**9 + now.nanosec

    def on_task(msg):
        if msg.stamp.sec * 10**9 + msg.stamp.nanosec >= now_ns and not msg.homing:
            episodes.append(msg)
            announced.set()
    task_sub = client.node.create_subscription(
        TaskInstance, names.TASK_INSTANCE, on_task,
        QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL))
    try:
        client.wait_for_subscribers([names.PSL_CONTROLLER_STATE, names.TASK_INSTANCE],
                                    subscriptions=[sub, task_sub])
        references.clear()
        results = []
        rollout = threading.Thread(target=lambda: results.append(client.rollout(
            TASK, task.tau_default, policy_for(task).default_theta, timeout=60)))
        rollout.start()
        try:
            assert announced.wait(30), 'the rollout\'s episode was not announced'
            client.update_goal(goal, time_from_start,
                               episode_ns=episodes[-1].stamp.sec * 10**9
                               + episodes[-1].stamp.nanosec)
        finally:
            rollout.join(timeout=90)
        assert results, 'the rollout did not end within 90 s'
        result = results[0]
        # every state's reference, also those still on their way
        deadline = time.monotonic() + 10.0
        while len(references) < result.evaluation.num_steps + 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(references) >= result.evaluation.num_steps + 1, \
            f'{len(references)} of the episode\'s {result.evaluation.num_steps + 1} references came'
        return result, np.asarray(references)
    finally:
        client.node.destroy_subscription(sub)
        client.node.destroy_subscription(task_sub)


def test_a_live_goal_outside_the_joint_range_is_refused_with_the_safety_reason(graph, client,
                                                                              task):
    from psl_task.arm_model import ArmModel
    from psl_task.safety_check import SafetyCheck
    check = SafetyCheck(ArmModel(task))            # the joint ranges less the safety margin
    goal = np.array([10.0, 0.0, 0.0])            # joint1 at 10 rad: far above its limit
    result, references = live_update(client, task, goal, 0.5)
    assert result.success, result.message
    assert 'refused by the safety check' in result.message and 'joint1' in result.message, \
        result.message
    assert result.evaluation.goal_change_time < 0                   # the goal did not change
    # the reference the controller tracked never left the joint ranges
    assert len(references) == result.evaluation.num_steps + 1      # every state answered
    assert np.all(references >= check.low) and np.all(references <= check.high)
    assert_the_graph_serves(graph, client, task)


@pytest.mark.parametrize('time_from_start', [1e308, math.inf, math.nan, -1.0, 1e4])
def test_a_live_goal_at_a_time_outside_the_episode_is_ignored_with_the_reason(
        graph, client, task, time_from_start):
    result, _ = live_update(client, task, task.goal_posture, time_from_start)
    assert result.success, result.message
    assert 'outside the episode' in result.message, result.message
    assert result.evaluation.goal_change_time < 0
    assert_the_graph_serves(graph, client, task)


# -- what one request may make the memory hold ------------------------------------------------
def test_a_sample_of_a_million_policy_parameters_is_refused_at_once(graph, client, task):
    before = client.memory('info').message
    response = client.memory('add_sample', timeout=60, skill='huge', tau=[0.5],
                             theta=[0.0] * 10**6)
    assert not response.success and 'max_theta_dim' in response.message, response.message
    assert client.memory('info').message == before
    for fields, bound in (({'skill': 'n' * 10**6, 'tau': [0.5], 'theta': [1.0]},
                           'max_name_length'),
                          ({'skill': 'wide', 'tau': [0.0] * 1000, 'theta': [1.0]},
                           'max_tau_dim')):
        response = client.memory('add_sample', timeout=60, **fields)
        assert not response.success and bound in response.message, response.message
    response = client.memory('create_skill', skill='vast', tau_low=[-1e308], tau_high=[1e308],
                             theta_reference=[0.0])
    assert not response.success and 'max_magnitude' in response.message, response.message
    assert client.memory('info').message == before
    assert_the_graph_serves(graph, client, task)


# -- torques from anyone ----------------------------------------------------------------------
def test_no_episode_starts_while_someone_else_publishes_torques(graph, client, task):
    """ROS 2 has no access control on topics and a message does not say who sent it: while a
    node besides the controller publishes on effort_command, no episode starts."""
    def reset():
        return call(client, ResetTask, names.RESET, task=TASK, tau=task.tau_default.tolist())

    def wait(condition, timeout=20.0) -> bool:
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)
        return True
    intruder = client.node.create_publisher(Float64MultiArray, names.EFFORT_COMMAND, RELIABLE)
    try:
        refusals = []
        assert wait(lambda: not refusals.append(reset()) and not refusals[-1].success), \
            'a reset started an episode beside a foreign torque publisher'
        assert 'besides the controller' in refusals[-1].message, refusals[-1].message
        # named, once ROS knows whose node the publisher is
        assert wait(lambda: client.node.get_fully_qualified_name() in reset().message)
        result = client.rollout(TASK, task.tau_default, policy_for(task).default_theta)
        assert not result.success and 'besides the controller' in result.message, \
            result.message
    finally:
        client.node.destroy_publisher(intruder)
    # once the simulator has seen it go, episodes start again: a rollout is no longer refused
    # (a refused one starts no episode; a bare sim/reset here would start a stray episode
    # the next rollout's trajectory could begin in)
    results = []
    assert wait(lambda: not results.append(client.rollout(
        TASK, task.tau_default, policy_for(task).default_theta, timeout=60))
        and 'besides the controller' not in results[-1].message, timeout=30.0), \
        results[-1].message
    assert results[-1].success and results[-1].evaluation.fulfilled, results[-1].message
    assert_the_graph_serves(graph, client, task)


# -- a generated family: every numeric and string field of every request ----------------------
def bad_requests(task):
    """(label, service type, name, fields) for every numeric and string field of the
    simulator's reset and the memory's services (the evaluator's goal_change holds none); a
    vector field of the reset's good request also gets the good vector with one bad entry
    (every BAD_NUMBERS value lies outside the task's tau ranges)."""
    good = {
        (ResetTask, names.RESET): dict(task=TASK, tau=task.tau_default.tolist()),
    }
    from psl_ros.client import MEMORY_SERVICES
    # a valid load replaces what the memory holds (an earlier test may have left a skill of
    # the file's name in it: without replace the load is refused, whatever the path)
    valid = {'load': dict(replace=True)}
    for service, srv in MEMORY_SERVICES.items():
        good[(srv, f'{names.SKILL_MEMORY}/{service}')] = valid.get(service, {})
    for (srv, name), fields in good.items():
        request = srv.Request()
        for field, kind in request.get_fields_and_field_types().items():
            if kind == 'string':
                for value in BAD_STRINGS:
                    yield f'{name}.{field}={value[:12]!r}', srv, name, {**fields, field: value}
            elif kind in ('double', 'float'):
                for value in BAD_NUMBERS:
                    yield f'{name}.{field}={value}', srv, name, {**fields, field: value}
            elif kind.startswith('sequence<double') or kind.startswith('sequence<float'):
                for value in ([], [math.nan], [math.inf] * 3, [1e308] * 3, [0.0] * 100000):
                    yield (f'{name}.{field}=[{len(value)} x {value[:1]}]', srv, name,
                           {**fields, field: value})
                # of the right length: one bad entry in a good value (first, then last)
                good = fields.get(field, [])
                for i in sorted({0, len(good) - 1}) if good else ():
                    for number in BAD_NUMBERS:
                        value = list(good)
                        value[i] = number
                        yield (f'{name}.{field}[{i}]={number}', srv, name,
                               {**fields, field: value})


# the generated requests the interfaces document as valid (every other one must be refused):
# the reset's default mode and duration, and a memory file by a name inside the memory folder
VALID = {f'{names.RESET}.mode=' + repr(''), f'{names.RESET}.duration=0.0',
         *(f'{names.SKILL_MEMORY}/{service}.path={name[:12]!r}'
           for service in ('save', 'load') for name in ('a/b\\c d', 'nö_ascii_✓'))}


def test_a_generated_family_of_bad_requests_leaves_every_node_serving(graph, client, task,
                                                                      memory_dir):
    """Every generated request is answered, the ones documented as valid accepted and every
    other one refused with a reason; no node dies, and the graph serves afterwards. The
    valid saves wrote into the graph's memory folder, the module's own."""
    # the one-bad-entry vectors are refused for that entry: no BAD_NUMBERS value is in range
    assert not any(low <= x <= high for x in BAD_NUMBERS
                   for low, high in zip(task.tau_low, task.tau_high))
    cases = list(bad_requests(task))
    assert VALID <= {label for label, *_ in cases}, VALID - {label for label, *_ in cases}
    for label, srv, name, fields in cases:
        try:
            response = call(client, srv, name, timeout=30, **fields)
        except TimeoutError as exc:
            raise AssertionError(f'{label}: no answer ({exc})') from None
        if label in VALID:
            assert response.success, f'{label}: refused ({response.message})'
        else:
            assert not response.success, f'{label}: accepted ({response.message})'
            assert response.message, f'{label}: refused without a reason'
        dead = [p.name for p in graph.processes if not pid_alive(p.pid)]
        assert not dead, f'{label} killed {dead}'
    assert (memory_dir / 'a' / 'b\\c d').is_file() and (memory_dir / 'nö_ascii_✓').is_file()
    assert_the_graph_serves(graph, client, task)
