"""Tests of ArmModel and of its reward geometry (the reward's sensors on a kinematic replay)
against closed-form planar kinematics and capsule geometry, plus dm_control-style properties
(finite observations of the declared shape, determinism)."""

import textwrap

import mujoco
import numpy as np
import pytest
import yaml

from psl_task.arm_model import ArmModel, joint_names_of
from psl_task.reward_geometry import RewardGeometry
from psl_task.task import EMBEDDED_TASKS, TaskError, load_task

DEFAULT_TASK = 'reach_over_obstacle'

# Geometry of reach_over_obstacle.xml, copied by hand.
LINKS = np.array([0.5, 0.5, 0.3])       # m
ARM_RADIUS = 0.025                       # m, capsule radius of every link
OBSTACLE_RADIUS = 0.04                   # m
OBSTACLE_LENGTH = 0.4                    # m, capsule segment from body z - 0.4 to body z
TORQUE_LIMIT = 40.0                      # N m, symmetric ctrlrange

TOL_FK = 1e-12          # m, MuJoCo kinematics vs closed form
TOL_QUAT = 1e-12        # quaternion components
TOL_DISTANCE = 1e-9     # m, mj_geomDistance (capsule-capsule) vs closed-form segment distance
TOL_POLICY_GOAL = 1e-3  # rad, |reference(default theta)[-1] - goal posture|

N_RANDOM_POSTURES = 300
N_ROLLOUT_STEPS = 400


# -- the reward geometry of one rollout ---------------------------------------------------------
def replay(arm, q, tau):
    """The reward sensors along one rollout's joint angles q (T, n): end-effector positions
    (T, 3) and arm-obstacle distances (T,) (None without an obstacle)."""
    measured = RewardGeometry(arm).replay(np.asarray(q, dtype=float)[None],
                                          np.asarray(tau, dtype=float)[None])
    distance = None if measured.distance is None else measured.distance[0]
    return measured.end_effector[0], distance


def ee_at(arm, q):
    return RewardGeometry(arm).end_effector_at(q)


# -- independent references -------------------------------------------------------------------
def planar_joint_points(q, lengths):
    """Closed-form positions (n+1, 3) of the base, every joint and the tip of a planar arm whose
    hinges turn about -y (positive angles lift): with phi_i = q_1 + ... + q_i,
    p_k = sum_{i<=k} l_i (cos phi_i, 0, sin phi_i)."""
    phi = np.cumsum(q)
    steps = np.stack([lengths * np.cos(phi), np.zeros_like(phi), lengths * np.sin(phi)], axis=1)
    return np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])


def planar_fk(q, lengths=LINKS):
    """End-effector position (3,): x = sum l_i cos phi_i, y = 0, z = sum l_i sin phi_i."""
    return planar_joint_points(q, lengths)[-1]


def _point_segment_distance(p, a, b):
    ab = b - a
    t = np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t * ab))


def _cross2(u, v):
    return u[0] * v[1] - u[1] * v[0]


def segment_distance_2d(a, b, c, d):
    """Distance between segments ab and cd in a plane: 0 when they cross, else the smallest
    endpoint-to-segment distance."""
    r, s = b - a, d - c
    denom = _cross2(r, s)
    if denom != 0.0:
        t = _cross2(c - a, s) / denom
        u = _cross2(c - a, r) / denom
        if 0.0 <= t <= 1.0 and 0.0 <= u <= 1.0:
            return 0.0
    return min(_point_segment_distance(a, c, d), _point_segment_distance(b, c, d),
               _point_segment_distance(c, a, b), _point_segment_distance(d, a, b))


def closed_form_signed_distance(q, tau, lengths=LINKS):
    """Smallest signed distance arm-obstacle: segment distance in the x-z plane minus both
    capsule radii (mj_geomDistance's convention for capsules)."""
    x, height = tau
    top = np.array([x, height - OBSTACLE_RADIUS])            # upper end of the obstacle segment
    bottom = top - np.array([0.0, OBSTACLE_LENGTH])
    points = planar_joint_points(q, lengths)[:, [0, 2]]       # (n+1, 2) in x-z
    seg = min(segment_distance_2d(points[i], points[i + 1], bottom, top)
              for i in range(len(lengths)))
    return seg - ARM_RADIUS - OBSTACLE_RADIUS


