"""The pose DMP in graph mode: pose_reach_3d (the hand's position and orientation DMPs, the
six-dimensional inverse kinematics, ILC turning the goal orientation) through the graph's
processes in lockstep; the same rollouts in batch mode agree."""
import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_task.task import EMBEDDED_TASKS, load_task


@pytest.fixture(scope='module')
def graph_task():
    return str(EMBEDDED_TASKS / 'pose_reach_3d.yaml')


@pytest.mark.parametrize('tau', [[0.44, 0.06, -0.08, 3.25], [0.37, -0.1, -0.18, 2.8]])
def test_a_pose_task_runs_in_the_graph_as_in_batch_mode(graph_matches_batch, graph_task, tau):
    """Instances with the yaw turned either way, a perturbed theta: the executor's reference
    and batch mode's are the same, so the rollouts and every reward component, the
    orientation error included, agree."""
    task = load_task(graph_task)
    policy = policy_for(task)
    rng = np.random.default_rng(int(100 * tau[0]))
    theta = policy.default_theta + rng.normal(0.0, 0.01, policy.num_parameters)
    evaluation, batch = graph_matches_batch(task, np.array(tau), theta)
    assert evaluation.num_steps == task.num_steps_of(np.array(tau))
    assert batch.evaluation.components['orientation_error'] > 0.05    # the yaw is not the default


def test_a_pose_goal_change_is_scored_against_the_new_orientation(client, graph_task):
    """A new goal of 7 values (the point and the hand's orientation) from 0.3 s, known before
    the start: the executor's reference is the policy's with the change, bit for bit, and the
    evaluator scores the hand's final orientation against the new one (the angle computed
    here from the measured joints by MuJoCo)."""
    import mujoco

    from psl_task import quaternion
    from psl_task.arm_model import ArmModel
    from psl_task.task import task_id
    task = load_task(graph_task)
    policy = policy_for(task)
    theta = policy.default_theta
    policy.movement.set_theta(theta[policy.kinematics])
    turned = quaternion.product(quaternion.exp_map([0.0, 0.0, 0.25]),
                                policy.movement.orientation.goal)
    goal = np.concatenate([policy.movement.position.goal, turned])
    result = client.rollout(task_id(task), task.tau_default, theta, new_goal=goal,
                            new_goal_time=0.3)
    assert result.success, result.message
    ev = result.evaluation
    n = task.n_joints
    q = np.array(ev.position).reshape(-1, n)
    q_ref = np.array(ev.reference_position).reshape(-1, n)
    expected = policy.reference_with_new_goal(theta, task.tau_default, ev.goal_change_time, goal)
    np.testing.assert_array_equal(q_ref, expected.q)
    arm = ArmModel(task)

    def angle_to_turned(joints):
        arm.data.qpos[arm.qpos_adr] = joints
        mujoco.mj_kinematics(arm.model, arm.data)
        hand = np.empty(4)
        mujoco.mju_mat2Quat(hand, arm.data.site_xmat[arm.ee_site])
        return np.linalg.norm(quaternion.log_map(quaternion.product(
            turned, quaternion.conjugate(hand))))
    components = dict(zip(ev.component_names, ev.component_values))
    assert components['orientation_error'] == pytest.approx(angle_to_turned(q[-1]), abs=1e-6)
    # the commanded hand turned to the new orientation (0.25 rad from the old one); the
    # measured one follows it up to the tracking error of the default theta (no feed-forward)
    assert angle_to_turned(q_ref[-1]) < 5e-3
    assert angle_to_turned(q[-1]) < 0.125
