"""Tests of PopulationIK against independent references: its kinematics against MuJoCo's
(mj_kinematics, mj_jacSite) on the tasks' models and on a model with every kind of chain
element; its solution against DifferentialIK candidate by candidate; row independence
(one candidate alone = the same candidate in a population, bit for bit, under every OpenBLAS
kernel this CPU runs); refused input; the optional orientation term."""

import os
from pathlib import Path

import mujoco
import numpy as np
import pytest

from psl_task.arm_model import ArmModel
from psl_task.inverse_kinematics import DifferentialIK, IKError
from psl_task.population_ik import PopulationIK
from psl_task.site_chain import orientation_error, quaternion_of, rotation_vector
from psl_task.task import load_task

EXAMPLES = Path(__file__).resolve().parents[3] / 'examples'

# MuJoCo's kinematics (quaternions, com-based Jacobian) and the chain's (Rodrigues, cross
# products) are two roundings of the same products of ~10 transforms: ~1e-15 apart
TOL_KINEMATICS = 1e-12      # m, m/rad, rad/rad, rotation matrix entries
# PopulationIK vs DifferentialIK: the same step in another floating-point order (LU instead
# of Cholesky, other summation orders, other kinematics), so the two drift apart by roundoff
# only; the step contracts the task-space error and the null-space pull (1 % per sample)
# contracts the rest, so the drift stays near the roundoff of one step amplified by the damped
# pseudo-inverse (|J^#| <= 1 / (2 damping) = 500 rad/m): measured <= 3e-14 rad on paths in
# reach, <= 2e-10 rad on the paths that leave it or pin joints on limits. 1e-9 rad keeps a
# margin of 5 over the worst of these and is 4 orders below the IK's own tolerance (1e-5 m
# over a ~0.5 m arm, 2e-5 rad).
TOL_PATH = 1e-9             # rad, whole paths where the reference is reproducible
TOL_BEYOND = 1e-8           # rad, a whole path out of the reach and back (measured 9e-10)
TOL_STEP = 1e-10            # rad, one sample from the reference's previous q (measured <= 6e-12)
TOL_POSE_POSITION = 1e-4    # m, a reachable pose path tracked with the orientation term
TOL_POSE_ANGLE = 1e-3       # rad

PATH_SAMPLES = 600          # 1.2 s at the task's 500 Hz


# -- models ---------------------------------------------------------------------------------------
def task_arm(name):
    arm = ArmModel(load_task(name))     # the examples' robots are installed (requirements.txt)
    return arm, arm.task.end_effector_site


TASK_MODELS = ['point_reach_3d', 'reach_4dof', 'planar_10dof_reach',
               str(EXAMPLES / 'ur5_reach_over_obstacle.yaml'),
               str(EXAMPLES / 'pusher_reach_over_obstacle.yaml')]     # passive slides


def mixed_chain(rail='type="slide" axis="1 0 0" ref="0.15"'):
    """Every chain element the population IK handles: a passive slide with ref (rail) and a
    passive hinge with ref (idle) on the chain, arm slides with non-unit axes, hinges with
    ref and off-centre anchors, several joints in a body, rotated bodies and site, a free body,
    a mocap body and a hinge off the chain elsewhere."""
    return mujoco.MjModel.from_xml_string(f"""
<mujoco>
  <compiler angle="radian" autolimits="true"/>
  <default><geom type="capsule" size="0.02" mass="0.3"/></default>
  <worldbody>
    <body name="ball" pos="1 1 1"><freejoint/><geom type="sphere" size="0.05"/></body>
    <body name="target" mocap="true" pos="0.3 0.2 0.1"><geom type="sphere" size="0.02"/></body>
    <body name="base" pos="0.1 -0.2 0.5" quat="0.9 0.1 0.3 -0.2">
      <joint name="rail" {rail}/>
      <geom type="box" size="0.05 0.05 0.05"/>
      <body name="carriage" pos="0 0.1 0">
        <joint name="lift" type="slide" axis="0.2 0.1 1" range="-0.3 0.3"/>
        <geom type="box" size="0.03 0.03 0.03"/>
        <body name="upper" pos="0.05 0 0.1" euler="0.3 -0.2 0.5">
          <joint name="yaw" axis="0 0 1" pos="0.02 0.01 0" range="-2 2"/>
          <joint name="pitch" axis="0 1 0" ref="0.4" range="-1 2"/>
          <joint name="spin" axis="1 0 0"/>
          <geom fromto="0 0 0 0.3 0 0"/>
          <body name="fore" pos="0.3 0 0" quat="0.8 0.2 -0.1 0.3">
            <joint name="elbow" axis="0.3 1 0.2" pos="0 0 0.03" ref="-0.2" range="-0.5 2.5"/>
            <joint name="idle" axis="0 0 1" ref="0.7"/>
            <geom fromto="0 0 0 0.25 0 0"/>
            <body name="hand" pos="0.25 0.02 -0.01">
              <joint name="wrist" type="slide" axis="1 0 0" range="-0.05 0.05"/>
              <geom fromto="0 0 0 0.08 0 0"/>
              <site name="tip" pos="0.08 0.01 0.02" quat="0.7 0.1 0.7 0.1"/>
            </body>
          </body>
        </body>
      </body>
    </body>
    <body name="other" pos="-1 0 0"><joint name="other" axis="0 0 1"/>
      <geom fromto="0 0 0 0.1 0 0"/></body>
  </worldbody>
</mujoco>""")


