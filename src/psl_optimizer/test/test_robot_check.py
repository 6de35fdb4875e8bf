"""psl check: the robot report against independent references (MuJoCo's inverse dynamics for
the gravity torque, the model's masses) and its warnings on tasks made to trigger them."""
import subprocess
import sys

import mujoco
import numpy as np
import pytest
import yaml

from psl_optimizer.robot_check import REACH_WARNING, SAG_WARNING, check_robot, format_report
from psl_task.arm_model import ArmModel
from psl_task.task import EMBEDDED_TASKS, load_task


def variant(tmp_path, name, change, xml=lambda text: text):
    data = yaml.safe_load((EMBEDDED_TASKS / f'{name}.yaml').read_text())
    model = data['model']
    change(data)
    (tmp_path / model).write_text(xml((EMBEDDED_TASKS / model).read_text()))
    path = tmp_path / f'{name}_variant.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_task(str(path))


def test_the_gravity_sag_is_the_inverse_dynamics_torque_over_kp():
    task = load_task('payload_transport')
    report = check_robot(task)
    arm = ArmModel(task)
    arm.reset(task.tau_default)
    data = mujoco.MjData(arm.model)
    data.qpos[arm.qpos_adr] = task.start_posture
    mujoco.mj_inverse(arm.model, data)               # at rest, zero acceleration: gravity
    np.testing.assert_allclose(report.sag_rad['start'],
                               data.qfrc_inverse[arm.dof_adr] / task.controller.kp, rtol=1e-9)
    assert report.sag_hand['start'] > 0.05            # the compliant arm sags by centimetres
    assert not report.warnings                         # ... and has feed-forward on
    total = sum(arm.model.body_mass[1:])               # the shoulder moves every body
    assert report.joints[0].mass_carried == pytest.approx(total)


def test_no_gravity_no_sag():
    report = check_robot(load_task('reach_over_obstacle'))
    assert all(np.all(s == 0) for s in report.sag_rad.values())
    assert [j.name for j in report.joints] == ['joint1', 'joint2', 'joint3']
    assert [j.torque_limit for j in report.joints] == [40.0, 40.0, 40.0]   # the MJCF's


def test_sag_without_feedforward_is_a_warning_with_the_fix(tmp_path):
    task = variant(tmp_path, 'payload_transport',
                   lambda d: d['policy'].update(feedforward=False))
    report = check_robot(task)
    assert report.sag_hand['start'] > SAG_WARNING
    (warning,) = report.warnings
    assert 'gravity sag' in warning and 'policy.feedforward: true' in warning


def test_saturation_is_a_warning_naming_the_joints(tmp_path):
    """The embedded arm with motors of 1 N m (its demonstration needs up to about 2)."""
    report = check_robot(variant(tmp_path, 'reach_over_obstacle', lambda d: None,
                                 lambda xml: xml.replace('ctrlrange="-40 40"',
                                                         'ctrlrange="-1 1"')))
    assert report.saturated_share > 0.01
    assert any('torque saturation' in w and 'joint1' in w for w in report.warnings)