@pytest.fixture(scope='module')
def task():
    return load_task(DEFAULT_TASK)


@pytest.fixture()
def arm(task):
    return ArmModel(task)


# -- kinematics -------------------------------------------------------------------------------
def test_sign_convention_positive_angle_lifts(arm):
    ee_flat = ee_at(arm, np.zeros(3))
    np.testing.assert_allclose(ee_flat, [LINKS.sum(), 0.0, 0.0], atol=TOL_FK)
    ee_up = ee_at(arm, np.array([0.5, 0.0, 0.0]))
    assert ee_up[2] > 0.0
    np.testing.assert_allclose(ee_up, LINKS.sum() * np.array([np.cos(0.5), 0, np.sin(0.5)]),
                               atol=TOL_FK)
    # Straight up: the end effector is above the base.
    np.testing.assert_allclose(ee_at(arm, np.array([np.pi / 2, 0.0, 0.0])),
                               [0.0, 0.0, LINKS.sum()], atol=TOL_FK)


@pytest.mark.parametrize('q', [
    [0.0, 0.0, 0.0], [0.3, -0.6, 0.9], [1.838, -2.115, -1.123], [0.639, -0.545, -1.495],
    [-1.0, 2.5, -2.9], [np.pi / 2, -np.pi / 2, -np.pi / 2]])
def test_forward_kinematics_closed_form(arm, q):
    q = np.array(q)
    np.testing.assert_allclose(ee_at(arm, q), planar_fk(q), rtol=0, atol=TOL_FK)


def test_replay_end_effector_matches_closed_form_on_random_postures(arm, task):
    rng = np.random.default_rng(0)
    q = rng.uniform(-3.0, 3.0, size=(50, 3))
    ee, _ = replay(arm, q, task.tau_default)
    assert ee.shape == (50, 3)
    expected = np.array([planar_fk(qk) for qk in q])
    np.testing.assert_allclose(ee, expected, rtol=0, atol=TOL_FK)


def test_end_effector_pose_after_reset(arm, task):
    arm.reset(task.tau_default)
    position, quat = arm.end_effector_pose()
    np.testing.assert_allclose(position, planar_fk(task.start_posture), atol=TOL_FK)
    # The site frame is turned by phi = sum(q) about -y: quat = (cos phi/2, 0, -sin phi/2, 0).
    phi = task.start_posture.sum()
    expected = np.array([np.cos(phi / 2), 0.0, -np.sin(phi / 2), 0.0])
    sign = np.sign(np.dot(quat, expected))        # q and -q are the same rotation
    np.testing.assert_allclose(sign * quat, expected, atol=TOL_QUAT)


def test_ee_goal_is_fk_of_goal_posture(arm, task):
    np.testing.assert_allclose(ee_at(arm, task.goal_posture), planar_fk(task.goal_posture),
                               atol=TOL_FK)


def test_joint_names(arm, task):
    assert arm.joint_names == ['joint1', 'joint2', 'joint3']
    assert joint_names_of(task) == ['joint1', 'joint2', 'joint3']


# -- obstacle distance ------------------------------------------------------------------------
@pytest.mark.parametrize('tau', [[0.55, 0.10], [0.675, 0.16], [0.8, 0.22]])
def test_replay_distance_arm_straight_up_is_gap_minus_radii(arm, tau):
    """Arm vertical along x = 0, obstacle vertical at x = tau[0] and overlapping in height:
    the capsules are parallel, distance = gap - radii."""
    _, dist = replay(arm, np.array([[np.pi / 2, 0.0, 0.0]]), tau)
    np.testing.assert_allclose(dist, [tau[0] - ARM_RADIUS - OBSTACLE_RADIUS], atol=TOL_DISTANCE)


