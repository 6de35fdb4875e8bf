"""The limits psl's own goals keep, through the graph (issue 46): each case starts a graph of
its own (its own task or controller parameters), in a file of its own, so no other graph of the
worker runs beside it on the worker's ROS domain."""
from psl_controller.policy import policy_for
from psl_ros.client import RosClient
from psl_ros.graph import NODES, Graph
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
LOOP = tuple(n for n in NODES if n[0] not in ('skill_memory', 'learner'))


def test_a_homing_whose_model_needs_more_than_the_torque_limits_is_taken(tmp_path):
    """ball_throw driven back to its start after a throw: along the homing the model's
    inverse dynamics asks up to 202 N m of the shoulder (80 N m: the ball in its cup near the
    start), which pd_controller rejects as a goal's effort; psl clips the homing's
    feed-forward into the limits, so the second rollout homes and runs. Before: "pd_controller
    rejected the goal"."""
    task = load_task('ball_throw')
    theta = policy_for(task).default_theta
    g = Graph(task='ball_throw', reset='drive', log_dir=tmp_path / 'logs', nodes=LOOP)
    try:
        g.start()
        g.wait_ready(timeout=60)
        with RosClient() as client:
            results = [client.rollout('ball_throw', task.tau_default, theta, timeout=120)
                       for _ in range(2)]
    finally:
        g.stop()
    assert all(r.success for r in results), [r.message for r in results]


def test_a_controller_narrower_than_the_model_rejects_saying_so(tmp_path):
    """pd_controller with max_velocity 0.5 rad/s, below the arm's (100 rad/s) and the
    default reference's 4 rad/s: the safety check passes the candidate (the model allows
    it), the controller rejects its goal, and the rollout fails saying the controller's limits
    may be narrower than the model's and where to look."""
    task = load_task(TASK)
    g = Graph(task=TASK, log_dir=tmp_path / 'logs', nodes=LOOP,
              extra_params={'pd_controller': {'max_velocity': 0.5}})
    try:
        g.start()
        g.wait_ready(timeout=60)
        with RosClient() as client:
            result = client.rollout(TASK, task.tau_default, policy_for(task).default_theta,
                                    timeout=120)
    finally:
        g.stop()
    assert not result.success
    assert ("pd_controller rejected the goal (its limits may be narrower than the model's: "
            'see its log)') in result.message, result.message
    assert not result.refused
