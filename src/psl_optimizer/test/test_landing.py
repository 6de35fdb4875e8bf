"""Where a thrown body lands (psl_optimizer.landing) against the closed form of a ballistic
flight, and the throwing task's observed ball in batch mode."""
import numpy as np
import pytest

from psl_optimizer.landing import landing_points
from psl_task.task import TaskError, load_task

G = 9.81
DT = 0.002


def flight(p0, v0, height, steps=2000):
    """Positions (T, 7) of a ballistic flight sampled every DT (orientation: identity), and
    the exact point where z comes down through `height`."""
    t = np.arange(steps) * DT
    p = np.asarray(p0) + np.outer(t, v0) + np.outer(0.5 * t**2, [0.0, 0.0, -G])
    vz, dz = v0[2], p0[2] - height
    t_hit = (vz + np.sqrt(vz**2 + 2 * G * dz)) / G          # z(t) = height, going down
    exact = np.asarray(p0) + np.asarray(v0) * t_hit + 0.5 * t_hit**2 * np.array([0, 0, -G])
    return np.hstack([p, np.tile([1.0, 0, 0, 0], (steps, 1))]), exact


@pytest.mark.parametrize('p0, v0', [((0.0, 0.0, 1.2), (3.0, 0.5, 2.0)),
                                    ((-0.5, 0.1, 0.8), (2.0, -0.3, -1.0))])
def test_the_landing_point_is_where_the_flight_comes_down_through_the_height(p0, v0):
    poses, exact = flight(p0, v0, height=0.025)
    point, landed = landing_points(poses[None], np.array([0.025]))
    assert landed[0]
    # linear interpolation between states DT apart: z is off by at most G DT^2 / 8, which
    # moves the crossing by that over the vertical speed there (> 1 m/s here)
    assert np.abs(point[0] - exact).max() < G * DT**2 / 8 * np.hypot(*v0[:2]) + 1e-12
    assert point[0, 2] == pytest.approx(0.025, abs=1e-12)


def test_a_body_that_never_comes_down_is_taken_where_it_ends():
    poses, _ = flight((0.0, 0.0, 1.0), (1.0, 0.0, 3.0), height=0.0, steps=100)   # still rising
    point, landed = landing_points(poses[None], np.array([0.0]))
    assert not landed[0]
    np.testing.assert_array_equal(point[0], poses[-1, :3])


def test_each_rollout_of_a_population_lands_as_it_would_alone():
    a, _ = flight((0.0, 0.0, 1.0), (2.0, 0.0, 1.0), 0.025, steps=800)
    b, _ = flight((0.0, 0.0, 1.5), (3.0, 0.2, 0.0), 0.025, steps=800)
    both, landed = landing_points(np.stack([a, b]), np.array([0.025, 0.025]))
    for i, alone in enumerate((a, b)):
        one, _ = landing_points(alone[None], np.array([0.025]))
        np.testing.assert_array_equal(both[i], one[0])
    assert landed.all()


def test_an_observed_body_the_model_lacks_is_refused(tmp_path):
    from psl_optimizer.batch_rollout import BatchRollouts

    task = load_task('ball_throw')
    source = task.path.read_text().replace('observe: [ball]', 'observe: [bal]')
    (tmp_path / 'ball_throw.xml').write_text(task.model_path.read_text())
    path = tmp_path / 'throw.yaml'
    path.write_text(source)
    with pytest.raises(TaskError, match="'bal'"):
        BatchRollouts(load_task(str(path)))


def test_the_balls_sensor_is_its_frame_as_the_simulator_publishes_it():
    """Batch mode's sensor readings of the ball are ArmModel.body_pose of the same states
    (what the simulator node publishes on world/ball/pose)."""
    import mujoco

    from psl_controller.policy import policy_for
    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_task.arm_model import ArmModel

    task = load_task('ball_throw')
    result = BatchRollouts(task).run(policy_for(task).default_theta[None], task.tau_default)[0]
    sensed = result.world['ball']
    assert sensed.shape == (task.num_steps + 1, 7)
    # the same states stepped again in the task's model, with the law the batch ran
    arm = ArmModel(task)
    arm.reset(task.tau_default)
    body = arm.body('ball')
    np.testing.assert_array_equal(arm.body_pose(body), sensed[0])
    assert sensed[:, 2].max() > 1.2 and sensed[-1, 2] < 0.03      # thrown, and landed
    assert np.allclose(np.linalg.norm(sensed[:, 3:], axis=1), 1.0, atol=1e-9)
    assert mujoco.mj_name2id(arm.model, mujoco.mjtObj.mjOBJ_BODY, 'ball') == body


def test_a_drive_reset_puts_the_observed_ball_back_in_the_cup():
    """ArmModel.place (a drive reset: the arm stays where it is) puts the bodies the reward
    observes back at their model pose, at rest; a teleport reset does the same."""
    from psl_task.arm_model import ArmModel

    task = load_task('ball_throw')
    arm = ArmModel(task)
    arm.reset(task.tau_default)
    rest = arm.body_pose(arm.body('ball')).copy()
    arm.set_body_pose('ball', np.array([1.2, 0.1, 0.025, 1.0, 0.0, 0.0, 0.0]))   # landed
    arm.data.qvel[:] = 0.5
    arm.place(task.tau_default)
    np.testing.assert_array_equal(arm.body_pose(arm.body('ball')), rest)
    ball = arm.model.body('ball')
    dofs = slice(arm.model.jnt_dofadr[ball.jntadr[0]], arm.model.jnt_dofadr[ball.jntadr[0]] + 6)
    assert not arm.data.qvel[dofs].any()
    assert (arm.data.qvel[arm.dof_adr] == 0.5).all()       # the arm itself is left as it is
