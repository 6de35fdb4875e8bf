"""A population's references in one pass equal the references one by one, bit for bit."""
import numpy as np
import pytest

from psl_controller.policy import TaskPolicy
from psl_sim.task import load_task

# joint space with and without feed-forward, a learned goal, durations that vary per
# instance, and end-effector space (which goes one by one)
TASKS = ('reach_over_obstacle', 'payload_transport', 'planar_10dof_reach',
         'payload_transport_timed', 'point_reach_3d')


@pytest.mark.parametrize('name', TASKS)
def test_references_of_a_population_are_those_of_each_theta(name):
    task = load_task(name)
    population, single = TaskPolicy(task), TaskPolicy(task)
    rng = np.random.default_rng(3)
    default = population.default_theta
    thetas = default + rng.normal(0.0, 0.05 * max(1.0, np.abs(default).max()),
                                  (9, default.size))
    taus = np.array([task.sample_tau(rng) for _ in range(9)])
    references = population.references(thetas, taus)
    assert len(references) == 9
    for reference, theta, tau in zip(references, thetas, taus):
        one = single.reference(theta, tau)
        for field in ('t', 'q', 'qd', 'u_ffwd'):
            np.testing.assert_array_equal(getattr(reference, field), getattr(one, field))
    if name == 'payload_transport_timed':          # the durations did differ
        assert len({len(r.t) for r in references}) > 1


def test_dmp_population_equals_set_theta_then_integrate():
    policy = TaskPolicy(load_task('planar_10dof_reach'))     # learns the goal
    dmp = policy.dmp
    rng = np.random.default_rng(4)
    thetas = dmp.get_theta() + rng.normal(0.0, 0.2, (5, dmp.num_parameters))
    many = dmp.integrate_population(0.01, thetas, 0.7)
    assert many.y.shape == (5, 71, dmp.n_dims) and many.y.flags.c_contiguous
    for b, theta in enumerate(thetas):
        dmp.set_theta(theta)
        one = dmp.integrate(0.01, 0.7)
        for field in ('y', 'yd', 'ydd'):
            np.testing.assert_array_equal(getattr(many, field)[b], getattr(one, field))


def test_a_bad_row_is_named():
    task = load_task('reach_over_obstacle')
    policy = TaskPolicy(task)
    thetas = np.tile(policy.default_theta, (3, 1))
    thetas[1, 2] = np.nan
    with pytest.raises(ValueError, match='theta 1: theta contains NaN'):
        policy.references(thetas, np.tile(task.tau_default, (3, 1)))
    with pytest.raises(ValueError, match='one task instance per row'):
        policy.references(thetas, np.tile(task.tau_default, (2, 1)))
    with pytest.raises(ValueError, match=r'thetas must be \(B, '):
        policy.dmp.integrate_population(0.01, thetas[:, :5])