@pytest.mark.parametrize('tau', [[0.55, 0.10], [0.675, 0.16], [0.8, 0.22]])
def test_replay_distance_arm_through_obstacle_is_negative(arm, tau):
    """Arm flat along +x at height 0 crosses the pillar (which spans z = 0): the segments
    intersect, so the signed distance is minus both radii."""
    _, dist = replay(arm, np.zeros((1, 3)), tau)
    assert dist[0] < 0.0
    np.testing.assert_allclose(dist, [-(ARM_RADIUS + OBSTACLE_RADIUS)], atol=TOL_DISTANCE)


def test_replay_distance_grazing_the_top():
    """Arm at angle a passes at perpendicular distance |z_top cos a - x sin a| from the top
    end of the obstacle segment (x, z_top): a partial overlap with a known depth."""
    arm = ArmModel(load_task(DEFAULT_TASK))
    x, height = 0.7, 0.20
    angle = 0.28          # the arm passes just above the top end (0.7 tan 0.28 > 0.16)
    z_top = height - OBSTACLE_RADIUS
    expected = abs(z_top * np.cos(angle) - x * np.sin(angle)) - ARM_RADIUS - OBSTACLE_RADIUS
    _, dist = replay(arm, np.array([[angle, 0.0, 0.0]]), [x, height])
    assert -(ARM_RADIUS + OBSTACLE_RADIUS) < dist[0] < 0.0
    np.testing.assert_allclose(dist, [expected], atol=TOL_DISTANCE)


def test_replay_distance_matches_closed_form_on_random_postures(arm, task):
    rng = np.random.default_rng(1)
    q = np.column_stack([rng.uniform(0.0, 2.0, N_RANDOM_POSTURES),
                         rng.uniform(-2.5, 1.0, N_RANDOM_POSTURES),
                         rng.uniform(-2.0, 2.0, N_RANDOM_POSTURES)])
    for tau in (task.tau_low, task.tau_default, task.tau_high):
        _, dist = replay(arm, q, tau)
        expected = np.array([closed_form_signed_distance(qk, tau) for qk in q])
        # The sample covers clear, grazing and crossing postures.
        assert np.any(expected > 0.05) and np.any(expected < 0.0)
        np.testing.assert_allclose(dist, expected, rtol=0, atol=TOL_DISTANCE)


def test_replay_leaves_the_live_simulation_alone(arm, task):
    tau = np.array([0.6, 0.2])
    arm.reset(tau)
    arm.step(np.array([5.0, -3.0, 1.0]))
    q_before, mocap_before = arm.q, arm.data.mocap_pos.copy()
    replay(arm, np.zeros((3, 3)), task.tau_high)
    np.testing.assert_array_equal(arm.tau, tau)
    np.testing.assert_array_equal(arm.q, q_before)
    np.testing.assert_array_equal(arm.data.mocap_pos, mocap_before)


def test_replay_rejects_tau_out_of_range(arm):
    with pytest.raises(TaskError, match='outside its range'):
        replay(arm, np.zeros((1, 3)), [0.1, 0.25])


# -- tau binding ------------------------------------------------------------------------------
@pytest.mark.parametrize('tau', [[0.55, 0.10], [0.675, 0.16], [0.8, 0.22], [0.61, 0.2]])
def test_tau_moves_mocap_obstacle(arm, tau):
    x, height = tau
    arm.reset(np.array(tau))
    body = arm.model.body('obstacle').id
    geom = arm.model.geom('obstacle').id
    np.testing.assert_allclose(arm.data.mocap_pos[0], [x, 0.0, height - OBSTACLE_RADIUS],
                               atol=1e-15)
    np.testing.assert_allclose(arm.data.xpos[body], [x, 0.0, height - OBSTACLE_RADIUS],
                               atol=1e-15)
    # Top of the capsule = geom centre + half length + radius = height.
    radius, half_length = arm.model.geom_size[geom][:2]
    assert radius == pytest.approx(OBSTACLE_RADIUS)
    assert half_length == pytest.approx(OBSTACLE_LENGTH / 2)
    assert arm.data.geom_xpos[geom][2] + half_length + radius == pytest.approx(height, abs=1e-12)
    assert arm.data.geom_xpos[geom][0] == pytest.approx(x, abs=1e-15)


