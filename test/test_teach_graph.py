"""psl teach from a bag psl record wrote of rollouts through the graph (as a person's guided
demonstrations would be recorded: the robot's joint states and the episodes psl announced):
planar_10dof_reach, three movements of known theta on known instances; psl teach --episodes
takes each episode with its tau, and the skill's samples reproduce the movements; cut from
rest to rest, the drives back to the start are skipped and each motion gets its instance."""
import threading
import time

import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_memory.skill_memory import SkillMemory
from psl_ros import names
from psl_ros.bag_recorder import record
from psl_task.task import EMBEDDED_TASKS, load_task, task_id

TOL_TAUGHT = 0.05           # rad, the taught movement against the commanded one: the
                            # demonstration is what the joints measured (the PD's lag in it)


@pytest.fixture(scope='module')
def graph_task():
    return str(EMBEDDED_TASKS / 'planar_10dof_reach.yaml')


@pytest.fixture(scope='module')
def graph_options():
    """Drive resets: the arm is driven back to the start between two episodes (homing
    episodes, announced as such), as a person brings it back between two demonstrations."""
    return {'reset': 'drive'}


def test_rollouts_recorded_from_the_graph_teach_the_skill(client, graph_task, tmp_path,
                                                         capsys):
    from psl_cli.main import main
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
    bag = tmp_path / 'guided'
    stop, counts = threading.Event(), {}
    recorder = threading.Thread(target=record, args=(bag, [names.JOINT_STATES,
                                                           names.TASK_INSTANCE]),
                                kwargs={'stop': stop, 'discovery_timeout': 2.0,
                                        'progress': lambda r: counts.update(r.counts)},
                                daemon=True)
    recorder.start()
    try:
        client.wait_for_subscribers([names.JOINT_STATES])
        for tau, theta in zip(taus, thetas):
            result = client.rollout(task_id(task), tau, theta)
            assert result.success, result.message
        steps = 3 * (task.num_steps_of(None) + 1)
        deadline = time.monotonic() + 10.0
        while (counts.get('/' + names.JOINT_STATES, 0) < steps
               and time.monotonic() < deadline):
            stop.wait(0.01)
        assert counts.get('/' + names.JOINT_STATES, 0) >= steps, \
            f'the recorder has {counts} of the episodes\' {steps} joint states'
    finally:
        stop.set()
        recorder.join(timeout=30)
    assert not recorder.is_alive(), 'the recorder did not end within 30 s'
    memory = tmp_path / 'taught.npz'
    assert main(['teach', '--task', graph_task, str(bag), '--episodes',
                 '--tau-topic', '/' + names.TASK_INSTANCE, '-o', str(memory)]) == 0
    out = capsys.readouterr().out
    assert out.count('accepted') == 3, out
    # cut from rest to rest instead: the drives back to the start are no demonstrations, each
    # motion's instance is the one psl announced for it
    by_motion = tmp_path / 'by_motion.npz'
    assert main(['teach', '--task', graph_task, str(bag), '--tau-topic',
                 '/' + names.TASK_INSTANCE, '-o', str(by_motion)]) == 0
    out = capsys.readouterr().out
    assert out.count('accepted') == 3 and 'refused' not in out, out
    # three drives to the start: from where the simulator starts the arm, and after each of
    # the first two episodes
    assert out.count('brought back to the start posture') == 3, out
    np.testing.assert_array_equal(SkillMemory.read(by_motion).get(task.name).taus,
                                  np.array([t.tolist() for t in taus]))
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
