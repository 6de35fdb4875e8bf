"""How a reward component is called (psl_task.reward_components): the read-only views of its
inputs, the check of what it returns, and the bound on its call's time (a worker thread that a
call past its bound keeps, while the component's further calls fail at once)."""
import collections
import dataclasses
import threading
import time

import numpy as np
import pytest

from psl_task import reward_components
from psl_task.reward_components import (CALLS, KEPT_WORKERS, ComponentFailed, ComponentTimedOut,
                                        costs, read_only)
from psl_task.task import load_task

WAIT = 30.0     # s a test waits at most for an event that comes at once when all is well


def evaluate(name: str, function, rollouts, timeout: float) -> np.ndarray:
    """`reward_components.evaluate` of one component on a worker, bounded by `timeout` s."""
    return CALLS.run(lambda call: reward_components.evaluate(name, function, rollouts, call),
                     timeout)


def wait_for(condition) -> bool:
    deadline = time.monotonic() + WAIT
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


# -- read-only views ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Inner:
    values: np.ndarray
    names: dict


Pair = collections.namedtuple('Pair', 'left right')


@dataclasses.dataclass(frozen=True)
class Outer:
    inner: Inner
    rows: list
    label: str = 'x'
    pair: Pair = Pair(np.zeros(1), 0)


def test_a_view_refuses_every_write_and_psl_keeps_its_own_arrays():
    array, weights = np.arange(6.0).reshape(2, 3), {'a': 1.0, 'nested': {'b': np.zeros(2)}}
    outer = Outer(Inner(array, weights), [np.ones(2), 3.0])
    view = read_only(outer)
    writes = {
        'an array': lambda: view.inner.values.__setitem__((0, 0), 9.0),
        'an array in place': lambda: np.add(view.inner.values, 1.0, out=view.inner.values),
        'a view of it': lambda: view.inner.values[1:].fill(0.0),
        'a mapping': lambda: view.inner.names.__setitem__('a', 0.0),
        'a mapping emptied': lambda: view.inner.names.clear(),
        'a nested mapping\'s array': lambda: view.inner.names['nested']['b'].fill(1.0),
        'a list': lambda: view.rows.append(1),
        'a list\'s array': lambda: view.rows[0].fill(5.0),
        'a field': lambda: setattr(view, 'label', 'y'),
        'a nested field': lambda: setattr(view.inner, 'values', None),
        'a named tuple\'s array': lambda: view.pair.left.fill(1.0),
    }
    for what, write in writes.items():
        with pytest.raises((ValueError, TypeError, AttributeError)):
            write()
            pytest.fail(f'{what} was written')
    assert np.array_equal(array, np.arange(6.0).reshape(2, 3)) and array.flags.writeable
    assert weights == {'a': 1.0, 'nested': {'b': weights['nested']['b']}}
    assert not weights['nested']['b'].any() and outer.rows[0].tolist() == [1.0, 1.0]
    assert np.array_equal(view.inner.values, array)       # the same numbers, read as before
    assert view.inner.names['a'] == 1.0 and view.label == 'x' and view.rows[1] == 3.0
    assert type(view.pair) is Pair and view.pair.right == 0 and not outer.pair.left.any()
    array[0, 0] = -1.0                                    # psl writes its own: the view follows
    assert view.inner.values[0, 0] == -1.0


def test_a_task_is_read_only_to_components_and_the_cached_task_unchanged():
    task = load_task('reach_over_obstacle')
    view = read_only(task)
    for write in (lambda: view.start_posture.fill(0.0),
                  lambda: view.goal_posture.__setitem__(0, 1.0),
                  lambda: view.controller.kp.fill(0.0),
                  lambda: view.demo_positions.fill(0.0),
                  lambda: view.reward.weights.__setitem__('goal_error', 0.0),
                  lambda: view.reward.weights.clear(),
                  lambda: setattr(view.reward, 'success_threshold', 0.0),
                  lambda: view.package_paths.__setitem__('x', None)):
        with pytest.raises((ValueError, TypeError, AttributeError)):
            write()
    again = load_task('reach_over_obstacle')                 # load_task's cached object
    assert again.reward.weights == task.reward.weights and again.reward.weights['goal_error']
    assert np.array_equal(again.start_posture, view.start_posture)
    assert view.control_period == task.control_period and view.n_joints == task.n_joints
    assert view.tau_names == task.tau_names and view.reward.success_threshold == \
        task.reward.success_threshold


