"""``psl render`` (psl_cli.render): a short rollout drawn into a GIF by MuJoCo's offscreen
renderer (in a fresh process, as the command runs) and by the matplotlib stick figure; the
fallback from one to the other; bad input refused with one line and exit code 2."""
import argparse
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image, ImageChops

from psl_cli import render
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
FPS = 5.0                       # frames per second of simulated time: few frames, fast
SIZE = (160, 120)               # px
EPISODE = 2.0                   # s, reach_over_obstacle: duration 1.5 + settle 0.5
FRAMES = int(EPISODE * FPS) + 1     # t = 0, 0.2, ..., 2.0 s
FRAME_MS = 200                  # 1 / FPS


@pytest.fixture(autouse=True)
def gl_environment(monkeypatch):
    """run() sets MUJOCO_GL for this process; keep it from the later tests' processes."""
    monkeypatch.delenv('MUJOCO_GL', raising=False)


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    render.add_arguments(parser)
    return parser.parse_args(list(argv))


def check_gif(path) -> None:
    """An animated GIF of the requested size, the whole episode long, whose frames differ."""
    with Image.open(path) as gif:
        assert gif.format == 'GIF' and gif.size == SIZE
        assert gif.n_frames >= 3
        frames, total_ms = [], 0
        for k in range(gif.n_frames):
            gif.seek(k)
            frames.append(gif.convert('RGB'))
            total_ms += gif.info['duration']
    # Pillow merges identical consecutive frames (the arm at rest) and adds up their durations
    assert total_ms == FRAMES * FRAME_MS
    assert ImageChops.difference(frames[0], frames[gif.n_frames // 2]).getbbox() is not None
    assert ImageChops.difference(frames[0], frames[-1]).getbbox() is not None


def test_frames_sample_the_episode_at_the_frame_rate():
    task = load_task(TASK)
    steps = render.frame_steps(task.num_steps, task.control_rate, FPS)
    np.testing.assert_array_equal(steps, np.arange(FRAMES) * 100)      # every 0.2 s = 100 steps
    steps = render.frame_steps(task.num_steps, task.control_rate, 30.0)
    assert steps[0] == 0 and steps[-1] == task.num_steps and len(steps) == 61


def test_mujoco_renders_a_short_rollout_in_a_fresh_process(tmp_path):
    """As ``psl render`` runs: MUJOCO_GL unset, run() picks EGL before mujoco loads."""
    out = tmp_path / 'rollout.gif'
    done = subprocess.run([sys.executable, '-m', 'psl_cli.main', 'render', '--task', TASK,
                           '--fps', str(FPS), '--size', *map(str, SIZE), '-o', str(out)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert 'MuJoCo offscreen renderer (MUJOCO_GL=egl)' in done.stdout
    assert 'failed' not in done.stdout
    check_gif(out)


def test_the_stick_figure_draws_the_same_rollout(tmp_path, capsys):
    out = tmp_path / 'rollout.gif'
    code = render.run(parse('--task', TASK, '--fps', str(FPS), '--size', *map(str, SIZE),
                            '--renderer', 'matplotlib', '-o', str(out)))
    assert code == 0
    assert 'matplotlib stick figure' in capsys.readouterr().out
    check_gif(out)


def test_auto_falls_back_to_the_stick_figure_and_says_why(tmp_path, capsys, monkeypatch):
    def no_gl(replay, width, height):
        raise RuntimeError('no OpenGL context\nsecond line')

    monkeypatch.setitem(render.RENDER, 'mujoco', (no_gl, 'MuJoCo offscreen renderer'))
    out = tmp_path / 'rollout.gif'
    code = render.run(parse('--fps', str(FPS), '--size', *map(str, SIZE), '-o', str(out)))
    printed = capsys.readouterr().out
    assert code == 0
    assert 'matplotlib stick figure' in printed and 'failed: no OpenGL context' in printed
    assert 'second line' not in printed
    check_gif(out)
    # asked for MuJoCo only: no fallback, exit code 1 and the reason
    code = render.run(parse('--renderer', 'mujoco', '-o', str(tmp_path / 'other.gif')))
    err = capsys.readouterr().err
    assert code == 1 and err.count('\n') == 1 and 'no OpenGL context' in err
    assert not (tmp_path / 'other.gif').exists()


@pytest.mark.parametrize('argv, words', [
    (['--tau', '0.6'], 'takes 2 task parameters'),
    (['--tau', '0.6', '0.9'], 'outside its range'),
    (['--task', 'no_such_task'], 'unknown task'),
    (['--theta-file', 'THETA'], 'takes theta with 24 entries'),
    (['--fps', '0'], '--fps'),
    (['--size', '0', '10'], '--size'),
    (['-o', 'rollout.mp4'], 'no video encoder'),
    (['-o', 'rollout.png'], 'must be a .gif'),
    (['-o', 'missing/rollout.gif'], 'does not exist'),
])
def test_bad_input_is_refused_with_one_line_and_exit_code_2(tmp_path, capsys, argv, words):
    theta = tmp_path / 'theta.txt'
    theta.write_text('1 2 3')
    argv = [str(theta) if a == 'THETA' else a for a in argv]
    argv = [str(tmp_path / a) if a.startswith(('rollout.', 'missing/')) else a for a in argv]
    if '-o' not in argv:
        argv += ['-o', str(tmp_path / 'rollout.gif')]
    code = render.run(parse(*argv))
    captured = capsys.readouterr()
    assert code == 2
    assert captured.err.count('\n') == 1 and captured.err.startswith('psl render: ')
    assert words in captured.err and 'Traceback' not in captured.err
    assert captured.out == ''
    assert not list(tmp_path.glob('rollout.*'))


def test_a_thrown_ball_is_drawn_where_it_was_measured():
    """ball_throw: each frame puts the observed ball at the pose the rollout measured (its
    flight), not where a kinematic replay of the arm would leave it (in the cup)."""
    task = load_task('ball_throw')
    from psl_controller.policy import policy_for

    replay = render.replay_rollout(task, task.tau_default, policy_for(task).default_theta,
                                   fps=10.0)
    body = replay.arm.body('ball')
    heights = []
    for step in replay.frames():
        np.testing.assert_array_equal(replay.arm.data.xpos[body],
                                      replay.world['ball'][step, :3])
        heights.append(replay.arm.data.xpos[body][2])
    assert max(heights) > 1.2 and heights[-1] < 0.03         # up in the air, then down


def test_passive_joints_are_drawn_as_simulated(tmp_path):
    """The Unitree G1's left arm from its full-body URDF, nothing locked: every frame draws
    the body where the rollout simulated it (its torso and right leg measured by MuJoCo's
    sensors during the rollout, reward.observe), falling, not where it started."""
    import yaml

    from psl_controller.policy import policy_for

    observed = ['torso_link', 'right_knee_link', 'right_wrist_yaw_link']
    arm = ['left_shoulder_pitch_joint', 'left_shoulder_roll_joint', 'left_shoulder_yaw_joint',
           'left_elbow_joint', 'left_wrist_roll_joint', 'left_wrist_pitch_joint',
           'left_wrist_yaw_joint']
    start, goal = [0.3, 0.3, 0.0, 0.8, 0.0, 0.0, 0.0], [0.0, 0.3, 0.0, 0.3, 0.0, 0.0, 0.0]
    task_file = tmp_path / 'g1.yaml'
    task_file.write_text(yaml.safe_dump({
        'robot': {'model': 'package://example-robot-data/robots/g1_description/urdf/'
                           'g1_29dof_rev_1_0.urdf',
                  'end_effector': {'body': 'left_wrist_yaw_link'}, 'joints': arm,
                  'gravity_compensation': True},
        'control_rate': 500.0, 'duration': 0.6, 'start_posture': start, 'goal_posture': goal,
        'task_parameters': [{'name': 'x', 'low': 0.0, 'high': 1.0,
                             'binds': {'kind': 'target_position', 'axis': 0}}],
        'target': {'position': [0.2, 0.2, 0.1]},
        'controller': {'kp': [70.0, 60.0, 8.0, 14.0, 0.15, 2.0, 0.7],
                       'kd': [7.0, 6.0, 0.8, 1.4, 0.015, 0.2, 0.07]},
        'policy': {'n_basis': 3},
        'demonstration': {'times': [0.0, 0.6], 'positions': [start, goal]},
        'reward': {'weights': {'goal_error': 1.0}, 'success_threshold': -1.0,
                   'observe': observed}}))
    task = load_task(str(task_file))
    replay = render.replay_rollout(task, task.tau_default, policy_for(task).default_theta,
                                   fps=10.0)
    ids = [replay.arm.body(name) for name in observed]
    first = None
    for step in replay.frames():
        data = replay.arm.data
        for name, body in zip(observed, ids):
            np.testing.assert_allclose(data.xpos[body], replay.world[name][step, :3],
                                       rtol=0, atol=1e-12)
            np.testing.assert_allclose(data.xquat[body], replay.world[name][step, 3:],
                                       rtol=0, atol=1e-12)
        if first is None:
            first = data.xpos[ids].copy(), data.xquat[ids[0]].copy()
    turned = 2 * np.arccos(min(1.0, abs(float(data.xquat[ids[0]] @ first[1]))))
    assert turned > 0.1                                          # the torso fell forward
    assert np.linalg.norm(data.xpos[ids[2]] - first[0][2]) > 0.05    # the right hand with it
