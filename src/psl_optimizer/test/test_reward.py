"""Tests of the reward: each cost component on hand-made data with known answers (one rollout
as a population of one, and a population against its members), the weighted score, and the
task's Reward on the embedded task against closed-form kinematics."""

import numpy as np
import pytest

from psl_controller.policy import TaskPolicy
from psl_optimizer.reward import (COMPONENTS, Reward, check_weights, clearance, effort, goal_error,
                                  penetration, score, smoothness, tracking_error)
from psl_task.arm_model import ArmModel
from psl_task.reward_geometry import RewardGeometry
from psl_task.task import load_task

TOL = 1e-12             # hand-computed numbers
TOL_SMOOTH = 1e-6       # relative: second difference of a sampled parabola (rounding / dt^4)
TOL_LINEAR = 1e-12      # rad^2/s^4, rounding of second differences of a line (~1e-23)
TOL_FK = 1e-12          # m, MuJoCo kinematics vs closed form
DEMO_GOAL_ERROR = 1e-3  # m, the fitted demonstration ends at the goal

LINKS = np.array([0.5, 0.5, 0.3])   # reach_over_obstacle.xml, copied by hand
ARM_RADIUS, OBSTACLE_RADIUS, OBSTACLE_LENGTH = 0.025, 0.04, 0.4


def one(component, *arrays, **options):
    """A component on one rollout: its arrays as a population of one, the one cost back."""
    return component(*[np.asarray(a, dtype=float)[None] for a in arrays], **options)[0]


def planar_fk(q):
    """Closed form for the planar arm with hinges about -y: phi_i = q_1 + ... + q_i,
    x = sum l_i cos phi_i, z = sum l_i sin phi_i."""
    phi = np.cumsum(q)
    return np.array([np.sum(LINKS * np.cos(phi)), 0.0, np.sum(LINKS * np.sin(phi))])


# -- goal_error -------------------------------------------------------------------------------
def test_goal_error_3_4_5():
    goal = np.array([0.2, -0.1, 0.7])
    assert one(goal_error, goal + [3.0, 4.0, 0.0], goal) == pytest.approx(5.0, abs=TOL)
    assert one(goal_error, goal + [0.0, -0.3, 0.4], goal) == pytest.approx(0.5, abs=TOL)
    assert one(goal_error, [2.0, 3.0, 6.0], [0.0, 0.0, 0.0]) == pytest.approx(7.0, abs=TOL)
    assert one(goal_error, goal, goal) == 0.0


@pytest.mark.parametrize('final, goal', [
    ([np.nan, 0, 0], [0, 0, 0]), ([0, 0, 0], [0, np.inf, 0])])
def test_goal_error_rejects_non_finite(final, goal):
    with pytest.raises(ValueError, match='finite'):
        one(goal_error, final, goal)


def test_goal_error_rejects_incompatible_shapes():
    with pytest.raises(ValueError):
        one(goal_error, [1.0, 2.0, 3.0], [1.0, 2.0])


@pytest.mark.parametrize('final, goal', [
    ([3.0, 4.0, 0.0], [0.0]), ([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]], [0.0, 0.0, 0.0])])
def test_goal_error_rejects_broadcastable_shape_mismatch(final, goal):
    with pytest.raises(ValueError):
        goal_error(final, goal)            # as given: no population axis, or one goal for two


# -- penetration ------------------------------------------------------------------------------
def test_penetration_is_deepest_negative_distance():
    assert one(penetration, [0.1, -0.03, -0.01, 0.2]) == pytest.approx(0.03, abs=TOL)
    assert one(penetration, [-0.5]) == pytest.approx(0.5, abs=TOL)


def test_penetration_zero_when_clear():
    assert one(penetration, [0.1, 0.02, 0.3]) == 0.0
    assert one(penetration, [0.0, 0.5]) == 0.0          # touching is not penetrating


def test_penetration_rejects_empty():
    with pytest.raises(ValueError, match='empty'):
        one(penetration, [])