def test_a_dataclass_that_is_not_frozen_is_refused():
    @dataclasses.dataclass
    class Loose:
        value: float = 0.0
    with pytest.raises(TypeError, match='Loose is not a frozen dataclass'):
        read_only(Outer(Inner(np.zeros(1), {}), [Loose()]))


# -- what a component returns ------------------------------------------------------------------
@pytest.mark.parametrize('returned, reason', [
    (np.full(3, 1 + 2j), r"returned complex numbers \(\(1\+2j\), \.\.\.\), not real costs"),
    (np.array(['1.0', '2', '3']), r"returned text \('1.0', \.\.\.\)"),
    (np.array([1.0, None, 2.0], dtype=object), r'returned Python objects \(1.0, \.\.\.\)'),
    (np.zeros((3, 1)), r'returned shape \(3, 1\), not one cost per rollout \(3,\)'),
    (np.zeros(2), r'returned shape \(2,\)'),
    (np.asarray(0.0), r'returned shape \(\), not one cost per rollout \(3,\)'),
])
def test_what_is_not_one_real_cost_per_rollout_is_refused(returned, reason):
    with pytest.raises(ComponentFailed, match=reason):
        costs('mine', returned, 3)


def test_real_costs_are_taken_as_floats_and_copied():
    for returned in (np.array([1, 2, 3]), np.array([1.0, 2.0, 3.0])):
        values = costs('mine', returned, 3)
        assert values.dtype == float and values.tolist() == [1.0, 2.0, 3.0]
        returned[0] = 7                      # the component keeps its array: ours stay
        assert values[0] == 1.0
    assert costs('mine', np.array([True, False]), 2).tolist() == [1.0, 0.0]
    nan = costs('mine', np.array([np.nan, np.inf, 0.0]), 3)      # each its rollout's failure
    assert reward_components.failures('mine', nan) == {
        0: "reward component 'mine' returned nan (not finite)",
        1: "reward component 'mine' returned inf (not finite)"}


def test_a_component_that_raises_or_exits_fails_with_the_reason():
    def exits(_):
        raise SystemExit(3)
    with pytest.raises(ComponentFailed, match="reward component 'exits' raised SystemExit: 3"):
        evaluate('exits', exits, [0, 0], 5.0)
    with pytest.raises(ComponentFailed, match=r"'text' returned text \('a'"):
        evaluate('text', lambda r: ['a', 'b'], [0, 0], 5.0)
    assert evaluate('fine', lambda r: [0.5, 1], [0, 0], 5.0).tolist() == [0.5, 1.0]


# -- the bound on a call's time ----------------------------------------------------------------
def workers() -> int:
    return sum(t.name == 'psl reward component' for t in threading.enumerate())


def test_a_call_past_its_bound_fails_and_its_component_fails_at_once_until_it_returns():
    release, entered = threading.Event(), []

    def slow(rollouts):
        entered.append(len(rollouts))
        release.wait(WAIT)
        return np.zeros(len(rollouts))
    try:
        with pytest.raises(ComponentTimedOut, match=r"reward component 'slow' did not return "
                           r'within 0.2 s \(reward.component_timeout\)'):
            evaluate('slow', slow, [0, 0], 0.2)
        assert entered == [2]
        for _ in range(5):      # its call still runs: no new call, no new thread
            with pytest.raises(ComponentTimedOut, match=r"reward component 'slow' has not "
                               r'returned from a call that passed its 0.2 s'):
                evaluate('slow', slow, [0, 0], 0.2)
            # the other components are called meanwhile, on another worker
            assert evaluate('fast', lambda r: np.ones(len(r)), [0], 0.2).tolist() == [1.0]
        assert entered == [2] and workers() <= KEPT_WORKERS + 1
    finally:
        release.set()
    # once its call has returned, the component is called again
    assert wait_for(lambda: 'slow' not in CALLS._late)
    assert evaluate('slow', slow, [0, 0, 0], 5.0).tolist() == [0.0, 0.0, 0.0]
    assert entered == [2, 3] and workers() <= KEPT_WORKERS


def test_calls_reuse_their_threads():
    before, threads = workers(), []

    def fast(rollouts):
        threads.append(threading.current_thread())      # kept: no two alike by accident
        return np.full(len(rollouts), len(threads))
    for k in range(1, 51):
        assert evaluate('fast', fast, [0, 0], 5.0).tolist() == [k, k]
    assert len(set(threads)) <= KEPT_WORKERS and workers() <= max(before, KEPT_WORKERS)
