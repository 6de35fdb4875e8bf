"""A new goal during the motion: the DMP's goal filter (`DMP.integrate_goal_change`) and the
policy's reference with a goal change (`TaskPolicy.reference_with_new_goal`)."""
import shutil

import numpy as np
import pytest
import yaml

from psl_controller.dmp import DMP
from psl_controller.policy import TaskPolicy, policy_for
from psl_task.task import EMBEDDED_TASKS, load_task

TOL_SETTLED = 1e-6      # |y - g_new| long after the switch (relative to the goal change)
EULER_RATIO = (1.8, 2.2)   # explicit Euler: halving the step halves the error (first order)
TOL_EULER = 2e-4        # error of the finer Euler run (relative to the signal scale)
TOL_IK = 1e-4           # m, the hand of the IK's joint path against the DMP's hand path

DT = 0.002


def random_dmp(rng, canonical='linear', time_scale=1.0, n_dims=3, duration=1.0):
    dmp = DMP(n_dims, 8, duration, rng.uniform(-1, 1, n_dims), rng.uniform(-1, 1, n_dims),
              canonical=canonical, time_scale=time_scale)
    dmp.set_theta(rng.normal(scale=200.0, size=dmp.num_parameters))
    return dmp


# -- the DMP ----------------------------------------------------------------------------------
@pytest.mark.parametrize('canonical', ['linear', 'exponential'])
@pytest.mark.parametrize('time_scale', [1.0, 1.5])
@pytest.mark.parametrize('t_switch', [0.0, 0.3, 0.3011, 0.9])
def test_before_the_switch_the_path_is_bit_identical(canonical, time_scale, t_switch):
    dmp = random_dmp(np.random.default_rng(0), canonical, time_scale)
    plain = dmp.integrate(DT, 1.5)
    changed = dmp.integrate_goal_change(DT, t_switch, dmp.goal + [0.3, -0.2, 0.1], 1.5)
    k_s = int(np.ceil(t_switch / DT - 1e-9))           # the first grid point at or after it
    np.testing.assert_array_equal(changed.t, plain.t)
    for name in ('y', 'yd', 'ydd'):
        np.testing.assert_array_equal(getattr(changed, name)[:k_s + 1],
                                      getattr(plain, name)[:k_s + 1])
        assert not np.array_equal(getattr(changed, name)[k_s + 1:],
                                  getattr(plain, name)[k_s + 1:])


@pytest.mark.parametrize('time_scale', [1.0, 2.0])
def test_long_after_the_switch_the_path_rests_at_the_new_goal(time_scale):
    dmp = random_dmp(np.random.default_rng(1), time_scale=time_scale)
    new_goal = dmp.goal + [0.5, -0.4, 0.2]
    traj = dmp.integrate_goal_change(DT, 0.6, new_goal, t_end=4.0 * time_scale)
    np.testing.assert_allclose(traj.y[-1], new_goal, atol=TOL_SETTLED)
    np.testing.assert_allclose(traj.yd[-1], 0.0, atol=TOL_SETTLED)
    # the unchanged path rests at the old goal
    np.testing.assert_allclose(dmp.integrate(DT, 4.0 * time_scale).y[-1], dmp.goal,
                               atol=TOL_SETTLED)