MIXED_ARM = ['elbow', 'lift', 'wrist', 'yaw', 'spin', 'pitch']   # q order != chain order


def mixed_ik(model, joints=MIXED_ARM, site='tip'):
    ids = [model.joint(name).id for name in joints]
    return DifferentialIK(model, site, model.jnt_qposadr[ids], model.jnt_dofadr[ids],
                          q_rest=np.zeros(len(ids)), knot_step=0.0)


def mujoco_kinematics(model, ik, q):
    """Site position (3,), rotation (3, 3), jacp and jacr (3, n) at q on a fresh MjData."""
    data = mujoco.MjData(model)
    data.qpos[ik.qpos_adr] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    mujoco.mj_jacSite(model, data, jacp, jacr, ik.site)
    return (data.site_xpos[ik.site].copy(), data.site_xmat[ik.site].reshape(3, 3).copy(),
            jacp[:, ik.dof_adr], jacr[:, ik.dof_adr])


def matrix_of(quat):
    out = np.empty(9)
    mujoco.mju_quat2Mat(out, quat)
    return out.reshape(3, 3)


def check_kinematics(model, ik, postures):
    population = PopulationIK(ik)
    x, quat = population.pose(postures)
    jacp, jacr = population.chain.jacobians(postures)
    np.testing.assert_array_equal(population.forward(postures), x)
    for k, q in enumerate(postures):
        x_ref, rot_ref, jacp_ref, jacr_ref = mujoco_kinematics(model, ik, q)
        np.testing.assert_allclose(x[k], x_ref, rtol=0, atol=TOL_KINEMATICS)
        np.testing.assert_allclose(matrix_of(quat[k]), rot_ref, rtol=0, atol=TOL_KINEMATICS)
        np.testing.assert_allclose(jacp[k], jacp_ref, rtol=0, atol=TOL_KINEMATICS)
        np.testing.assert_allclose(jacr[k], jacr_ref, rtol=0, atol=TOL_KINEMATICS)


# -- (1) kinematics against MuJoCo ----------------------------------------------------------------
@pytest.mark.parametrize('name', TASK_MODELS)
def test_kinematics_match_mujoco_on_the_task_models(name):
    arm, site = task_arm(name)
    ik = DifferentialIK(arm.model, site, arm.qpos_adr, arm.dof_adr, arm.task.start_posture)
    rng = np.random.default_rng(0)
    # random postures over the joints' ranges and beyond (the kinematics have no limits)
    postures = rng.uniform(-np.pi, np.pi, size=(40, ik.n))
    check_kinematics(arm.model, ik, postures)


def test_kinematics_match_mujoco_on_every_kind_of_chain_element():
    model = mixed_chain()
    ik = mixed_ik(model)
    rng = np.random.default_rng(1)
    postures = rng.uniform(-2.0, 2.0, size=(40, ik.n))
    check_kinematics(model, ik, postures)
    # the batch shape is kept: (2, 20, n) -> (2, 20, 3)
    assert PopulationIK(ik).forward(postures.reshape(2, 20, -1)).shape == (2, 20, 3)