def test_reset_puts_arm_at_start_at_rest(arm, task):
    arm.reset(task.tau_default)
    arm.step(np.full(3, 10.0))
    arm.reset(task.tau_default)
    np.testing.assert_array_equal(arm.q, task.start_posture)
    np.testing.assert_array_equal(arm.qd, np.zeros(3))
    assert arm.data.time == 0.0


def test_reset_rejects_bad_tau(arm):
    with pytest.raises(TaskError):
        arm.reset(np.array([0.7, np.nan]))


# -- torque -----------------------------------------------------------------------------------
def test_torque_limits_come_from_ctrlrange(arm):
    np.testing.assert_array_equal(arm.torque_low, np.full(3, -TORQUE_LIMIT))
    np.testing.assert_array_equal(arm.torque_high, np.full(3, TORQUE_LIMIT))


def test_step_clips_torque_both_signs_and_returns_applied(task):
    commanded = np.array([100.0, -250.0, 12.5])
    expected = np.array([TORQUE_LIMIT, -TORQUE_LIMIT, 12.5])
    clipped_arm, reference_arm = ArmModel(task), ArmModel(task)
    clipped_arm.reset(task.tau_default)
    reference_arm.reset(task.tau_default)
    for _ in range(5):
        applied = clipped_arm.step(commanded)
        np.testing.assert_array_equal(applied, expected)
        np.testing.assert_array_equal(clipped_arm.data.ctrl, expected)
        reference_arm.step(expected)
    # The simulation ran with the clipped torque, not the commanded one.
    np.testing.assert_array_equal(clipped_arm.q, reference_arm.q)
    np.testing.assert_array_equal(clipped_arm.qd, reference_arm.qd)


def test_step_within_limits_is_unchanged(arm, task):
    arm.reset(task.tau_default)
    torque = np.array([-39.9, 0.0, 40.0])
    np.testing.assert_array_equal(arm.step(torque), torque)


def test_step_is_one_control_period(arm, task):
    arm.reset(task.tau_default)
    for k in range(1, 11):
        arm.step(np.zeros(3))
        assert arm.data.time == pytest.approx(k * task.control_period, abs=1e-12)


def test_positive_torque_accelerates_joint_positively(arm, task):
    arm.reset(task.tau_default)
    for _ in range(10):
        arm.step(np.array([0.0, 0.0, 5.0]))
    assert arm.qd[2] > 0.0
    assert arm.q[2] > task.start_posture[2]


# -- dm_control-style properties --------------------------------------------------------------
def _rollout(arm, tau, torques):
    arm.reset(tau)
    qs = [arm.q]
    for u in torques:
        arm.step(u)
        qs.append(arm.q)
    return np.array(qs)


def test_same_tau_and_torques_give_bit_identical_trajectory(task):
    rng = np.random.default_rng(3)
    torques = rng.uniform(-50.0, 50.0, size=(N_ROLLOUT_STEPS, 3))
    other = rng.uniform(-50.0, 50.0, size=(N_ROLLOUT_STEPS, 3))
    tau = task.sample_tau(rng)
    arm = ArmModel(task)
    first = _rollout(arm, tau, torques)
    _rollout(arm, task.tau_high, other)          # a different episode in between
    second = _rollout(arm, tau, torques)
    third = _rollout(ArmModel(task), tau, torques)
    assert np.array_equal(first, second)
    assert np.array_equal(first, third)
    assert not np.array_equal(first, _rollout(arm, tau, other))


@pytest.mark.parametrize('seed', [0, 1])
def test_observations_finite_and_of_declared_shape(task, seed):
    rng = np.random.default_rng(seed)
    arm = ArmModel(task)
    n = task.n_joints
    arm.reset(task.sample_tau(rng))
    for _ in range(N_ROLLOUT_STEPS):
        applied = arm.step(rng.uniform(-2 * TORQUE_LIMIT, 2 * TORQUE_LIMIT, size=n))
        q, qd = arm.q, arm.qd
        position, quat = arm.end_effector_pose()
        assert applied.shape == q.shape == qd.shape == (n,)
        assert position.shape == (3,) and quat.shape == (4,)
        for value in (applied, q, qd, position, quat):
            assert np.all(np.isfinite(value))
        assert np.all(np.abs(applied) <= TORQUE_LIMIT)
        assert np.linalg.norm(quat) == pytest.approx(1.0, abs=1e-9)
        assert np.linalg.norm(position[[0, 2]]) <= LINKS.sum() + 1e-9   # reach
        assert position[1] == pytest.approx(0.0, abs=1e-12)              # planar