def test_penetration_rejects_nan():
    with pytest.raises(ValueError):
        one(penetration, [0.1, np.nan, -0.2])


# -- clearance --------------------------------------------------------------------------------
def test_clearance_mean_shortfall():
    # margin 0.02: shortfalls 0, 0.01, 0.04, 0 -> mean 0.0125
    assert one(clearance, [0.05, 0.01, -0.02, 0.03], margin=0.02) == pytest.approx(0.0125,
                                                                                abs=TOL)
    # margin 0: only penetration counts, mean over all samples: (0 + 0.1) / 2
    assert one(clearance, [0.3, -0.1], margin=0.0) == pytest.approx(0.05, abs=TOL)


def test_clearance_zero_when_beyond_margin():
    assert one(clearance, [0.05, 0.02, 1.0], margin=0.02) == 0.0


@pytest.mark.parametrize('distance, margin, message', [
    ([0.1], -0.01, 'margin'), ([], 0.02, 'empty')])
def test_clearance_rejects_bad_input(distance, margin, message):
    with pytest.raises(ValueError, match=message):
        one(clearance, distance, margin=margin)


@pytest.mark.parametrize('distance, margin', [([0.1, np.nan], 0.02), ([0.1, 0.0], np.nan)])
def test_clearance_rejects_nan(distance, margin):
    with pytest.raises(ValueError):
        one(clearance, distance, margin=margin)


# -- smoothness -------------------------------------------------------------------------------
def test_smoothness_of_parabola_is_acceleration_squared():
    dt = 0.002
    t = np.arange(200) * dt
    accel = np.array([2.0, -3.0, 0.5])                  # rad/s^2 per joint
    q = 0.5 * t[:, None] ** 2 * accel + np.array([0.1, -0.4, 1.2])   # (T, 3)
    expected = np.mean(accel**2)                        # (4 + 9 + 0.25) / 3
    assert one(smoothness, q, dt=dt) == pytest.approx(expected, rel=TOL_SMOOTH)


def test_smoothness_of_linear_trajectory_is_zero():
    dt = 0.01
    t = np.arange(50) * dt
    q = np.column_stack([1.0 + 2.0 * t, -0.5 * t])
    assert one(smoothness, q, dt=dt) == pytest.approx(0.0, abs=TOL_LINEAR)
    assert one(smoothness, np.ones((10, 2)), dt=dt) == 0.0


def test_smoothness_by_hand():
    # second differences of [0, 1, 0, 0] are [-2, 1]; dt = 0.5 -> accel [-8, 4]; mean 40
    assert one(smoothness, np.array([[0.0], [1.0], [0.0], [0.0]]), dt=0.5) == pytest.approx(
        40.0, abs=TOL)


@pytest.mark.parametrize('dt', [0.0, -0.002])
def test_smoothness_rejects_non_positive_dt(dt):
    with pytest.raises(ValueError, match='dt'):
        one(smoothness, np.zeros((5, 2)), dt=dt)


def test_smoothness_rejects_nan():
    q = np.zeros((5, 2))
    q[2, 1] = np.nan
    with pytest.raises(ValueError, match='finite'):
        one(smoothness, q, dt=0.002)


# -- effort -----------------------------------------------------------------------------------
def test_effort_mean_square():
    assert one(effort, np.array([[1.0, 2.0], [3.0, -4.0]])) == pytest.approx(7.5, abs=TOL)
    assert one(effort, np.full((4, 3), -2.0)) == pytest.approx(4.0, abs=TOL)
    assert one(effort, np.zeros((10, 3))) == 0.0


@pytest.mark.parametrize('bad', [np.nan, np.inf])
def test_effort_rejects_non_finite(bad):
    with pytest.raises(ValueError, match='finite'):
        one(effort, np.array([[1.0, bad]]))