def test_no_jump_the_steps_stay_within_the_paths_normal_steps():
    """A property over random DMPs, switch times and goal changes: no step of the changed
    path exceeds the largest step of the unchanged one by more than alpha_goal |g_new - g| dt
    (the goal filter's fastest step; the critically damped spring follows it no faster), 2 %
    of |g_new - g| here, where a hard goal switch would jump by it; the acceleration changes
    at the switch by at most k_s |g_new - g| alpha_goal dt more than without the change
    (2 % of a hard switch's jump, k_s |g_new - g|)."""
    rng = np.random.default_rng(2)
    for _ in range(40):
        dmp = random_dmp(rng, canonical=rng.choice(['linear', 'exponential']))
        plain = dmp.integrate(DT, 2.0)
        extent = plain.y.max(axis=0) - plain.y.min(axis=0)                # (n_dims,)
        change = rng.uniform(-0.3, 0.3, dmp.n_dims) * extent
        t_switch = rng.uniform(0.0, 1.5)
        changed = dmp.integrate_goal_change(DT, t_switch, dmp.goal + change, 2.0)
        normal_step = np.abs(np.diff(plain.y, axis=0)).max(axis=0)
        filter_step = dmp.alpha_goal * np.abs(change) * DT
        assert np.all(np.abs(np.diff(changed.y, axis=0)).max(axis=0)
                      <= (normal_step + filter_step) * (1.0 + 1e-9))
        k = int(np.ceil(t_switch / DT - 1e-9))
        jerk_step = np.abs(changed.ydd[k + 1] - changed.ydd[k])
        plain_step = np.abs(plain.ydd[k + 1] - plain.ydd[k])
        filtered = dmp.k_s * np.abs(change) * dmp.alpha_goal * DT           # k_s |dg| a_g dt
        assert np.all(jerk_step <= plain_step + filtered * (1.0 + 1e-6))


def euler(dmp: DMP, dt: float, n_steps: int, k_s: int, new_goal, substeps: int):
    """Explicit Euler on [y, yd, g], `substeps` per grid step, forcing held over each grid
    step (as the DMP's zero-order hold), goal filter g' = a (g_new - g) from grid step k_s."""
    h = dt / substeps
    s2 = dmp.time_scale ** 2
    k, d, a = dmp.k_s / s2, dmp.k_d / dmp.time_scale, dmp.alpha_goal / dmp.time_scale
    forcing = dmp.forcing(np.arange(n_steps + 1) * dt)               # already divided by s2
    y, yd, g = dmp.y0.copy(), np.zeros(dmp.n_dims), dmp.goal.copy()
    out = [y.copy()]
    for n in range(n_steps):
        target = new_goal if n >= k_s else g
        for _ in range(substeps):
            ydd = k * (g - y) - d * yd + forcing[n]
            gd = a * (target - g)
            y, yd, g = y + h * yd, yd + h * ydd, g + h * gd
        out.append(y.copy())
    return np.array(out)


def test_the_goal_change_matches_a_brute_force_euler_integration():
    """The exact discretisation against explicit Euler on the same ODE (held forcing, goal
    filter from the switch): Euler's error halves with its step and is small."""
    dt, t_end, t_switch = 0.02, 1.6, 0.4
    dmp = random_dmp(np.random.default_rng(3), duration=0.8, time_scale=1.25)
    new_goal = dmp.goal + [0.4, -0.3, 0.25]
    exact = dmp.integrate_goal_change(dt, t_switch, new_goal, t_end).y
    n_steps, k_s = int(round(t_end / dt)), int(round(t_switch / dt))
    errors = [np.abs(euler(dmp, dt, n_steps, k_s, new_goal, m) - exact).max()
              for m in (200, 400)]
    scale = max(1.0, np.abs(exact).max())
    assert EULER_RATIO[0] < errors[0] / errors[1] < EULER_RATIO[1], errors
    assert errors[1] < TOL_EULER * scale, errors


def test_bad_goal_changes_are_refused():
    dmp = random_dmp(np.random.default_rng(4))
    with pytest.raises(ValueError, match='new_goal must have shape'):
        dmp.integrate_goal_change(DT, 0.5, [1.0, 2.0])
    with pytest.raises(ValueError, match='new_goal must be finite'):
        dmp.integrate_goal_change(DT, 0.5, [1.0, np.nan, 2.0])
    for t_switch in (-0.1, 1.2, np.inf, np.nan):
        with pytest.raises(ValueError, match='t_switch'):
            dmp.integrate_goal_change(DT, t_switch, np.zeros(3))
    with pytest.raises(ValueError, match='alpha_goal'):
        DMP(1, 3, 1.0, [0.0], [1.0], alpha_goal=0.0)


# -- the policy -------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def joint_task():
    return load_task('reach_over_obstacle')