def test_replay_output_shapes(arm, task):
    q = np.tile(task.start_posture, (7, 1))
    ee, dist = replay(arm, q, task.tau_default)
    assert ee.shape == (7, 3) and dist.shape == (7,)
    assert np.all(np.isfinite(ee)) and np.all(np.isfinite(dist))


# -- another MJCF via a task YAML -------------------------------------------------------------
LINKS4 = np.array([0.4, 0.35, 0.3, 0.2])

ARM4_XML = textwrap.dedent("""\
    <mujoco model="planar4">
      <compiler angle="radian" autolimits="true"/>
      <option timestep="{timestep}" gravity="0 0 -9.81" integrator="Euler"/>
      <default>
        <joint type="hinge" axis="0 -1 0" damping="0.1" armature="0.01" range="-3 3"/>
        <geom type="capsule" size="0.02" contype="0" conaffinity="0"/>
        <motor ctrlrange="-30 30"/>
      </default>
      <worldbody>
        <body name="b1">
          <joint name="j1"/>
          <geom name="g1" fromto="0 0 0 0.4 0 0" mass="1.0"/>
          <body name="b2" pos="0.4 0 0">
            <joint name="j2"/>
            <geom name="g2" fromto="0 0 0 0.35 0 0" mass="0.8"/>
            <body name="b3" pos="0.35 0 0">
              <joint name="j3"/>
              <geom name="g3" fromto="0 0 0 0.3 0 0" mass="0.6"/>
              <body name="b4" pos="0.3 0 0">
                <joint name="j4"/>
                <geom name="g4" fromto="0 0 0 0.2 0 0" mass="0.4"/>
                <site name="tip" pos="0.2 0 0"/>
              </body>
            </body>
          </body>
        </body>
        <body name="post" mocap="true" pos="0.5 0 0.2">
          <geom name="post" type="sphere" size="0.05"/>
        </body>
      </worldbody>
      <actuator>
        <motor joint="j1"/> <motor joint="j2"/> <motor joint="j3"/> <motor joint="j4"/>
      </actuator>
    </mujoco>
    """)

START4 = [1.2, -0.8, -0.6, -0.4]
GOAL4 = [0.3, 0.4, -0.9, -0.5]
POST_RADIUS = 0.05
ARM4_RADIUS = 0.02


def arm4_task_data(model_file='planar4.xml', control_rate=500.0):
    """A task YAML for the 4-joint arm with the structure of reach_over_obstacle.yaml."""
    data = yaml.safe_load((EMBEDDED_TASKS / f'{DEFAULT_TASK}.yaml').read_text())
    data.update({
        'name': 'planar4_reach', 'model': model_file, 'end_effector_site': 'tip',
        'control_rate': control_rate, 'duration': 0.6, 'settle_time': 0.4,
        'start_posture': START4, 'goal_posture': GOAL4,
        'task_parameters': [{'name': 'post_x', 'unit': 'm', 'low': 0.3, 'high': 0.9,
                             'default': 0.6,
                             'binds': {'kind': 'mocap_position', 'body': 'post', 'axis': 0}}],
        'controller': {'kp': [100.0, 80.0, 60.0, 40.0], 'kd': [10.0, 8.0, 6.0, 4.0]},
        'demonstration': {'times': [0.0, 0.3, 0.6],
                          'positions': [START4, [0.8, -0.2, -0.8, -0.45], GOAL4]},
    })
    data['policy'] = dict(data['policy'], n_basis=6)
    data['reward'] = dict(data['reward'], obstacle_geoms=['post'],
                          arm_geoms=['g1', 'g2', 'g3', 'g4'])
    return data


