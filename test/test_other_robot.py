"""A robot the code was not written for: the 4-joint arm of the embedded task reach_4dof, in
batch mode, through the graph (separate processes over DDS) and in a short learning session."""
import numpy as np
import pytest
import yaml

from psl_controller.policy import policy_for
from psl_memory.parameterized_skill import scaler_around
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.policy_search import SearchSettings, search
from psl_task.arm_model import ArmModel
from psl_task.task import load_task

TASK = 'reach_4dof'
JOINTS = ['waist', 'shoulder', 'elbow', 'wrist']     # reach_4dof.xml, in actuator order
TORQUE_LIMITS = [30.0, 50.0, 25.0, 8.0]              # its ctrlranges, copied by hand
LEARN = LearnSettings(strategy='bootstrap', num_tasks=12, seed=2, num_test=30,
                      search=SearchSettings(max_rollouts=100))


@pytest.fixture(scope='module')
def graph_task():
    """The module's graph (conftest) runs the 4-joint robot."""
    return TASK


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


@pytest.fixture(scope='module')
def batch(task):
    return BatchRollouts(task)


def rewards_of(batch, thetas, taus):
    results = batch.run(thetas, taus)
    return (np.array([r.evaluation.reward for r in results]),
            np.array([r.evaluation.fulfilled for r in results]))


def task_grid(task, n=7):
    """n x n instances spanning the task space, corners included."""
    axes = [np.linspace(lo, hi, n) for lo, hi in zip(task.tau_low, task.tau_high)]
    return np.array(np.meshgrid(*axes)).reshape(len(axes), -1).T


def test_the_four_joint_task_loads(task):
    arm = ArmModel(task)
    assert task.n_joints == 4 and arm.joint_names == JOINTS
    assert task.tau_names == ['post_x', 'post_y']
    np.testing.assert_array_equal(arm.torque_high, TORQUE_LIMITS)
    assert task.control_period == pytest.approx(0.004)
    assert policy_for(task).num_parameters == 4 * task.policy.n_basis
    reference = policy_for(task).reference(policy_for(task).default_theta)
    assert reference.q.shape == (task.num_steps + 1, 4)


def test_batch_mode_runs_a_population(task, batch):
    rng = np.random.default_rng(0)
    default = batch.policy.default_theta
    thetas = default + rng.normal(0.0, 0.1 * np.abs(default).max(), (10, default.size))
    taus = np.array([task.sample_tau(rng) for _ in range(10)])
    results = batch.run(thetas, taus)
    assert len(results) == 10
    for result in results:
        assert result.q.shape == result.torque.shape == (task.num_steps + 1, 4)
        assert np.all(np.isfinite(result.q)) and np.isfinite(result.evaluation.reward)
        assert np.all(np.abs(result.torque) <= np.array(TORQUE_LIMITS) + 1e-12)
    assert len({r.evaluation.reward for r in results}) == 10


def test_the_demonstration_fulfils_some_instances_but_not_all(task, batch):
    taus = task_grid(task)
    _, fulfilled = rewards_of(batch, np.tile(batch.policy.default_theta, (len(taus), 1)), taus)
    assert 0.2 < fulfilled.mean() < 0.8
    # the start and the goal posture are clear of the post everywhere: no instance is lost
    # before the motion starts
    for tau in taus:
        distance = batch.geometry.replay(np.array([[task.start_posture, task.goal_posture]]),
                                         np.asarray(tau)[None]).distance
        assert distance.min() > task.reward.clearance_margin


@pytest.mark.parametrize('corner', [(0, 0), (0, 1), (1, 0), (1, 1), (0.5, 0.5)])
def test_cma_es_solves_the_corners_of_the_task_space(task, batch, corner):
    tau = task.tau_low + np.array(corner) * (task.tau_high - task.tau_low)
    default = batch.policy.default_theta
    scaler = scaler_around(default)
    result = search('scratch', lambda thetas: rewards_of(batch, thetas, np.tile(
                        tau, (len(thetas), 1))),
                    tau, default, lambda _: default, 0.5 * (scaler.high + scaler.low),
                    0.5 * (scaler.high - scaler.low), task.tau_low, task.tau_high,
                    SearchSettings(max_rollouts=200), seed=1)
    assert result.fulfilled, f'no solution for tau={tau.tolist()} in 200 rollouts'


def test_graph_and_batch_mode_agree_on_the_four_joint_arm(graph_matches_batch, task):
    rng = np.random.default_rng(11)
    theta = policy_for(task).default_theta
    perturbed = theta + rng.normal(0.0, 0.1 * np.abs(theta).max(), theta.size)
    evaluation, batch_result = graph_matches_batch(task, task.sample_tau(rng), perturbed)
    assert evaluation.task == TASK and evaluation.num_steps == task.num_steps
    assert np.any(batch_result.q[-1] != batch_result.q[0])


def test_a_task_yaml_outside_the_search_path_runs_in_the_graph(graph_matches_batch, task,
                                                              tmp_path):
    """A user's task file elsewhere, its model given by absolute path: every node loads it
    from the path the simulator announces (its name finds no file on the search path)."""
    data = yaml.safe_load(task.path.read_text())
    data.update(name='my_robot_task', model=str(task.model_path))
    data['reward'] = dict(data['reward'], success_threshold=-0.5)
    path = tmp_path / 'my_robot_task.yaml'
    path.write_text(yaml.safe_dump(data))
    mine = load_task(str(path))
    evaluation, _ = graph_matches_batch(mine, mine.tau_default, policy_for(mine).default_theta)
    assert evaluation.task == str(path.resolve())


def test_the_graph_refuses_a_task_of_another_robot(client, task):
    """The graph runs the 4-joint arm; a rollout of the 3-joint task fails at once with the
    reason, and the graph goes on serving its own task."""
    other = load_task('reach_over_obstacle')
    result = client.rollout('reach_over_obstacle', other.tau_default,
                            policy_for(other).default_theta, timeout=30)
    assert not result.success
    assert 'joints' in result.message and 'waist' in result.message, result.message
    good = client.rollout(TASK, task.tau_default, policy_for(task).default_theta)
    assert good.success, good.message


def test_a_short_learning_session_improves_over_the_demonstration(task, batch, tmp_path):
    metrics = Learner(task, LEARN, tmp_path, batch).run().to_dict()
    assert metrics['complete']
    assert all(record['fulfilled'] for record in metrics['tasks'])
    summary = metrics['summary']
    test = np.array(summary['test_taus'])
    demo_rewards, demo_fulfilled = rewards_of(
        batch, np.tile(batch.policy.default_theta, (len(test), 1)), test)
    assert summary['zero_shot_success_rate'] > demo_fulfilled.mean()
    assert summary['zero_shot_mean_reward'] > demo_rewards.mean()
