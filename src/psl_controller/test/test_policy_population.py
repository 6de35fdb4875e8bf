"""A population's references in one pass equal the references one by one, within rounding.

What is promised (docs/testing.md, "What is equal to what"): the population's matrix products
have other shapes than one rollout's, so BLAS may block and sum them in another order, and
which order it takes depends on the CPU (OpenBLAS chooses its kernels by CPU and by shape:
with its SkylakeX kernels the two agree bit for bit, with its Haswell kernels, which AMD EPYC
machines run, they differ in the last bits). So the promise is equality within ULPS units in
the last place of each field's largest magnitude, and the last test holds that promise under
every OpenBLAS kernel this CPU can run.
"""
import os

import numpy as np
import pytest

from psl_controller.policy import TaskPolicy
from psl_task.task import load_task

# joint space with and without feed-forward, a learned goal, durations that vary per
# instance, and end-effector space (which goes one by one)
TASKS = ('reach_over_obstacle', 'payload_transport', 'planar_10dof_reach',
         'payload_transport_timed', 'point_reach_3d')
ULPS = 16     # measured: at most 0.6 ulps of a field's largest magnitude on every kernel


def assert_equal_within_rounding(actual: np.ndarray, desired: np.ndarray) -> None:
    """|actual - desired| <= ULPS ulps of desired's largest magnitude, element by element."""
    assert actual.shape == desired.shape
    scale = float(np.abs(desired).max(initial=0.0))
    np.testing.assert_allclose(actual, desired, rtol=0.0, atol=ULPS * np.spacing(scale))


# end-effector space goes one by one (TaskPolicy.references): the path of one theta, row by
# row, so a few rows show it; under another OpenBLAS kernel it is that path again (the IK's own
# rows: test_population_ik.py, under every kernel too)
ONE_BY_ONE = {'point_reach_3d': 3}


@pytest.mark.parametrize('name', TASKS)
def test_references_of_a_population_are_those_of_each_theta(name):
    task = load_task(name)
    population, single = TaskPolicy(task), TaskPolicy(task)
    rows = ONE_BY_ONE.get(name, 9)
    rng = np.random.default_rng(3)
    default = population.default_theta
    thetas = default + rng.normal(0.0, 0.05 * max(1.0, np.abs(default).max()),
                                  (rows, default.size))
    taus = np.array([task.sample_tau(rng) for _ in range(rows)])
    references = population.references(thetas, taus)
    assert len(references) == rows
    for reference, theta, tau in zip(references, thetas, taus):
        one = single.reference(theta, tau)
        np.testing.assert_array_equal(reference.t, one.t)       # the same grid, no BLAS
        for field in ('q', 'qd', 'u_ffwd'):
            assert_equal_within_rounding(getattr(reference, field), getattr(one, field))
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
            assert_equal_within_rounding(getattr(many, field)[b], getattr(one, field))


def test_a_bad_row_is_named():
    task = load_task('reach_over_obstacle')
    policy = TaskPolicy(task)
    thetas = np.tile(policy.default_theta, (3, 1))
    thetas[1, 2] = np.nan
    with pytest.raises(ValueError, match='theta 1: theta contains NaN'):
        policy.references(thetas, np.tile(task.tau_default, (3, 1)))
    with pytest.raises(ValueError, match='one task instance per row'):
        policy.references(thetas, np.tile(task.tau_default, (2, 1)))
    with pytest.raises(ValueError, match=r'thetas must be \(P, '):
        policy.dmp.integrate_population(0.01, thetas[:, :5])


SWEEP = 'PSL_OPENBLAS_SWEEP'     # the kernel a sweep's run was asked to take


@pytest.mark.skipif(bool(os.environ.get(SWEEP)), reason='inside the sweep')
def test_the_promise_holds_under_every_openblas_kernel_this_cpu_runs():
    """The tests above, once per OpenBLAS kernel (OPENBLAS_CORETYPE), as on other CPUs; the
    tasks whose populations go one by one (`ONE_BY_ONE`) left out: the same path as one
    theta under any kernel."""
    from psl_bench.openblas import run_per_kernel
    try:
        outputs = run_per_kernel([__file__, '-k', 'not every_openblas_kernel and not '
                                  + ' and not '.join(ONE_BY_ONE)])
    except ValueError as exc:
        pytest.skip(str(exc))
    for kernel, out in outputs.items():     # every test ran, and passed
        assert ' passed' in out and 'skipped' not in out, \
            f'with the {kernel} kernel:\n{out[-3000:]}'