def test_the_reference_is_the_policys_until_the_switch_then_reaches_the_new_goal(joint_task):
    policy = policy_for(joint_task)
    theta, tau = policy.default_theta, joint_task.tau_default
    new_goal = np.asarray(joint_task.goal_posture) + [-0.1, 0.15, 0.1]
    plain = policy.reference(theta, tau)
    changed = policy.reference_with_new_goal(theta, tau, 0.5, new_goal)
    k = int(round(0.5 / joint_task.control_period))
    for name in ('t', 'q', 'qd', 'u_ffwd'):
        np.testing.assert_array_equal(getattr(changed, name)[:k + 1],
                                      getattr(plain, name)[:k + 1])
    np.testing.assert_allclose(changed.q[-1], new_goal, atol=1e-3)
    assert np.abs(plain.q[-1] - new_goal).max() > 0.09
    steps, normal = np.abs(np.diff(changed.q, axis=0)), np.abs(np.diff(plain.q, axis=0))
    filter_step = (policy.dmp.alpha_goal * np.abs(new_goal - policy.dmp.goal)
                   * joint_task.control_period)
    assert np.all(steps.max(axis=0) <= normal.max(axis=0) + filter_step)


@pytest.mark.parametrize('t_switch, goal, words', [
    (0.5, [0.1, 0.2], ['needs 3 values', 'joint angles', 'got 2']),
    (0.5, [0.1, np.inf, 0.2], ['finite']),
    (2.0, [0.1, 0.2, 0.3], ['[0, 2) s', 'got 2.0']),
    (-0.5, [0.1, 0.2, 0.3], ['[0, 2) s']),
    (np.nan, [0.1, 0.2, 0.3], ['[0, 2) s']),
])
def test_the_policy_refuses_bad_goal_changes(joint_task, t_switch, goal, words):
    policy = policy_for(joint_task)
    with pytest.raises(ValueError) as info:
        policy.reference_with_new_goal(policy.default_theta, None, t_switch, goal)
    for word in words:
        assert word in str(info.value)


@pytest.fixture(scope='module')
def hand_space_task(tmp_path_factory):
    """planar_10dof_reach with its DMP over the hand position."""
    folder = tmp_path_factory.mktemp('hand_space_goal_change')
    data = yaml.safe_load((EMBEDDED_TASKS / 'planar_10dof_reach.yaml').read_text())
    data['policy'].update(space='end_effector')
    shutil.copy(EMBEDDED_TASKS / data['model'], folder / data['model'])
    (folder / 'hand_space.yaml').write_text(yaml.safe_dump(data))
    return load_task(str(folder / 'hand_space.yaml'))


def test_in_end_effector_space_the_new_goal_is_a_hand_point(hand_space_task):
    """The hand path (forward kinematics on the model) turns to the new 3-D goal point; the
    joint reference is the policy's until the switch."""
    from psl_task.arm_model import ArmModel
    from psl_task.reward_geometry import RewardGeometry

    policy = TaskPolicy(hand_space_task)
    theta = policy.default_theta
    new_goal = policy.dmp.goal + [0.05, -0.05, 0.0]
    plain = policy.reference(theta)
    changed = policy.reference_with_new_goal(theta, None, 0.3, new_goal)
    k = int(round(0.3 / hand_space_task.control_period))
    np.testing.assert_array_equal(changed.q[:k + 1], plain.q[:k + 1])
    np.testing.assert_array_equal(changed.qd[:k], plain.qd[:k])   # qd: a central difference
    geometry = RewardGeometry(ArmModel(hand_space_task))
    np.testing.assert_allclose(geometry.end_effector_at(changed.q[-1]), new_goal, atol=TOL_IK)
    policy.dmp.set_theta(theta[policy.kinematics])
    dt = hand_space_task.control_period
    path = policy.dmp.integrate_goal_change(dt, 0.3, new_goal, len(changed.t) * dt - dt).y
    hands = np.array([geometry.end_effector_at(q) for q in changed.q[::25]])
    np.testing.assert_allclose(hands, path[::25], atol=TOL_IK)
    with pytest.raises(ValueError, match='needs 3 values .the hand point'):
        policy.reference_with_new_goal(theta, None, 0.3, np.zeros(10))