def write_arm4_task(folder, timestep=0.002, control_rate=500.0, extra=None):
    (folder / 'planar4.xml').write_text(ARM4_XML.format(timestep=timestep))
    data = arm4_task_data(control_rate=control_rate)
    if extra:
        data.update(extra)
    path = folder / 'planar4_reach.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def test_other_mjcf_four_joints_without_code_changes(tmp_path):
    task = write_arm4_task(tmp_path)
    arm = ArmModel(task)
    assert task.n_joints == 4 and task.tau_names == ['post_x']
    assert arm.joint_names == ['j1', 'j2', 'j3', 'j4']
    np.testing.assert_array_equal(arm.torque_high, np.full(4, 30.0))

    arm.reset(np.array([0.45]))
    np.testing.assert_array_equal(arm.q, START4)
    np.testing.assert_allclose(arm.data.mocap_pos[0], [0.45, 0.0, 0.2], atol=1e-15)
    np.testing.assert_allclose(arm.end_effector_pose()[0], planar_fk(START4, LINKS4),
                               atol=TOL_FK)
    np.testing.assert_array_equal(arm.step(np.array([50.0, -50.0, 1.0, 0.0])),
                                  [30.0, -30.0, 1.0, 0.0])
    for _ in range(20):
        arm.step(np.zeros(4))
    assert arm.q.shape == (4,) and np.all(np.isfinite(arm.q))
    assert not np.array_equal(arm.q, START4)

    # Replay: closed-form FK and sphere-to-segment distances.
    q = np.array([START4, GOAL4, [0.0, 0.0, 0.0, 0.0], [np.pi / 2, 0.0, 0.0, 0.0]])
    ee, dist = replay(arm, q, [0.6])
    np.testing.assert_allclose(ee, [planar_fk(qk, LINKS4) for qk in q], atol=TOL_FK)
    centre = np.array([0.6, 0.2])
    for qk, dk in zip(q, dist):
        points = planar_joint_points(qk, LINKS4)[:, [0, 2]]
        seg = min(_point_segment_distance(centre, points[i], points[i + 1]) for i in range(4))
        assert dk == pytest.approx(seg - POST_RADIUS - ARM4_RADIUS, abs=TOL_DISTANCE)
    np.testing.assert_allclose(ee_at(arm, GOAL4), planar_fk(GOAL4, LINKS4), atol=TOL_FK)


def test_other_mjcf_policy(tmp_path):
    from psl_controller.policy import TaskPolicy

    task = write_arm4_task(tmp_path)
    policy = TaskPolicy(task)
    assert policy.default_theta.shape == (4 * 6,)
    reference = policy.reference(policy.default_theta)
    assert reference.q.shape == (task.num_steps + 1, 4)
    np.testing.assert_allclose(reference.q[0], START4, atol=1e-12)
    np.testing.assert_allclose(reference.q[-1], GOAL4, atol=TOL_POLICY_GOAL)


def test_the_control_rate_divides_the_physics_rate(tmp_path):
    """1 kHz physics at 500 Hz control: two physics steps per command; 400 Hz is refused."""
    assert ArmModel(write_arm4_task(tmp_path, timestep=0.001, control_rate=500.0)).n_substeps == 2
    task = write_arm4_task(tmp_path, timestep=0.001, control_rate=400.0)
    with pytest.raises(TaskError) as info:
        ArmModel(task)
    assert 'control_rate 400 Hz must divide the physics rate 1 / timestep = 1000 Hz' in \
        str(info.value)


def test_posture_length_must_match_model(tmp_path):
    task = write_arm4_task(tmp_path, extra={
        'start_posture': [0.1, 0.2, 0.3], 'goal_posture': [0.1, 0.2, 0.3],
        'controller': {'kp': [1.0] * 3, 'kd': [1.0] * 3},
        'demonstration': {'times': [0.0, 0.6], 'positions': [[0.1, 0.2, 0.3]] * 2}})
    with pytest.raises(TaskError, match='4 joints'):
        ArmModel(task)


def test_unknown_site_raises(tmp_path):
    task = write_arm4_task(tmp_path, extra={'end_effector_site': 'no_such_site'})
    with pytest.raises(TaskError, match='no_such_site'):
        ArmModel(task)


