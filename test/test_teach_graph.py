"""psl teach from a bag psl record wrote of rollouts through the graph (as a person's guided
demonstrations would be recorded: the robot's joint states and the episodes psl announced):
planar_10dof_reach, movements on known instances. The documented line (--tau-topic
/task_instance, no --episodes) takes each episode psl announced with its tau, the same samples
as --episodes: with the task's teleport reset (what psl up gives a new user), where cutting
from rest to rest cannot separate the episodes, and with drive resets, where it can (the drives
back to the start skipped, each motion given its instance)."""
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_memory.skill_memory import SkillMemory
from psl_optimizer.learning import LearnSettings
from psl_ros import names
from psl_ros.bag_recorder import record
from psl_task.task import EMBEDDED_TASKS, load_task, task_id

TOL_TAUGHT = 0.05           # rad, the taught movement against the commanded one: the
                            # demonstration is what the joints measured (the PD's lag in it)
TEACH = [sys.executable, '-m', 'psl_cli.main', 'teach']


@pytest.fixture(scope='module')
def graph_task():
    return str(EMBEDDED_TASKS / 'planar_10dof_reach.yaml')


@pytest.fixture
def reset(client):
    """Set the executor's reset (its dynamic parameter, as ``ros2 param set /dmp_executor
    reset drive`` would); the task's own (teleport) again afterwards."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    service = client.node.create_client(SetParameters, 'dmp_executor/set_parameters')

    def set_reset(mode: str) -> None:
        request = SetParameters.Request(parameters=[Parameter(name='reset', value=ParameterValue(
            type=ParameterType.PARAMETER_STRING, string_value=mode))])
        assert service.wait_for_service(timeout_sec=10)
        response = client.wait(service.call_async(request), 10, 'set_parameters')
        assert all(r.successful for r in response.results), response.results
    try:
        yield set_reset
    finally:
        set_reset('')
        client.node.destroy_client(service)


def record_rollouts(client, task, bag, rollouts, topics=()):
    """Record `topics` (none: every topic, as psl record does) into `bag` while the graph runs
    each (tau, theta) of `rollouts`, the next once the recorder has taken the episode's
    announcement (as a person types one rollout after the other); returns once the recorder
    has taken every joint state the simulator published (as many as a subscription of this
    client matched with it saw, up to the last episode's end) and ended. psl announces
    episodes on a latched topic of depth 1: an announcement the recorder has not taken when
    the next one is published is lost (the recorder counts it), as a homing episode's may be
    to its primitive's. The graph has run an episode before: its announcement, the recorder's
    first (taken or lost), shows the recorder matched the announcing executor."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    from psl_msgs.msg import TaskInstance

    stop, counts, lost, seen, announced = threading.Event(), {}, {}, [], []
    states, instances = '/' + names.JOINT_STATES, '/' + names.TASK_INSTANCE

    def stamp_ns(stamp) -> int:
        return stamp.sec * 10**9 + stamp.nanosec

    def progress(recording) -> None:
        counts.update(recording.counts)
        lost.update(recording.lost)
    subs = [client.node.create_subscription(
                JointState, names.JOINT_STATES, lambda m: seen.append(stamp_ns(m.header.stamp)),
                QoSProfile(depth=20000, reliability=ReliabilityPolicy.RELIABLE)),
            client.node.create_subscription(       # latched, as the recorder subscribes
                TaskInstance, names.TASK_INSTANCE, lambda m: announced.append(stamp_ns(m.stamp)),
                QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL))]
    recorder = threading.Thread(target=record, args=(bag, list(topics)),
                                kwargs={'stop': stop, 'progress': progress},  # psl record's
                                daemon=True)                                  # discovery time
    recorder.start()

    def wait(condition, what: str, timeout: float = 15.0) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            assert recorder.is_alive() and time.monotonic() < deadline, \
                f'{what} (the recorder has {counts}, lost {lost}; this client has ' \
                f'{len(seen)} joint states and {len(announced)} announcements)'
            stop.wait(0.01)

    def recorded() -> bool:         # every announcement this client saw taken or lost
        return counts.get(instances, 0) + lost.get(instances, 0) >= len(announced)
    try:
        wait(lambda: {states, instances} <= counts.keys(), 'the recorder did not subscribe',
             30.0)
        # matched with the simulator, which publishes only in episodes: from here on the
        # recorder takes what this client's subscription sees
        client.wait_for_subscribers([names.JOINT_STATES], extra=2, subscriptions=subs[:1])
        wait(lambda: announced and recorded(), 'no announcement of an episode before')
        for tau, theta in rollouts:
            result = client.rollout(task_id(task), tau, theta)
            assert result.success, result.message
            start = stamp_ns(result.evaluation.stamp)
            wait(lambda: start in announced and recorded(),
                 'the episode\'s announcement did not come')
        end = start + task.num_steps_of(tau) * task.control_period_ns
        wait(lambda: seen and seen[-1] >= end and counts.get(states, 0) >= len(seen),
             'the last episode\'s joint states did not come')
        assert counts.get(states, 0) == len(seen), \
            f'the recorder took {counts.get(states, 0)} of the {len(seen)} joint states'
    finally:
        stop.set()
        recorder.join(timeout=30)
        for sub in subs:
            client.node.destroy_subscription(sub)
    assert not recorder.is_alive(), 'the recorder did not end within 30 s'


