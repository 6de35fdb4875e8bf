"""JointSelection: the task's joints out of a robot's joint states, by name."""

import numpy as np
import pytest

from psl_task.joint_selection import JointSelection, MissingJoints


def test_any_order_and_extra_joints():
    select = JointSelection(['a', 'b', 'c'])
    names = ['gripper', 'c', 'a', 'b']
    values = [9.0, 3.0, 1.0, 2.0]
    assert select.pick(names, values).tolist() == [1.0, 2.0, 3.0]
    # a random permutation with extras: every joint's own value, by name
    rng = np.random.default_rng(0)
    for _ in range(20):
        order = list(rng.permutation(['a', 'b', 'c', 'x', 'y']))
        values = {name: float(rng.normal()) for name in order}
        got = select.pick(order, [values[n] for n in order])
        assert got.tolist() == [values['a'], values['b'], values['c']]


def test_an_empty_field_stays_empty():
    assert JointSelection(['a']).pick(['a', 'b'], []).size == 0


def test_a_missing_joint_is_named():
    with pytest.raises(MissingJoints, match=r"lack the joint 'b' .*list a, c"):
        JointSelection(['a', 'b']).indices(['a', 'c'])


def test_a_ragged_field_and_repeated_joints_are_refused():
    with pytest.raises(ValueError, match='2 values for 3 names'):
        JointSelection(['a']).pick(['a', 'b', 'c'], [1.0, 2.0])
    with pytest.raises(ValueError, match='repeat'):
        JointSelection(['a', 'a'])