# -- tracking_error ---------------------------------------------------------------------------
def test_tracking_error_rms():
    q = np.array([[0.0, 1.0], [2.0, -1.0]])
    q_ref = q + np.array([[0.1, -0.2], [0.3, 0.0]])
    assert one(tracking_error, q, q_ref) == pytest.approx(np.sqrt(0.14 / 4), abs=TOL)
    assert one(tracking_error, q, q + 0.25) == pytest.approx(0.25, abs=TOL)
    assert one(tracking_error, q, q) == 0.0


def test_tracking_error_rejects_shape_mismatch():
    with pytest.raises(ValueError, match='shape'):
        one(tracking_error, np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match='shape'):
        one(tracking_error, np.zeros((5, 3)), np.zeros((5, 1)))   # would broadcast


def test_tracking_error_rejects_nan():
    with pytest.raises(ValueError, match='finite'):
        one(tracking_error, np.zeros((2, 2)), np.array([[0.0, np.nan], [0.0, 0.0]]))


@pytest.mark.filterwarnings('ignore::RuntimeWarning')
def test_tracking_error_rejects_empty():
    with pytest.raises(ValueError):
        one(tracking_error, np.zeros((0, 3)), np.zeros((0, 3)))


# -- score ------------------------------------------------------------------------------------
COMPONENTS_EXAMPLE = {'goal_error': 0.01, 'penetration': 0.002, 'clearance': 0.001,
                      'smoothness': 500.0, 'effort': 100.0, 'tracking_error': 0.03,
                      'orientation_error': 0.05}
WEIGHTS_EXAMPLE = {'goal_error': 10.0, 'penetration': 100.0, 'clearance': 20.0,
                   'smoothness': 1e-5, 'effort': 1e-5, 'tracking_error': 1.0,
                   'orientation_error': 2.0}
# 0.1 + 0.2 + 0.02 + 0.005 + 0.001 + 0.03 + 0.1 = 0.456
REWARD_EXAMPLE = -0.456


def test_score_is_minus_weighted_sum():
    result = score(COMPONENTS_EXAMPLE, WEIGHTS_EXAMPLE, -1.0)
    assert result.reward == pytest.approx(REWARD_EXAMPLE, abs=TOL)
    assert result.components == COMPONENTS_EXAMPLE
    assert set(COMPONENTS) == set(COMPONENTS_EXAMPLE)


def test_score_threshold_both_sides():
    below = score(COMPONENTS_EXAMPLE, WEIGHTS_EXAMPLE, REWARD_EXAMPLE + 1e-6)
    above = score(COMPONENTS_EXAMPLE, WEIGHTS_EXAMPLE, REWARD_EXAMPLE - 1e-6)
    assert below.fulfilled is False
    assert above.fulfilled is True
    exact = score({'goal_error': 0.5}, {'goal_error': 1.0}, -0.5)
    assert exact.reward == -0.5 and exact.fulfilled is True      # reward >= threshold


def test_score_component_without_weight_counts_zero():
    result = score(COMPONENTS_EXAMPLE, {'goal_error': 2.0}, -1.0)
    assert result.reward == pytest.approx(-0.02, abs=TOL)


def test_an_unregistered_weight_is_refused_with_the_nearest_name():
    with pytest.raises(ValueError, match=r"'goal_eror' \(did you mean goal_error\?\)"):
        check_weights({'goal_error': 1.0, 'goal_eror': 1.0})
    check_weights(dict.fromkeys(COMPONENTS, 1.0))      # psl's own are all registered


def test_components_nonnegative_and_reward_nonpositive_on_random_data():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=(30, 3))
        comps = {'goal_error': one(goal_error, rng.normal(size=3), rng.normal(size=3)),
                 'penetration': one(penetration, rng.normal(size=30)),
                 'clearance': one(clearance, rng.normal(size=30), margin=0.02),
                 'smoothness': one(smoothness, q, dt=0.01),
                 'effort': one(effort, rng.normal(size=(30, 3))),
                 'tracking_error': one(tracking_error, q, q + rng.normal(size=q.shape))}
        assert all(value >= 0.0 for value in comps.values())
        assert score(comps, WEIGHTS_EXAMPLE, 0.0).reward <= 0.0


