"""A reward component cannot hurt the others or the session (psl_optimizer.reward.Reward with
components of a package on the Python path, registered by its metadata): a write into any of
its inputs fails its rollouts and changes nothing the others see; what is not a finite real
cost is refused; a call past the task's reward.component_timeout fails its population, and the
component's later calls fail at once until it returns; a session that could score nothing says
so (psl_optimizer.learning.nothing_scored)."""
import importlib
import re
import sys
import textwrap
import threading
import time

import numpy as np
import pytest
import yaml

from psl_optimizer.learning import nothing_scored
from psl_optimizer.metrics import TaskRecord
from psl_optimizer.reward import FAILED, Reward
from psl_task.arm_model import ArmModel
from psl_task.reward_geometry import RewardGeometry
from psl_task.task import load_task

WAIT = 30.0         # s a test waits at most for what comes at once when all is well
TIMEOUT = 1.0       # s reward.component_timeout of the slow component's task
# what each writer writes: every input a component gets
WRITES = {
    'q': 'r.q[:] = 0.0',
    'torque': 'r.torque[0, 0, 0] = 1.0',
    'q_ref': 'r.q_ref[:] += 1.0',
    'end_effector': 'r.measured.end_effector[:] = 0.0',
    'end_effector_quat': 'r.measured.end_effector_quat[..., 0] = 1.0',
    'distance': 'r.measured.distance[:] = 1.0',
    'world_poses': "r.world['obstacle'][:] = 0.0",
    'measured_world': "r.measured.world['obstacle'][0, 0, 0] = 5.0",
    'world_mapping': "r.world['obstacle'] = None",
    'taus': 'r.taus[:] = 0.0',
    'goal_position': 'r.goal_position[:] = 0.0',
    'goal_rotation': 'r.goal_rotation[:] = 0.0',
    'task_weights': "r.task.reward.weights['goal_error'] = 0.0",
    'task_weights_cleared': 'r.task.reward.weights.clear()',
    'task_posture': 'r.task.goal_posture[:] = 0.0',
    'task_gains': 'r.task.controller.kp[:] = 0.0',
    'task_tau_range': 'r.task.parameters[0].binds.offset = 1.0',
}
PLUGIN = '\n'.join([
    'import threading', 'import numpy as np',
    'RELEASE = threading.Event()', 'ENTERED = []', 'WRITTEN = []',
    *(f'def writes_{kind}(r):\n    {code}\n    return np.zeros(len(r))'
      for kind, code in WRITES.items()),
    textwrap.dedent('''
    def writes_all_quietly(r):
        """A careless component: it writes wherever it can and goes on."""
        for kind, write in WRITERS.items():
            try:
                write(r)
                WRITTEN.append(kind)
            except Exception:
                pass
        return np.zeros(len(r))

    def returns_complex(r):
        return np.full(len(r), 1.0 + 2.0j)

    def returns_text(r):
        return ['0.5'] * len(r)

    def returns_too_many(r):
        return np.zeros(len(r) + 1)

    def returns_inf(r):
        return np.full(len(r), np.inf)

    def returns_none(r):
        return None

    def exits(r):
        raise SystemExit('plugin exit')

    def slow_until_released(r):
        ENTERED.append(len(r))
        RELEASE.wait(60.0)
        return np.zeros(len(r))
    '''),
    'WRITERS = {' + ', '.join(f'{k!r}: writes_{k}' for k in WRITES) + '}',
])
NAMES = ([f'writes_{kind}' for kind in WRITES]
         + ['writes_all_quietly', 'returns_complex', 'returns_text', 'returns_too_many',
            'returns_inf', 'returns_none', 'exits', 'slow_until_released'])


@pytest.fixture(scope='module')
def plugin(tmp_path_factory):
    """The components as an installed package would register them: a module and its
    dist-info (entry points) in a folder on the Python path while this module runs."""
    site = tmp_path_factory.mktemp('site')
    (site / 'psl_guard_costs.py').write_text(PLUGIN)
    info = site / 'psl_guard_costs-0.0.1.dist-info'
    info.mkdir()
    (info / 'METADATA').write_text('Metadata-Version: 2.1\nName: psl-guard-costs\n'
                                   'Version: 0.0.1\n')
    (info / 'entry_points.txt').write_text(
        '[psl.reward_components]\n' + ''.join(f'{n} = psl_guard_costs:{n}\n' for n in NAMES))
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(site))
        importlib.invalidate_caches()
        yield importlib.import_module('psl_guard_costs')
    sys.modules.pop('psl_guard_costs', None)