@pytest.mark.parametrize('rail, kind', [('type="ball"', 'ball'), ('type="free"', 'free')])
def test_ball_and_free_joints_on_the_chain_are_refused(rail, kind):
    model = (mixed_chain(rail) if kind == 'ball' else mujoco.MjModel.from_xml_string("""
<mujoco><worldbody><body name="base"><freejoint name="float"/>
  <geom type="sphere" size="0.05"/>
  <body name="link"><joint name="j0" axis="0 0 1"/><geom type="capsule" fromto="0 0 0 0.3 0 0"
    size="0.02"/><site name="tip" pos="0.3 0 0"/></body></body></worldbody></mujoco>"""))
    ik = mixed_ik(model) if kind == 'ball' else mixed_ik(model, ['j0'])
    with pytest.raises(IKError, match=f'{kind} joint .* lies on the chain .* site \'tip\''):
        PopulationIK(ik)


def test_an_arm_joint_off_the_chain_is_refused():
    ik = mixed_ik(mixed_chain(), MIXED_ARM + ['other'])
    with pytest.raises(IKError, match=r"\['other'\] are not on the chain"):
        PopulationIK(ik)


def test_quaternions_and_rotation_vectors_match_mujoco():
    rng = np.random.default_rng(2)
    quats = rng.normal(size=(200, 4))
    quats[:50, 0] = 0.0                                  # rotations by pi
    quats[50:60, 1:] *= 1e-9                             # rotations by nearly 0
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    rotations = np.array([matrix_of(q) for q in quats])
    for quat, mine in zip(quats, quaternion_of(rotations)):
        expected = np.empty(4)
        mujoco.mju_mat2Quat(expected, matrix_of(quat).reshape(9))
        assert min(np.abs(mine - expected).max(), np.abs(mine + expected).max()) < 1e-14
    for quat, mine in zip(quats[50:], rotation_vector(quats[50:])):     # angles < pi
        expected = np.empty(3)
        mujoco.mju_quat2Vel(expected, quat, 1.0)
        np.testing.assert_allclose(mine, expected, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(rotation_vector(quats[:50]), axis=1), np.pi,
                               rtol=1e-14)
    np.testing.assert_array_equal(rotation_vector(-quats), rotation_vector(quats))
    np.testing.assert_allclose(orientation_error(quats, quats), 0.0, rtol=0, atol=1e-12)


# -- (2) the solution against DifferentialIK ------------------------------------------------------
def minimum_jerk(n):
    u = np.linspace(0.0, 1.0, n)
    return 10 * u ** 3 - 15 * u ** 4 + 6 * u ** 5


def line(a, b, n=PATH_SAMPLES, hold=100):
    """From a to b (3,) with minimum-jerk timing, then hold samples at b."""
    path = a + minimum_jerk(n - hold)[:, None] * (np.asarray(b) - a)
    return np.vstack([path, np.repeat(path[-1:], hold, axis=0)])


def circle(start, radius, u, w, n=PATH_SAMPLES):
    """A circle through start in the plane of the unit vectors u, w (centre start - r u)."""
    angle = 2 * np.pi * minimum_jerk(n)[:, None]
    return start + radius * ((np.cos(angle) - 1.0) * np.asarray(u) + np.sin(angle) * w)


@pytest.fixture(scope='module')
def reach():
    """point_reach_3d's DifferentialIK, start posture, grid step and hand paths from the
    start (hand at (0.31, -0.06, -0.53), shoulder at 0, reach 0.65 m): in reach; with the
    shoulder flexion on its lower limit for 260 samples (still in reach); three joints or
    more on limits toward a target they make infeasible (error 0.03 m); a circle that pins
    the elbow on its limit and leaves the reach (0.03 m); out of reach and back (0.14 m
    beyond)."""
    arm, site = task_arm('point_reach_3d')
    task = arm.task
    ik = DifferentialIK(arm.model, site, arm.qpos_adr, arm.dof_adr, task.start_posture,
                        knot_step=0.0)     # every sample, as PopulationIK
    q0 = np.array(task.start_posture)
    x0 = ik.forward(q0)
    half = PATH_SAMPLES // 2
    paths = {
        'in_reach': line(x0, [0.42, 0.0, -0.10]),
        'shoulder_on_limit': line(x0, [-0.35, -0.05, -0.45]),
        'three_on_limits': line(x0, [0.0, 0.0, -0.2]),
        'circle_beyond_reach': circle(x0, 0.1, np.array([1.0, 0, 0]), np.array([0, 0, 1.0])),
        'out_and_back': np.vstack([line(x0, [0.70, 0.1, -0.35], half, 20),
                                   line([0.70, 0.1, -0.35], x0, PATH_SAMPLES - half, 20)]),
    }
    return ik, q0, task.control_period, paths