def samples(memory_file, task):
    skill = SkillMemory.read(memory_file).get(task.name)
    return skill.taus, skill.thetas


def test_the_documented_line_teaches_rollouts_psl_record_recorded(client, graph_task,
                                                                  tmp_path, capsys):
    """A new user's session: the graph of the task (its teleport reset), a rollout tried,
    then psl record of every topic while three rollouts run (the default theta, as psl
    rollout --tau X Y sends it), then the documented line as typed. Each episode is a
    demonstration, accepted with its tau: the same samples as --episodes gives; the episode
    before the recording (its announcement is latched, so the bag holds it) is said and
    skipped, no motion is outside the episodes; one line on stderr says the bag was cut by
    its episodes."""
    from psl_cli.main import main
    task = load_task(graph_task)
    policy = policy_for(task)
    theta = policy.default_theta
    result = client.rollout(task_id(task), np.array([0.55, 0.25]), theta)
    assert result.success, result.message
    taus = [np.array([0.5, 0.2]), np.array([0.62, 0.35]), np.array([0.45, 0.1])]
    record_rollouts(client, task, tmp_path / 'demos', [(tau, theta) for tau in taus])
    documented = subprocess.run(TEACH + ['--task', 'planar_10dof_reach', 'demos/',
                                         '--tau-topic', '/task_instance', '-o', 'taught.npz'],
                                cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert documented.returncode == 0, documented.stdout + documented.stderr
    out = documented.stdout
    assert out.count('accepted') == 3 and 'refused' not in out, out
    # the latched announcement of the rollout before (unless the recorder lost it to the
    # first one's, see record_rollouts)
    assert out.count('no demonstration (not wholly in the recording') <= 1, out
    assert 'in no episode announced' not in out, out
    said = documented.stderr.strip().splitlines()
    assert len(said) == 1 and 'announces psl\'s episodes' in said[0], documented.stderr
    assert main(['teach', '--task', 'planar_10dof_reach', str(tmp_path / 'demos'),
                 '--episodes', '--tau-topic', '/task_instance',
                 '-o', str(tmp_path / 'forced.npz')]) == 0
    forced = capsys.readouterr()
    assert forced.out == out.replace('taught.npz', str(tmp_path / 'forced.npz'))
    assert 'announces' not in forced.err
    taught_taus, taught_thetas = samples(tmp_path / 'taught.npz', task)
    forced_taus, forced_thetas = samples(tmp_path / 'forced.npz', task)
    np.testing.assert_array_equal(taught_taus, np.array([t.tolist() for t in taus]))
    np.testing.assert_array_equal(taught_taus, forced_taus)
    np.testing.assert_array_equal(taught_thetas, forced_thetas)
    for tau, taught in zip(taus, taught_thetas):
        np.testing.assert_allclose(policy.reference(taught, tau).q,
                                   policy.reference(theta, tau).q, rtol=0, atol=TOL_TAUGHT)


def test_rollouts_with_drive_resets_teach_the_skill(client, graph_task, reset, tmp_path,
                                                    capsys):
    """Drive resets: the arm is driven back to the start between two episodes (homing
    episodes, announced as such), as a person brings it back between two demonstrations.
    Three movements of known theta: the documented line takes each episode with its tau (the
    homing episodes said and skipped), as --episodes does, and the skill's samples reproduce
    the movements; cut from rest to rest (the library, as psl bench teach does), the drives
    back to the start are skipped and each motion gets the instance psl announced for it."""
    from psl_cli.main import main
    from psl_optimizer import teaching
    from psl_ros.bag_recorder import make_typestore
    from psl_task.arm_model import joint_names_of
    task = load_task(graph_task)
    policy = policy_for(task)
    rng = np.random.default_rng(2)
    taus = [np.array([0.5, 0.2]), np.array([0.62, 0.35]), np.array([0.45, 0.1])]
    default = policy.reference(policy.default_theta).q
    # the default's weights and goal moved: each movement more than twice the tolerance from
    # the default's (which would not pass for it)
    thetas = []
    for tau in taus:
        theta = policy.default_theta.copy()
        scale = np.abs(theta[:policy.goal.start]).max()
        theta[:policy.goal.start] += rng.normal(0.0, 0.05 * scale, policy.goal.start)
        theta[policy.goal] += rng.normal(0.0, 0.1, policy.goal.stop - policy.goal.start)
        assert np.abs(policy.reference(theta, tau).q - default).max() > 2 * TOL_TAUGHT
        thetas.append(theta)
    result = client.rollout(task_id(task), taus[0], policy.default_theta)     # one before
    assert result.success, result.message
    reset('drive')
    bag = tmp_path / 'guided'
    record_rollouts(client, task, bag, list(zip(taus, thetas)),
                    [names.JOINT_STATES, names.TASK_INSTANCE])
    documented = tmp_path / 'documented.npz'
    assert main(['teach', '--task', graph_task, str(bag), '--tau-topic',
                 '/' + names.TASK_INSTANCE, '-o', str(documented)]) == 0
    said = capsys.readouterr()
    assert said.out.count('accepted') == 3 and 'refused' not in said.out, said.out
    # three drives to the start, from the goal of the episode before: each homing episode
    # whose announcement the bag holds is said; one whose announcement the recorder lost to
    # its primitive's (see record_rollouts) is a motion in no announced episode
    homing = sum(a.homing for a in teaching.read_announcements(
        bag, '/' + names.TASK_INSTANCE, make_typestore()))
    assert said.out.count('no demonstration (a homing episode') == homing, said.out
    assert said.out.count('in no episode announced') <= max(0, 3 - homing), said.out
    assert 'announces psl\'s episodes' in said.err
    memory = tmp_path / 'taught.npz'
    assert main(['teach', '--task', graph_task, str(bag), '--episodes',
                 '--tau-topic', '/' + names.TASK_INSTANCE, '-o', str(memory)]) == 0
    assert capsys.readouterr().out == said.out.replace(str(documented), str(memory))
    for got, want in zip(samples(documented, task), samples(memory, task)):
        np.testing.assert_array_equal(got, want)
    # cut from rest to rest instead: the drives back to the start are no demonstrations, each
    # motion's instance is the one psl announced for it
    recording = teaching.read_joint_states(bag, '/' + names.JOINT_STATES,
                                           joint_names_of(task))
    spans, returns = teaching.split_returns(task, recording, teaching.rest_to_rest(recording))
    assert len(spans) == 3 and len(returns) == 3
    by_motion = teaching.taus_from_topic(teaching.read_announcements(
        bag, '/' + names.TASK_INSTANCE, make_typestore()), recording, spans)
    np.testing.assert_array_equal(by_motion, np.array([t.tolist() for t in taus]))
    outcomes = teaching.teach(task, recording, spans, by_motion,
                              SkillMemory(LearnSettings().skill))
    assert all(o.accepted for o in outcomes), [o.reason for o in outcomes]
    skill = SkillMemory.read(memory).get(task.name)
    assert skill.num_samples == 3
    taught = sorted(zip(skill.taus.tolist(), skill.thetas), key=lambda s: s[0])
    for (tau, theta_taught), (tau_given, theta) in zip(taught, sorted(
            zip([t.tolist() for t in taus], thetas), key=lambda s: s[0])):
        assert tau == tau_given
        np.testing.assert_allclose(policy.reference(theta_taught, np.array(tau)).q,
                                   policy.reference(theta, np.array(tau)).q, rtol=0,
                                   atol=TOL_TAUGHT)
        # which is far from what the default theta moves
        assert np.abs(policy.reference(theta_taught, np.array(tau)).q - default).max() \
            > TOL_TAUGHT