def task_with(folder, weights: dict, **reward_keys):
    """reach_over_obstacle observing its obstacle (world poses), `weights` (in this order)
    before its own."""
    plain = load_task('reach_over_obstacle')
    data = yaml.safe_load(plain.path.read_text())
    data['model'] = str(plain.model_path)
    data['name'] = 'guarded_' + '_'.join(weights)[:80]
    data['reward'] = {**data['reward'], 'observe': ['obstacle'], **reward_keys,
                      'weights': {**weights, **data['reward']['weights']}}
    path = folder / f"{data['name']}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_task(str(path))


def population(task, count: int = 3):
    """What batch mode gives the reward: joint angles, torques, reference, the geometry along
    them with the obstacle's poses, and the instances, for `count` rollouts."""
    rng = np.random.default_rng(1)
    steps, n = task.num_steps + 1, task.n_joints
    path = np.linspace(task.start_posture, task.goal_posture, steps)
    q = path + 0.01 * rng.standard_normal((count, steps, n))
    torque = rng.standard_normal((count, steps, n))
    q_ref = np.broadcast_to(path, q.shape).copy()
    taus = np.array([task.sample_tau(rng) for _ in range(count)])
    geometry = RewardGeometry(ArmModel(task))
    world = {'obstacle': np.tile([0.6, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0], (count, steps, 1))}
    measured = geometry.replay(q, taus, world)
    # goals given as after a goal change (graph mode): arrays of psl's, as the others
    goal_positions = np.tile(geometry.end_effector_at(task.goal_posture), (count, 1))
    goal_rotations = np.tile(np.eye(3), (count, 1, 1))
    return geometry, (q, torque, q_ref, measured, taus, goal_positions, goal_rotations)


def copies(inputs):
    q, torque, q_ref, measured, taus, goal_positions, goal_rotations = inputs
    return [a.copy() for a in (q, torque, q_ref, measured.end_effector,
                                measured.end_effector_quat, measured.distance,
                                measured.world['obstacle'], taus, goal_positions,
                                goal_rotations)]


@pytest.mark.parametrize('kind', WRITES)
def test_a_write_into_any_input_fails_the_rollouts_and_changes_nothing(plugin, tmp_path,
                                                                        kind):
    name = f'writes_{kind}'
    task = task_with(tmp_path, {name: 1.0})
    weights = dict(task.reward.weights)
    geometry, inputs = population(task)
    before = copies(inputs)
    results = Reward(task, geometry).evaluate(*inputs)
    for result in results:
        assert result.failure.startswith(f'reward component {name!r} raised '), result.failure
        assert any(error in result.failure for error in (
            'ValueError: assignment destination is read-only',
            'ValueError: output array is read-only',
            "TypeError: 'mappingproxy' object does not support item",
            "AttributeError: 'mappingproxy' object has no attribute 'clear'",
            'ValidationError')), result.failure
        assert result.reward == task.safety.penalty and result.components == {FAILED: 1.0}
    for old, new in zip(before, copies(inputs)):
        assert np.array_equal(old, new)
    again = load_task(str(task.path))               # load_task's cached task: as it was
    assert dict(again.reward.weights) == weights
    assert np.array_equal(again.goal_posture, load_task('reach_over_obstacle').goal_posture)
    assert again.controller.kp.all() and again.parameters[0].binds.offset == 0.0


def test_a_careless_writer_changes_no_other_components_cost(plugin, tmp_path):
    careless = task_with(tmp_path, {'writes_all_quietly': 1.0})
    plain = task_with(tmp_path, {})
    geometry, inputs = population(careless)
    before = copies(inputs)
    mine = Reward(careless, geometry).evaluate(*inputs)
    assert plugin.WRITTEN == [], f'written: {plugin.WRITTEN}'
    theirs = Reward(plain, geometry).evaluate(*inputs)
    for a, b in zip(mine, theirs):
        assert a.failure == '' and a.reward == b.reward and a.fulfilled == b.fulfilled
        assert a.components == {**b.components, 'writes_all_quietly': 0.0}
    for old, new in zip(before, copies(inputs)):
        assert np.array_equal(old, new)


