"""The dynamics modality through the real path: theta_D -> JointTrajectory effort field ->
pd_controller -> sim, as separate processes, against batch mode, on payload_transport."""
import numpy as np
import pytest

from psl_controller.policy import policy_for
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.inverse_dynamics import oracle_theta
from psl_task.task import load_task

TASK = 'payload_transport'


@pytest.fixture(scope='module')
def graph_task():
    """The module's graph (conftest) runs the payload task."""
    return TASK


def test_graph_and_batch_agree_with_a_nonzero_feedforward(graph_matches_batch):
    task = load_task(TASK)
    policy = policy_for(task)
    tau = np.array([2.4])                                        # kg of payload
    theta = oracle_theta(task, tau, policy.default_theta)
    rng = np.random.default_rng(3)
    theta[policy.dynamics] += rng.normal(0.0, 1.0, policy.feedforward.num_parameters)   # N m
    u_ffwd = policy.reference(theta).u_ffwd
    assert np.abs(u_ffwd).max(axis=0).min() > 5.0                 # N m on every joint
    _, batch = graph_matches_batch(task, tau, theta)
    # the feed-forward acts: PD alone (theta_D = 0) tracks at least twice as badly
    pd_only = theta.copy()
    pd_only[policy.dynamics] = 0.0
    alone = BatchRollouts(task).run(pd_only[None], tau)[0]
    assert (2 * batch.evaluation.components['tracking_error']
            < alone.evaluation.components['tracking_error'])
