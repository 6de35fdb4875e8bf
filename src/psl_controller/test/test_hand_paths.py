"""End-effector space: the joint path of a theta_K seen again is the one solved the first time.

`TaskPolicy._hand_path` keeps the last `HAND_PATHS_KEPT` joint paths by what determines them
(theta_K, the instance's duration and its number of steps). The references are compared with
those of a fresh policy (its own inverse kinematics, nothing kept): bit for bit, since the
solve is deterministic and a kept path is the very arrays of its first solve.
"""
from pathlib import Path

import numpy as np
import pytest
import yaml

from psl_controller import policy as policy_module
from psl_controller.policy import TaskPolicy
from psl_task.task import find_task_file, load_task


def assert_same_reference(actual, desired):
    for field in ('t', 'q', 'qd', 'u_ffwd'):
        np.testing.assert_array_equal(getattr(actual, field), getattr(desired, field))


def thetas_of(policy, count, seed=0):
    rng = np.random.default_rng(seed)
    default = policy.default_theta
    return default + rng.normal(0.0, 0.02, (count, default.size))


def test_a_theta_k_seen_again_reuses_its_joint_path_and_its_feedforward_is_new():
    task = load_task('point_reach_3d')
    policy, fresh = TaskPolicy(task), TaskPolicy(task)
    theta = thetas_of(policy, 1)[0]
    first = policy.reference(theta)
    assert (policy.ik_paths, policy.ik_reused) == (1, 0)
    other_torque = policy.with_feedforward(theta, np.linspace(-1.0, 1.0,
                                                              policy.feedforward.num_parameters))
    again = policy.reference(other_torque)
    assert (policy.ik_paths, policy.ik_reused) == (1, 1)
    assert again.q is first.q                          # the path kept, not solved again
    assert not np.array_equal(again.u_ffwd, first.u_ffwd)
    assert_same_reference(again, fresh.reference(other_torque))
    assert not again.q.flags.writeable and not again.t.flags.writeable


def test_another_theta_k_is_solved_and_the_oldest_path_is_dropped():
    task = load_task('point_reach_3d')
    policy, fresh = TaskPolicy(task), TaskPolicy(task)
    kept = policy_module.HAND_PATHS_KEPT
    thetas = thetas_of(policy, kept + 1, seed=1)
    for theta in thetas:
        policy.reference(theta)
    assert (policy.ik_paths, policy.ik_reused) == (kept + 1, 0)
    # the newest are kept; the first was dropped to make room and is solved again
    assert_same_reference(policy.reference(thetas[-1]), fresh.reference(thetas[-1]))
    assert (policy.ik_paths, policy.ik_reused) == (kept + 1, 1)
    assert_same_reference(policy.reference(thetas[0]), fresh.reference(thetas[0]))
    assert (policy.ik_paths, policy.ik_reused) == (kept + 2, 1)


def test_a_kept_path_is_not_taken_for_another_duration(tmp_path: Path):
    source = find_task_file('point_reach_3d')
    data = yaml.safe_load(source.read_text())
    data['model'] = str(source.parent / data['model'])
    data['task_parameters'].append({'name': 'duration', 'unit': 's', 'low': 0.8, 'high': 1.2,
                                    'binds': {'kind': 'duration'}})
    path = tmp_path / 'point_reach_timed.yaml'
    path.write_text(yaml.safe_dump(data))
    task = load_task(str(path))
    policy, fresh = TaskPolicy(task), TaskPolicy(task)
    theta = thetas_of(policy, 1, seed=2)[0]
    base = np.array([0.42, 0.0, -0.1, 1.0])
    for duration in (1.0, 0.8, 1.2, 1.0):
        tau = base.copy()
        tau[3] = duration
        assert_same_reference(policy.reference(theta, tau), fresh.reference(theta, tau))
    assert (policy.ik_paths, policy.ik_reused) == (3, 1)


@pytest.mark.parametrize('name', ['point_reach_3d', 'pose_reach_3d'])
def test_a_population_with_repeated_rows_equals_each_row_alone(name):
    task = load_task(name)
    policy, fresh = TaskPolicy(task), TaskPolicy(task)
    thetas = thetas_of(policy, 3, seed=4)
    thetas = np.concatenate([thetas, thetas[::-1]])
    taus = np.array([task.tau_default] * len(thetas))
    references = policy.references(thetas, taus)
    assert (policy.ik_paths, policy.ik_reused) == (3, 3)
    for reference, theta, tau in zip(references, thetas, taus):
        assert_same_reference(reference, fresh.reference(theta, tau))