def test_each_component_of_a_population_equals_its_members_alone():
    rng = np.random.default_rng(1)
    q, q_ref, torque = rng.normal(size=(3, 5, 40, 3))          # (B, T, n) each
    distance, ee, goal = rng.normal(size=(5, 40)), rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    population = {'goal_error': goal_error(ee, goal), 'penetration': penetration(distance),
                  'clearance': clearance(distance, 0.1), 'smoothness': smoothness(q, 0.01),
                  'effort': effort(torque), 'tracking_error': tracking_error(q, q_ref)}
    for b in range(5):
        alone = {'goal_error': one(goal_error, ee[b], goal[b]),
                 'penetration': one(penetration, distance[b]),
                 'clearance': one(clearance, distance[b], margin=0.1),
                 'smoothness': one(smoothness, q[b], dt=0.01), 'effort': one(effort, torque[b]),
                 'tracking_error': one(tracking_error, q[b], q_ref[b])}
        for name, value in alone.items():
            assert population[name].shape == (5,)
            assert population[name][b] == pytest.approx(value, rel=1e-12, abs=1e-15)


# -- the task's Reward on the embedded task (graph mode: geometry from a replay) ---------------
@pytest.fixture(scope='module')
def task():
    return load_task('reach_over_obstacle')


@pytest.fixture(scope='module')
def arm(task):
    return ArmModel(task)


@pytest.fixture(scope='module')
def reward(task, arm):
    return Reward(task, RewardGeometry(arm))


def evaluate_rollout(reward, tau, q, torque, q_ref):
    """One rollout scored from a replay of its joint angles (what the evaluator node does)."""
    return reward.evaluate_replayed(np.asarray(q, dtype=float)[None],
                                    np.asarray(torque, dtype=float)[None],
                                    np.asarray(q_ref, dtype=float)[None],
                                    np.asarray(tau, dtype=float)[None])[0]


def _segment_distance(p, a, b):
    ab = b - a
    t = np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t * ab))


def test_evaluate_rollout_holding_start_posture(task, reward):
    steps = task.num_steps + 1
    q = np.tile(task.start_posture, (steps, 1))
    torque = np.zeros((steps, task.n_joints))
    result = evaluate_rollout(reward, task.tau_default, q, torque, q.copy())
    expected_goal_error = np.linalg.norm(planar_fk(task.start_posture)
                                         - planar_fk(task.goal_posture))
    c = result.components
    assert set(c) == set(COMPONENTS)
    assert c['goal_error'] == pytest.approx(expected_goal_error, abs=TOL_FK)
    assert c['tracking_error'] == 0.0
    assert c['smoothness'] == 0.0
    assert c['effort'] == 0.0
    # The start posture (end effector on the table left of the pillar) keeps clear of it:
    # closed form, distance from the pillar's segment to the arm's joint points and links.
    x, height = task.tau_default
    phi = np.cumsum(task.start_posture)
    joints = np.vstack([[0.0, 0.0], np.cumsum(np.column_stack(
        [LINKS * np.cos(phi), LINKS * np.sin(phi)]), axis=0)])
    assert np.all(joints[:, 0] < x)        # every link is left of the pillar: no crossing
    top, bottom = np.array([x, height - OBSTACLE_RADIUS]), np.array(
        [x, height - OBSTACLE_RADIUS - OBSTACLE_LENGTH])
    seg = min(min(_segment_distance(top, joints[i], joints[i + 1]),
                  _segment_distance(bottom, joints[i], joints[i + 1]),
                  _segment_distance(joints[i], bottom, top),
                  _segment_distance(joints[i + 1], bottom, top)) for i in range(3))
    signed = seg - ARM_RADIUS - OBSTACLE_RADIUS
    margin = task.reward.clearance_margin
    assert c['penetration'] == pytest.approx(max(0.0, -signed), abs=1e-9)
    assert c['clearance'] == pytest.approx(max(0.0, margin - signed), abs=1e-9)
    weights = task.reward.weights
    assert result.reward == pytest.approx(-sum(weights.get(k, 0.0) * c[k] for k in c), abs=TOL)
    assert result.fulfilled == (result.reward >= task.reward.success_threshold)
    assert result.fulfilled is False        # standing still does not reach the goal