def test_paths_exercise_limits_and_reach(reach):
    """The premises of the comparisons below: which paths pin joints, which leave the reach."""
    ik, q0, dt, paths = reach
    on_limit = {}
    for name, path in paths.items():
        q = ik.solve(path, q0, dt).q
        on_limit[name] = np.flatnonzero(np.any((q == ik.low) | (q == ik.high), axis=0))
    assert on_limit['in_reach'].size == 0
    assert list(on_limit['shoulder_on_limit']) == [0]
    assert len(on_limit['three_on_limits']) >= 3 and len(on_limit['circle_beyond_reach']) >= 1
    assert ik.solve(paths['out_and_back'], q0, dt).max_error > 0.1


def test_population_matches_differential_ik_along_whole_paths(reach):
    """Candidate by candidate, the whole path within TOL_PATH (q), TOL_PATH (error, m) and
    TOL_PATH / dt (qd); 'out_and_back' within TOL_BEYOND: as the target crosses the edge of
    the reach the arm is stretched (singular) and the steps amplify rounding, by a bounded
    factor since the selective damping of singular directions (the next test)."""
    ik, q0, dt, paths = reach
    names = list(paths)
    results = PopulationIK(ik).solve(np.array([paths[n] for n in names]), q0, dt)
    for name, result in zip(names, results):
        reference = ik.solve(paths[name], q0, dt)
        tol = TOL_BEYOND if name == 'out_and_back' else TOL_PATH
        np.testing.assert_allclose(result.q, reference.q, rtol=0, atol=tol, err_msg=name)
        np.testing.assert_allclose(result.error, reference.error, rtol=0, atol=tol,
                                   err_msg=name)
        np.testing.assert_allclose(result.qd, reference.qd, rtol=0, atol=tol / dt,
                                   err_msg=name)
        assert np.all((result.q >= ik.low) & (result.q <= ik.high)), name


def test_beyond_reach_the_reference_is_reproducible(reach):
    """x_ref changed by one part in 1e15 moves DifferentialIK's q by less than TOL_PATH in
    reach and TOL_BEYOND out of it. (Before the selective damping of singular directions,
    the stretched arm amplified any difference tenfold per sample as the target crossed the
    edge of the reach: 'out_and_back' moved by more than 0.01 rad.)"""
    ik, q0, dt, paths = reach
    for name, path in paths.items():
        q = ik.solve(path, q0, dt).q
        q_nudged = ik.solve(path * (1.0 - 1e-15), q0, dt).q
        tol = TOL_BEYOND if name == 'out_and_back' else TOL_PATH
        assert np.abs(q_nudged - q).max() < tol, name


def test_population_matches_differential_ik_sample_by_sample(reach):
    """Teacher forcing: sample k solved from DifferentialIK's q_{k-1} (a population of T - 1
    one-sample paths) gives DifferentialIK's q_k within TOL_STEP on every path, out of reach
    included: the same step, halving, limit and iteration decisions at every sample."""
    ik, q0, dt, paths = reach
    population = PopulationIK(ik)
    for name, path in paths.items():
        reference = ik.solve(path, q0, dt).q
        steps = population.solve(path[1:, None, :], reference[:-1], dt)
        q = np.array([result.q[0] for result in steps])
        np.testing.assert_allclose(q, reference[1:], rtol=0, atol=TOL_STEP, err_msg=name)


def test_a_start_per_candidate(reach):
    ik, q0, dt, paths = reach
    path = paths['in_reach'][:200]
    starts = q0 + np.array([[0.0] * 7, [0.05, -0.05, 0.1, 0.1, 0.0, 0.1, -0.1]])
    results = PopulationIK(ik).solve(np.array([path, path]), starts, dt)
    for start, result in zip(starts, results):
        np.testing.assert_allclose(result.q, ik.solve(path, start, dt).q, rtol=0, atol=TOL_PATH)
    assert not np.allclose(results[0].q[0], results[1].q[0])