def test_psl_check_prints_the_table():
    done = subprocess.run([sys.executable, '-m', 'psl_cli.main', 'check', '--task',
                           'point_reach_3d'], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert 'shoulder_flexion' in done.stdout and 'site palm' in done.stdout
    task = load_task('point_reach_3d')
    report, components = done.stdout.strip().split('\nreward components ')
    assert report == format_report(check_robot(task))
    # then every registered component, the task's weight beside those it uses
    listed = {line.split()[-4]: line.split() for line in components.splitlines()[1:]}
    assert set(listed) >= set(task.reward.weights) | {'orientation_error', 'clearance'}
    for name, weight in task.reward.weights.items():
        assert listed[name][:3] == ['*', f'{weight:g}', name], listed[name]


def test_gravity_compensation_removes_the_sag(tmp_path):
    """robot.gravity_compensation: MuJoCo's gravcomp cancels the weight of the moving bodies:
    no sag left, and the arm holds its start posture with zero torque."""
    task = variant(tmp_path, 'payload_transport', lambda d: d.update(
        robot={'model': d.pop('model'), 'end_effector': {'site': d.pop('end_effector_site')},
               'gravity_compensation': True}))
    report = check_robot(task)
    assert max(report.sag_hand.values()) < 1e-9
    arm = ArmModel(task)
    arm.reset(task.tau_default)
    for _ in range(200):
        arm.step(np.zeros(task.n_joints))
    np.testing.assert_allclose(arm.q, task.start_posture, atol=1e-6)


def test_psl_learn_says_the_warnings_before_it_learns(tmp_path):
    """The same words on the command that would suffer from them, one line each."""
    task = variant(tmp_path, 'reach_over_obstacle', lambda d: None,
                   lambda xml: xml.replace('ctrlrange="-40 40"', 'ctrlrange="-1 1"'))
    done = subprocess.run([sys.executable, '-m', 'psl_cli.main', 'learn', '--task',
                           str(task.path), '--tasks', '1', '--budget', '4', '--test-tasks', '1',
                           '-o', str(tmp_path / 'run')], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    warnings = [line for line in done.stderr.splitlines() if 'warning' in line]
    assert len(warnings) == 1, done.stderr
    assert warnings[0].startswith('psl learn: warning: torque saturation') and \
        f'(psl check --task {task.path})' in warnings[0]


def test_a_posture_at_a_joint_limit_is_a_warning(tmp_path):
    """The Pusher's wrist flex at 0, the upper end of its range [-1.09, 0]: the safety check
    would refuse every candidate that bends it further; the check names the joint."""
    from pathlib import Path
    source = Path(__file__).resolve().parents[3] / 'examples' / 'pusher_reach_over_obstacle.yaml'
    data = yaml.safe_load(source.read_text())
    for key in ('start_posture', 'goal_posture'):
        data[key][5] = 0.0
    for row in data['demonstration']['positions']:
        row[5] = 0.0
    path = tmp_path / 'pusher_at_limit.yaml'
    path.write_text(yaml.safe_dump(data))
    report = check_robot(load_task(str(path)))
    (warning,) = report.warnings
    assert warning.startswith('postures at a joint limit: r_wrist_flex_joint;')
    assert not check_robot(load_task(str(source))).warnings


def test_a_target_range_out_of_reach_is_a_warning(tmp_path):
    """point_reach_3d's target box within reach: every corner's default movement ends at the
    target; its x range moved 0.5 m out, beyond the arm's reach: every corner is far (over
    0.1 m) and the warning says how many and what to change."""
    task = load_task('point_reach_3d')
    report = check_robot(task)
    assert len(report.reach) == 8 and max(miss for _, miss in report.reach) < 1e-3
    assert not any('out of reach' in w for w in report.warnings)
    far = variant(tmp_path, 'point_reach_3d', lambda d: d['task_parameters'][0].update(
        low=d['task_parameters'][0]['low'] + 0.5, high=d['task_parameters'][0]['high'] + 0.5))
    report = check_robot(far)
    assert min(miss for _, miss in report.reach) > 0.1
    (warning,) = [w for w in report.warnings if 'out of reach' in w]
    assert 'at 8 of the 8 corners' in warning and 'target_position ranges' in warning


def test_a_target_orientation_range_out_of_reach_is_a_warning(tmp_path):
    """pose_reach_3d's yaw range (+-0.3 rad) is reached at all 16 corners (its orientation
    goal turned to each target); widened to +-2.5 rad the arm's ranges stop the hand short
    at some: the warning counts them and names what to change."""
    from psl_optimizer.robot_check import orientation_reach
    task = load_task('pose_reach_3d')
    turns = orientation_reach(task)
    assert len(turns) == 16 and max(angle for _, angle in turns) < 1e-2
    assert not any('orientations out of reach' in w for w in check_robot(task).warnings)
    wide = variant(tmp_path, 'pose_reach_3d', lambda d: d['task_parameters'][3].update(
        low=3.085 - 2.5, high=3.085 + 2.5))
    turns = orientation_reach(wide)
    assert max(angle for _, angle in turns) > 0.1
    (warning,) = [w for w in check_robot(wide).warnings if 'orientations out of reach' in w]
    weight, threshold = wide.reward.weights['orientation_error'], wide.reward.success_threshold
    far = sum(weight * angle > REACH_WARNING * abs(threshold) for _, angle in turns)
    assert far > 0
    assert f'at {far} of the 16 corners' in warning
    assert 'target_orientation ranges' in warning


@pytest.mark.parametrize('joint, attribute, cause', [
    ('joint1', 'frictionloss="200"', 'frictionloss 200 N m'),
    ('joint3', 'damping="500"', 'damping 500 N m s/rad')])
def test_a_joint_its_own_friction_or_damping_holds_is_named(tmp_path, joint, attribute, cause):
    """reach_over_obstacle's joint1 (kp 300, its motor 40 N m) given 200 N m of friction (a
    static error up to 0.67 rad; its reference moves it 1.2 rad), or joint3 (kp 100) 500 N m
    s/rad of damping (a time constant of 5 s against the 1.5 s movement): the demonstration
    leaves it behind and the warning names it, the cause and what to change; as published,
    no joint is named, nor is payload_transport's elbow, which lags 0.25 rad under gravity by
    design (its feed-forward is learned), with neither friction nor damping to blame."""
    assert not any('do not follow' in w for w in check_robot(load_task('reach_over_obstacle'))
                   .warnings)
    assert not any('do not follow' in w for w in check_robot(load_task('payload_transport'))
                   .warnings)
    held = variant(tmp_path, 'reach_over_obstacle', lambda d: None,
                   lambda text: text.replace(f'<joint name="{joint}"/>',
                                             f'<joint name="{joint}" {attribute}/>'))
    (warning,) = [w for w in check_robot(held).warnings if 'do not follow' in w]
    assert f'{joint} up to' in warning and cause in warning
    assert 'raise their controller.kp' in warning
    assert sum(f'joint{k} up to' in warning for k in (1, 2, 3)) == 1


def test_the_saturation_warning_names_the_gain_whose_torque_saturates(tmp_path):
    """Weak motors (1 N m) under the task's gains: the error's kp e term makes most of the
    torque where it saturates; gains with a tenfold kd: the kd e' term. The split is held
    against the demonstration stepped here on the arm with the measured velocity itself
    (ArmModel.step, the graph's stepping: psl's PD law on each state), and the advice gives
    the gain rule's gains for the task."""
    from psl_controller.pd_law import law_for
    from psl_controller.policy import policy_for
    from psl_task.gain_rule import arm_gains
    weak = variant(tmp_path, 'reach_over_obstacle', lambda d: None,
                   lambda xml: xml.replace('ctrlrange="-40 40"', 'ctrlrange="-1 1"'))
    (tmp_path / 'kd').mkdir()
    damped = variant(tmp_path / 'kd', 'reach_over_obstacle',
                     lambda d: d['controller'].update(kd=[200.0, 120.0, 50.0]))
    for task, gain in ((weak, 'kp'), (damped, 'kd')):
        report = check_robot(task)
        arm = ArmModel(task)
        arm.reset(task.tau_default)
        policy, law = policy_for(task), law_for(task)
        ref = policy.reference(policy.default_theta, task.tau_default)
        sums = np.zeros(3)
        for k in range(len(ref.t) - 1):
            q, qd = arm.q.copy(), arm.qd.copy()
            u = law.torque(q, qd, ref.q[k], ref.qd[k], ref.u_ffwd[k])
            at = np.abs(u) >= law.torque_high - 1e-9
            sums += [np.sum(np.abs(part[at])) for part in (
                law.kp * (ref.q[k] - q), law.kd * (ref.qd[k] - qd), ref.u_ffwd[k])]
            arm.step(u)
        np.testing.assert_allclose([report.saturation_parts[name] for name in
                                    ('kp', 'kd', 'feed-forward')], sums / sums.sum(), atol=1e-9)
        assert report.saturation_parts[gain] > 0.5
        (warning,) = [w for w in report.warnings if w.startswith('torque saturation')]
        words = 'kp e' if gain == 'kp' else "kd e'"
        assert f'of the torque there {words} makes ' in warning, warning
        assert f'lower controller.{gain},' in warning
        rule = arm_gains(arm)
        assert warning.endswith(f'picks {rule.controller_yaml()}')
        assert report.rule_gains.controller_yaml() == rule.controller_yaml()
        pasted = yaml.safe_load(rule.controller_yaml())['controller']
        np.testing.assert_allclose(pasted['kp'], rule.kp, rtol=5e-3)   # 3 digits
        np.testing.assert_allclose(pasted['kd'], rule.kd, rtol=5e-3)
    assert check_robot(load_task('reach_over_obstacle')).saturation_parts == {}


def payload_hand(q: np.ndarray) -> np.ndarray:
    """payload_transport.xml's closed form: shoulder at (0, 0, 0.6), links 0.4 and 0.35 m in
    the x-z plane, positive angles lift."""
    a, b = q[0], q[0] + q[1]
    return np.array([0.4 * np.cos(a) + 0.35 * np.cos(b), 0.0,
                     0.6 + 0.4 * np.sin(a) + 0.35 * np.sin(b)])


def test_the_hand_at_the_start_and_goal_postures():
    task = load_task('payload_transport')
    report = check_robot(task)
    for label, q in (('start', task.start_posture), ('goal', task.goal_posture)):
        np.testing.assert_allclose(report.hand[label], payload_hand(q), atol=1e-12)
    text = format_report(report)
    x, y, z = payload_hand(task.start_posture)
    assert f'hand at the start posture: ({x:.3f}, {y:.3f}, {z:.3f}) m' in text


def test_the_closest_approach_to_a_singular_posture(tmp_path):
    """The 2-link arm's position manipulability is l1 l2 |sin q2| (Yoshikawa 1985), over
    L^2 = (l1 + l2)^2: its least value along the demonstration's reference, where and at the
    start; an elbow straightened at the start (sin q2 = 0) is a warning naming it."""
    from psl_controller.policy import policy_for

    def closed_form(task):
        policy = policy_for(task)
        q = policy.reference(policy.default_theta, task.tau_default).q
        return 0.4 * 0.35 * np.abs(np.sin(q[:, 1])) / 0.75 ** 2, q

    task = load_task('payload_transport')
    report = check_robot(task)
    w, q = closed_form(task)
    k = int(np.argmin(w))
    m = report.manipulability
    assert (m.rank, m.length) == (2, pytest.approx(0.75, rel=1e-12))
    assert (m.start, m.minimum) == (pytest.approx(w[0], rel=1e-9), pytest.approx(w[k], rel=1e-9))
    assert m.t == pytest.approx(k * task.control_period) and np.array_equal(m.q, q[k])
    assert not any('singular' in x for x in report.warnings)
    planar = check_robot(load_task('reach_over_obstacle')).manipulability   # 3 joints, a plane
    assert planar.rank == 2 and planar.minimum > 0.1
    assert 'closest to a singular posture along the demonstration: manipulability ' \
        f'{w[k]:.3g} of L^2 (L = 0.75 m) at t = {k * task.control_period:.3g} s' \
        in format_report(report)

    def straight(d):
        d['start_posture'][1] = 0.0
        d['demonstration']['positions'][0][1] = 0.0
    stretched = variant(tmp_path, 'payload_transport', straight)
    report = check_robot(stretched)
    assert report.manipulability.minimum < 1e-6 and report.manipulability.t == 0.0
    (warning,) = [x for x in report.warnings if 'singular' in x]
    assert warning.startswith('near a singular posture: the hand\'s manipulability falls to ')
    assert 'at t = 0 s' in warning


def test_a_refused_demonstration_is_a_warning_not_a_crash(tmp_path):
    """A demonstration the safety check refuses (its velocity past safety.max_velocity) runs
    nothing: the check says so, with the reason, and reports the rest."""
    task = variant(tmp_path, 'reach_over_obstacle',
                   lambda d: d.setdefault('safety', {}).update(max_velocity=0.5))
    report = check_robot(task)
    assert report.saturated_share == 0.0 and report.manipulability is not None
    (warning,) = [w for w in report.warnings if 'refused' in w]
    assert warning.startswith('the demonstration is refused by the safety check (joint ')


def test_a_demonstration_the_safety_check_refuses_is_a_warning(tmp_path):
    """A demonstration faster than the task's velocity bound runs nothing: psl check says so
    (it raised a TypeError on the missing torque; psl init met it on the SO-ARM100's 1 rad/s
    joints)."""
    task = variant(tmp_path, 'reach_4dof', lambda d: d.update(safety={'max_velocity': 0.05}))
    report = check_robot(task)
    assert report.saturated_share == 0.0
    assert any(w.startswith('the demonstration is refused by the safety check') and
               'velocity' in w for w in report.warnings), report.warnings