def test_evaluate_rollout_demonstration_reference(task, reward):
    policy = TaskPolicy(task)
    reference = policy.reference(policy.default_theta)
    q = reference.q
    assert q.shape == (task.num_steps + 1, task.n_joints)
    torque = np.zeros_like(q)
    result = evaluate_rollout(reward, task.tau_default, q, torque, q.copy())
    assert result.components['penetration'] == 0.0
    assert result.components['goal_error'] < DEMO_GOAL_ERROR
    assert result.components['tracking_error'] == 0.0
    assert result.components['smoothness'] > 0.0      # it moves


def test_evaluate_rollout_penetrating_posture(task, reward):
    """The flat arm crosses the pillar: penetration = both radii."""
    q = np.zeros((5, task.n_joints))
    result = evaluate_rollout(reward, task.tau_default, q, np.zeros_like(q), q)
    assert result.components['penetration'] == pytest.approx(ARM_RADIUS + OBSTACLE_RADIUS,
                                                             abs=1e-9)
    assert result.fulfilled is False


def test_evaluate_rollout_rejects_nan(task, reward):
    q = np.tile(task.start_posture, (5, 1))
    q[3, 0] = np.nan
    with pytest.raises(ValueError):
        evaluate_rollout(reward, task.tau_default, q, np.zeros((5, 3)), np.zeros((5, 3)))


@pytest.mark.parametrize('torque_shape', [(5, 2), (1, 3)])
def test_evaluate_rollout_rejects_torque_shape_mismatch(task, reward, torque_shape):
    q = np.tile(task.start_posture, (5, 1))
    with pytest.raises(ValueError):
        evaluate_rollout(reward, task.tau_default, q, np.ones(torque_shape), q)


def test_a_task_weighting_an_unknown_component_is_refused(task, arm):
    import dataclasses
    typo = dataclasses.replace(task, reward=dataclasses.replace(
        task.reward, weights={**task.reward.weights, 'goal_eror': 1.0}))
    with pytest.raises(ValueError, match='goal_eror'):
        Reward(typo, RewardGeometry(arm))


def test_smoothness_of_the_reference_ignores_measurement_noise(task, tmp_path):
    """reward.smoothness_of: reference scores the commanded motion: noise on the measured
    angles leaves it as it is (the measured one grows by about 6 sigma^2 / dt^4); without
    noise the measured default and the reference agree when the arm tracks exactly."""
    import yaml
    data = yaml.safe_load(task.path.read_text())
    data.update(name='reach_reference_smoothness', model=str(task.model_path))
    data['reward']['smoothness_of'] = 'reference'
    path = tmp_path / 'task.yaml'
    path.write_text(yaml.safe_dump(data))
    by_reference = load_task(str(path))
    policy = TaskPolicy(task)
    q_ref = policy.reference(policy.default_theta).q
    torque = np.zeros_like(q_ref)
    sigma, dt = 1e-3, task.control_period
    noisy = q_ref + np.random.default_rng(0).normal(0.0, sigma, q_ref.shape)
    measured = Reward(task, RewardGeometry(ArmModel(task)))
    referenced = Reward(by_reference, RewardGeometry(ArmModel(by_reference)))
    clean = evaluate_rollout(measured, task.tau_default, q_ref, torque, q_ref)
    assert evaluate_rollout(referenced, task.tau_default, q_ref, torque, q_ref) \
        .components['smoothness'] == clean.components['smoothness']
    assert evaluate_rollout(referenced, task.tau_default, noisy, torque, q_ref) \
        .components['smoothness'] == clean.components['smoothness']
    grown = evaluate_rollout(measured, task.tau_default, noisy, torque, q_ref) \
        .components['smoothness'] - clean.components['smoothness']
    assert grown == pytest.approx(6 * sigma**2 / dt**4, rel=0.1)