def test_slides_and_a_permuted_chain_match_differential_ik():
    model = mixed_chain()
    ik = mixed_ik(model)
    q0 = np.array([0.8, 0.05, 0.0, 0.3, -0.4, 0.6])
    x0 = ik.forward(q0)
    paths = np.array([line(x0, x0 + [0.05, -0.04, 0.03], 300, 50),
                      line(x0, x0 + [-0.1, 0.1, -0.05], 300, 50)])
    for path, result in zip(paths, PopulationIK(ik).solve(paths, q0, 2e-3)):
        np.testing.assert_allclose(result.q, ik.solve(path, q0, 2e-3).q, rtol=0, atol=TOL_PATH)


def test_a_single_sample(reach):
    ik, q0, dt, paths = reach
    result = PopulationIK(ik).solve(paths['in_reach'][None, 5:6], q0, dt)[0]
    reference = ik.solve(paths['in_reach'][5:6], q0, dt)
    assert result.q.shape == result.qd.shape == (1, 7) and np.all(result.qd == 0.0)
    np.testing.assert_allclose(result.q, reference.q, rtol=0, atol=TOL_STEP)


# -- (3) rows are independent ---------------------------------------------------------------------
def test_one_candidate_alone_equals_it_in_any_population(reach):
    """Row-wise arithmetic only: a candidate's q, qd and error do not depend on the others
    (how many, which, in what order, which of them take further steps, halve or hit limits),
    bit for bit, the chaotic 'out_and_back' included."""
    ik, q0, dt, paths = reach
    population = PopulationIK(ik)
    stacked = np.array(list(paths.values()))
    together = population.solve(stacked, q0, dt)
    order = np.array([3, 0, 4, 2, 1] * 3)                 # 15 candidates, each thrice
    shuffled = population.solve(stacked[order], q0, dt)
    for i, path in enumerate(stacked):
        alone = population.solve(path[None], q0, dt)[0]
        again = [shuffled[j] for j in np.flatnonzero(order == i)]
        for result in [together[i]] + again:
            np.testing.assert_array_equal(result.q, alone.q)
            np.testing.assert_array_equal(result.qd, alone.qd)
            np.testing.assert_array_equal(result.error, alone.error)


SWEEP = 'PSL_OPENBLAS_SWEEP'     # the kernel a sweep's run was asked to take


@pytest.mark.skipif(bool(os.environ.get(SWEEP)), reason='inside the sweep')
def test_rows_are_independent_under_every_openblas_kernel_this_cpu_runs():
    """OpenBLAS blocks a matrix product by its shape, with kernels chosen by CPU
    (test_policy_population.py): the row-independence test above once per kernel
    (OPENBLAS_CORETYPE), as on other CPUs."""
    from psl_bench import openblas
    try:
        outputs = openblas.run_per_kernel(
            [__file__, '-k', 'alone_equals_it_in_any_population or orientation_term'])
    except ValueError as exc:
        pytest.skip(str(exc))
    for kernel, out in outputs.items():
        assert '2 passed' in out, f'with the {kernel} kernel:\n{out[-3000:]}'


# -- (4) refused input ----------------------------------------------------------------------------
def _nan_at(array, index):
    array = np.array(array, dtype=float)
    array[index] = np.nan
    return array


@pytest.mark.parametrize('change, message', [
    (dict(x_ref=np.zeros((5, 3))), r'x_ref must have shape \(P, T, 3\).*\(5, 3\)'),
    (dict(x_ref=np.zeros((2, 5, 2))), r'x_ref must have shape \(P, T, 3\)'),
    (dict(x_ref=np.zeros((2, 0, 3))), r'P, T >= 1, got \(2, 0, 3\)'),
    (dict(x_ref=np.zeros((0, 5, 3))), r'P, T >= 1'),
    (dict(x_ref=_nan_at(np.zeros((2, 5, 3)), (1, 3, 2))),
     'x_ref must be finite; candidate 1 is not at sample 3'),
    (dict(q0=np.zeros(6)), r'q0 must have shape \(7,\) or \(2, 7\), got \(6,\)'),
    (dict(q0=np.zeros((3, 7))), r'q0 must have shape .* got \(3, 7\)'),
    (dict(q0=_nan_at(np.zeros((2, 7)), (1, 4))), 'q0 must be finite; candidate 1'),
    (dict(dt=0.0), 'dt must be finite and > 0'),
    (dict(dt=np.nan), 'dt must be finite and > 0'),
    (dict(orientation_ref=np.ones((2, 5))), r'orientation_ref must have shape \(2, 5, 4\)'),
    (dict(orientation_ref=np.ones((2, 5, 4)) * 0.5 + [0, 0, 0, 1e-3]),
     'unit quaternions .* candidate 0 at sample 0 has norm'),
    (dict(orientation_ref=_nan_at(np.ones((2, 5, 4)) * 0.5, (0, 2, 1))),
     'orientation_ref must be finite; candidate 0 is not at sample 2'),
    (dict(orientation_ref=np.ones((2, 5, 4)) * 0.5, orientation_weight=0.0),
     'orientation_weight must be finite and > 0'),
])
def test_bad_input_is_refused(reach, change, message):
    ik = reach[0]
    arguments = dict(x_ref=np.zeros((2, 5, 3)), q0=np.zeros(7), dt=0.002)
    with pytest.raises(IKError, match=message):
        PopulationIK(ik).solve(**{**arguments, **change})