def test_replay_with_mass_parameter_leaves_dynamics_alone(tmp_path):
    task = write_arm4_task(tmp_path, extra={'task_parameters': [
        {'name': 'payload', 'unit': 'kg', 'low': 0.1, 'high': 5.0, 'default': 0.4,
         'binds': {'kind': 'body_mass', 'body': 'b4'}}]})
    torques = np.tile([5.0, -3.0, 2.0, 1.0], (50, 1))
    undisturbed = _rollout(ArmModel(task), [0.2], torques)

    arm = ArmModel(task)
    arm.reset(np.array([0.2]))
    replay(arm, np.zeros((1, 4)), [5.0])          # scoring another task instance
    states = [arm.q]
    for u in torques:
        arm.step(u)
        states.append(arm.q)
    np.testing.assert_array_equal(np.array(states), undisturbed)


# -- what the MJCF must offer: one plain torque motor per joint ------------------------------
def _rewrite_model(folder, old, new):
    path = folder / 'planar4.xml'
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))


@pytest.mark.parametrize('actuator, name', [
    ('<position joint="j2" kp="50" ctrlrange="-1 1"/>', 'a position servo'),
    ('<general joint="j2" dyntype="filter" dynprm="0.05" ctrlrange="-30 30"/>', 'a filter'),
])
def test_actuators_other_than_plain_joint_motors_are_refused(tmp_path, actuator, name):
    task = write_arm4_task(tmp_path)
    _rewrite_model(tmp_path, '<motor joint="j2"/>', actuator)
    with pytest.raises(TaskError, match='not plain joint motors') as info:
        ArmModel(task)
    assert '<motor' in str(info.value), name


def test_two_motors_on_one_joint_are_refused(tmp_path):
    task = write_arm4_task(tmp_path)
    _rewrite_model(tmp_path, '<motor joint="j2"/>', '<motor joint="j1"/>')
    with pytest.raises(TaskError, match='more than one actuator.*exactly one'):
        ArmModel(task)


def test_forcerange_and_joint_actuatorfrcrange_narrow_the_torque_limits(tmp_path):
    """MuJoCo clamps the force to the actuator's forcerange and the joint's actuatorfrcrange
    after ctrlrange: the torque limits (and so the applied torques) are the narrowest."""
    task = write_arm4_task(tmp_path)
    _rewrite_model(tmp_path, '<motor joint="j2"/>', '<motor joint="j2" forcerange="-12 20"/>')
    _rewrite_model(tmp_path, '<joint name="j3"/>', '<joint name="j3" actuatorfrcrange="-5 5"/>')
    arm = ArmModel(task)
    np.testing.assert_array_equal(arm.torque_low, [-30.0, -12.0, -5.0, -30.0])
    np.testing.assert_array_equal(arm.torque_high, [30.0, 20.0, 5.0, 30.0])
    arm.reset(np.array([0.6]))
    applied = arm.step(np.array([0.0, -50.0, 50.0, 0.0]))
    np.testing.assert_array_equal(applied, [0.0, -12.0, 5.0, 0.0])
    np.testing.assert_allclose(arm.data.qfrc_actuator[arm.dof_adr], applied, atol=1e-12)


def test_end_effector_pose_is_that_of_the_current_state(arm, task):
    """After steps, the pose is the kinematics of the joint angles the arm has now (on a data
    of its own), not of the state before the last step."""
    arm.reset(task.tau_default)
    for _ in range(30):
        arm.step(np.full(task.n_joints, 0.5 * TORQUE_LIMIT))
    position, quat = arm.end_effector_pose()
    data = mujoco.MjData(arm.model)
    data.qpos[:] = arm.data.qpos
    mujoco.mj_kinematics(arm.model, data)
    np.testing.assert_allclose(position, data.site_xpos[arm.ee_site], rtol=0, atol=1e-12)
    expected = np.empty(4)
    mujoco.mju_mat2Quat(expected, data.site_xmat[arm.ee_site])
    np.testing.assert_allclose(quat, expected, rtol=0, atol=1e-12)