@pytest.mark.parametrize('name, reason', [
    ('returns_complex', r"reward component 'returns_complex' returned complex numbers "
                        r'\(\(1\+2j\), \.\.\.\), not real costs'),
    ('returns_text', r"reward component 'returns_text' returned text \('0.5', \.\.\.\), "
                     'not real costs'),
    ('returns_too_many', r"reward component 'returns_too_many' returned shape \(2,\), not one "
                         r'cost per rollout \(1,\)'),
    ('returns_none', r"reward component 'returns_none' returned Python objects \(None"),
    ('returns_inf', r"reward component 'returns_inf' returned inf \(not finite\)"),
    ('exits', r"reward component 'exits' raised SystemExit: plugin exit"),
])
def test_what_is_not_a_finite_real_cost_fails_every_rollout_with_the_reason(plugin, tmp_path,
                                                                            name, reason):
    task = task_with(tmp_path, {name: 1.0})
    geometry, inputs = population(task)
    for result in Reward(task, geometry).evaluate(*inputs):   # each tried alone: the same
        assert not result.fulfilled and result.reward == task.safety.penalty
        assert re.fullmatch(reason + '.*', result.failure), result.failure


def test_a_slow_component_fails_its_populations_until_its_call_returns(plugin, tmp_path):
    task = task_with(tmp_path, {'slow_until_released': 1.0}, component_timeout=TIMEOUT)
    plain = task_with(tmp_path, {})
    geometry, inputs = population(task)
    reward = Reward(task, geometry)
    try:
        late = reward.evaluate(*inputs)
        assert [r.failure for r in late] == [
            "reward component 'slow_until_released' did not return within 1 s "
            '(reward.component_timeout)'] * 3
        assert plugin.ENTERED == [3]
        for _ in range(3):   # its call still runs: its populations fail without a new call
            assert {r.failure for r in reward.evaluate(*inputs)} == {
                "reward component 'slow_until_released' has not returned from a call that "
                'passed its 1 s (reward.component_timeout): its rollouts fail until it does'}
        assert plugin.ENTERED == [3]
        assert all(r.failure == '' for r in Reward(plain, geometry).evaluate(*inputs))
    finally:
        plugin.RELEASE.set()
    deadline, results = time.monotonic() + WAIT, None
    while time.monotonic() < deadline:      # once its call has returned it is called again
        results = reward.evaluate(*inputs)
        if results[0].failure == '':
            break
        time.sleep(0.01)
    assert plugin.ENTERED == [3, 3]
    plain_results = Reward(plain, geometry).evaluate(*inputs)
    assert [r.reward for r in results] == [r.reward for r in plain_results]
    threads = sum(t.name == 'psl reward component' for t in threading.enumerate())
    assert threads <= 3


def test_after_a_failure_of_every_rollout_no_further_component_is_called(plugin, tmp_path):
    task = task_with(tmp_path, {'returns_complex': 1.0, 'slow_until_released': 1.0},
                     component_timeout=TIMEOUT)
    geometry, inputs = population(task)
    entered = len(plugin.ENTERED)
    results = Reward(task, geometry).evaluate(*inputs)
    assert all('returns_complex' in r.failure for r in results)
    assert len(plugin.ENTERED) == entered


def record(rollouts: int, failed: int, refused: int = 0, failure: str = '') -> TaskRecord:
    return TaskRecord(index=0, tau=[0.0], rollouts=rollouts, fulfilled=False, best_reward=-100.0,
                      start_reward=-100.0, seconds=1.0, refused=refused, failed=failed,
                      failure=failure)


def test_a_session_that_scored_nothing_says_why():
    assert nothing_scored([record(4, 0), record(4, 0)]) == ''
    assert nothing_scored([record(4, 4, failure='a'), record(4, 3, failure='b')]) == ''
    assert nothing_scored([record(4, 0, refused=4)]) == ''        # nothing failed: the task's
    assert nothing_scored([record(4, 4, failure='a'), record(5, 3, refused=2, failure='b')]) == (
        "the reward scored none of the session's 9 rollouts (7 not scored, 2 refused by the "
        'safety check): b')
    assert nothing_scored([record(6, 6, failure="reward component 'x' raised")]) == (
        "the reward scored none of the session's 6 rollouts (6 not scored): reward component "
        "'x' raised")