# -- orientation (issue 26) -----------------------------------------------------------------------
def test_a_reachable_pose_path_is_tracked_with_the_orientation_term(reach):
    """Poses along joint paths (forward kinematics, so reachable exactly): with the
    orientation term the hand follows position and orientation; without it the position only,
    the orientation drifts where the redundancy and the null-space pull take it."""
    ik, q0, dt, _ = reach
    population = PopulationIK(ik)
    s = minimum_jerk(PATH_SAMPLES)[:, None]
    goals = np.array([[0.411, 0.059, 0.041, 1.625, -0.007, 0.25, -0.017],
                      [0.9, 0.4, -0.6, 1.2, 0.8, -0.5, 0.3]])
    joint_paths = q0 + s * (goals[:, None, :] - q0)                 # (2, T, 7)
    x_ref, quat_ref = population.pose(joint_paths)
    posed = population.solve(x_ref, q0, dt, orientation_ref=quat_ref, orientation_weight=0.1)
    plain = population.solve(x_ref, q0, dt)
    for k, (with_term, without) in enumerate(zip(posed, plain)):
        angle = orientation_error(population.pose(with_term.q)[1], quat_ref[k])
        angle_without = orientation_error(population.pose(without.q)[1], quat_ref[k])
        assert with_term.max_error < TOL_POSE_POSITION and angle.max() < TOL_POSE_ANGLE
        assert without.max_error < TOL_POSE_POSITION
        assert angle_without.max() > 1e-2 and angle_without.max() > 100 * angle.max()
    # rows stay independent with the term too
    alone = population.solve(x_ref[1:], q0, dt, orientation_ref=quat_ref[1:],
                             orientation_weight=0.1)[0]
    np.testing.assert_array_equal(alone.q, posed[1].q)


def test_without_orientation_reference_the_weight_changes_nothing(reach):
    ik, q0, dt, paths = reach
    population = PopulationIK(ik)
    x_ref = np.array([paths['circle_beyond_reach']])
    default = population.solve(x_ref, q0, dt)[0]
    weighted = population.solve(x_ref, q0, dt, orientation_ref=None, orientation_weight=5.0)[0]
    np.testing.assert_array_equal(default.q, weighted.q)


def test_the_serial_pose_solve_matches_the_population_one(reach):
    """DifferentialIK's six-dimensional step (mju_* calls, MuJoCo's quaternions and
    Jacobians) against PopulationIK's (numpy, the chain's Rodrigues kinematics): the same
    algorithm in two floating-point orders, along a pose path in reach."""
    ik, q0, dt, paths = reach
    population = PopulationIK(ik)
    s = minimum_jerk(PATH_SAMPLES)[:, None]
    goal = np.array([0.9, 0.4, -0.6, 1.2, 0.8, -0.5, 0.3])
    x_ref, quat_ref = population.pose(q0 + s * (goal - q0))
    serial = ik.solve(x_ref, q0, dt, orientation_ref=quat_ref)
    side = population.solve(x_ref[None], q0, dt, orientation_ref=quat_ref[None],
                            orientation_weight=ik.orientation_weight)[0]
    np.testing.assert_allclose(serial.q, side.q, rtol=0, atol=TOL_PATH)
    np.testing.assert_allclose(serial.rotation_error,
                               orientation_error(population.pose(side.q)[1], quat_ref),
                               rtol=0, atol=TOL_KINEMATICS)
    assert serial.max_error < TOL_POSE_POSITION and serial.rotation_error.max() < TOL_POSE_ANGLE
