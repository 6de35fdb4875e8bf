"""Tests of task definitions: loading, the search path, validation and sampling of tau."""

import copy
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from psl_task.task import (EMBEDDED_TASKS, TaskDefinition, TaskError, find_task_file, list_tasks,
                          load_task, task_id)

DEFAULT_TASK = 'reach_over_obstacle'
EMBEDDED_YAML = EMBEDDED_TASKS / f'{DEFAULT_TASK}.yaml'
EMBEDDED_XML = EMBEDDED_TASKS / f'{DEFAULT_TASK}.xml'

# Hand-copied from reach_over_obstacle.yaml (an independent reference, not read back).
TAU_NAMES = ['obstacle_x', 'obstacle_height']
TAU_LOW = np.array([0.55, 0.10])
TAU_HIGH = np.array([0.80, 0.22])
TAU_DEFAULT = np.array([0.675, 0.16])
NUM_STEPS = 1000  # (duration 1.5 s + settle 0.5 s) * 500 Hz

N_SAMPLES = 2000
SAMPLE_COVERAGE = 0.05  # uniform samples reach within this fraction of each range end


def embedded_data():
    return yaml.safe_load(EMBEDDED_YAML.read_text())


def write_task(folder, data, name='my_task', copy_model=True):
    """Write a task YAML (and a copy of the embedded MJCF next to it) into folder."""
    folder.mkdir(parents=True, exist_ok=True)
    if copy_model:
        shutil.copy(EMBEDDED_XML, folder / data['model'])
    path = folder / f'{name}.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


# -- the embedded task ------------------------------------------------------------------------
def test_embedded_task_loads_by_name():
    task = load_task(DEFAULT_TASK)
    assert isinstance(task, TaskDefinition)
    assert task.name == DEFAULT_TASK
    assert task.path == EMBEDDED_YAML.resolve()
    assert task.model_path == EMBEDDED_XML.resolve()
    assert DEFAULT_TASK in list_tasks()


def test_embedded_task_parameters_and_ranges():
    task = load_task(DEFAULT_TASK)
    assert task.tau_names == TAU_NAMES
    np.testing.assert_array_equal(task.tau_low, TAU_LOW)
    np.testing.assert_array_equal(task.tau_high, TAU_HIGH)
    np.testing.assert_array_equal(task.tau_default, TAU_DEFAULT)
    assert np.all(task.tau_low <= task.tau_default) and np.all(task.tau_default <= task.tau_high)


def test_embedded_task_timing():
    task = load_task(DEFAULT_TASK)
    data = embedded_data()
    assert task.control_rate == data['control_rate']
    assert task.duration == data['duration']
    assert task.settle_time == data['settle_time']
    assert task.num_steps == NUM_STEPS
    assert task.num_steps == round((data['duration'] + data['settle_time'])
                                   * data['control_rate'])
    assert task.control_period == pytest.approx(1.0 / 500.0, abs=1e-15)
    assert task.control_period_ns == 2_000_000


def test_embedded_task_postures_and_demonstration_shapes():
    task = load_task(DEFAULT_TASK)
    data = embedded_data()
    assert task.n_joints == 3
    np.testing.assert_array_equal(task.start_posture, data['start_posture'])
    np.testing.assert_array_equal(task.goal_posture, data['goal_posture'])
    assert task.controller.kp.shape == task.controller.kd.shape == (3,)
    assert task.demo_positions.shape == (len(task.demo_times), 3)
    # The demonstration goes from the start posture to the goal posture.
    np.testing.assert_array_equal(task.demo_positions[0], task.start_posture)
    np.testing.assert_array_equal(task.demo_positions[-1], task.goal_posture)


def test_unknown_task_name_lists_known_tasks():
    with pytest.raises(TaskError) as info:
        load_task('no_such_task_xyz')
    message = str(info.value)
    assert 'no_such_task_xyz' in message
    assert 'known tasks' in message
    assert DEFAULT_TASK in message


def test_missing_yaml_path_raises():
    with pytest.raises(TaskError, match='does not exist'):
        load_task('/nonexistent/folder/task.yaml')


# -- validate_tau -----------------------------------------------------------------------------
@pytest.mark.parametrize('tau', [[0.7], [0.7, 0.2, 0.1], [], [[0.7, 0.2]]])
def test_validate_tau_wrong_size(tau):
    task = load_task(DEFAULT_TASK)
    with pytest.raises(TaskError) as info:
        task.validate_tau(tau)
    message = str(info.value)
    assert 'takes 2 task parameters' in message
    assert 'obstacle_x' in message and 'obstacle_height' in message


@pytest.mark.parametrize('bad', [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize('index', [0, 1])
def test_validate_tau_non_finite(bad, index):
    task = load_task(DEFAULT_TASK)
    tau = TAU_DEFAULT.copy()
    tau[index] = bad
    with pytest.raises(TaskError, match='finite'):
        task.validate_tau(tau)


@pytest.mark.parametrize('index, value', [
    (0, 0.55 - 1e-6), (0, 0.80 + 1e-6), (1, 0.10 - 1e-6), (1, 0.22 + 1e-6), (1, -5.0)])
def test_validate_tau_out_of_range(index, value):
    task = load_task(DEFAULT_TASK)
    tau = TAU_DEFAULT.copy()
    tau[index] = value
    with pytest.raises(TaskError) as info:
        task.validate_tau(tau)
    message = str(info.value)
    assert TAU_NAMES[index] in message
    assert 'outside its range' in message
    assert f'{TAU_LOW[index]:g}' in message and f'{TAU_HIGH[index]:g}' in message


@pytest.mark.parametrize('tau', [TAU_DEFAULT, TAU_LOW, TAU_HIGH, [0.6, 0.2], (0.8, 0.15)])
def test_validate_tau_in_range_returns_float_array(tau):
    task = load_task(DEFAULT_TASK)
    result = task.validate_tau(tau)
    assert isinstance(result, np.ndarray)
    assert result.dtype == float and result.shape == (2,)
    np.testing.assert_array_equal(result, np.asarray(tau, dtype=float))


# -- loading from other places ----------------------------------------------------------------
def test_load_by_yaml_path(tmp_path):
    data = embedded_data()
    data['name'] = 'copied_task'
    data['duration'] = 1.0
    data['demonstration']['times'] = [0.0, 0.5, 1.0]
    path = write_task(tmp_path, data)
    task = load_task(str(path))
    assert task.name == 'copied_task'
    assert task.path == path.resolve()
    assert task.model_path == (tmp_path / data['model']).resolve()
    assert task.duration == 1.0
    assert task.num_steps == round((1.0 + data['settle_time']) * data['control_rate'])


def test_load_embedded_by_yaml_path_equals_by_name():
    by_path = load_task(str(EMBEDDED_YAML))
    by_name = load_task(DEFAULT_TASK)
    assert by_path.path == by_name.path
    np.testing.assert_array_equal(by_path.start_posture, by_name.start_posture)


def test_task_path_environment_adds_folder(tmp_path, monkeypatch):
    folder = tmp_path / 'extra_tasks'
    data = embedded_data()
    data.pop('name')   # the name defaults to the file stem
    write_task(folder, data, name='extra_reach')
    monkeypatch.setenv('PSL_TASK_PATH', f'{tmp_path / "empty_missing"}:{folder}')
    assert 'extra_reach' in list_tasks()
    assert DEFAULT_TASK in list_tasks()           # the embedded folder stays on the path
    assert find_task_file('extra_reach') == (folder / 'extra_reach.yaml').resolve()
    task = load_task('extra_reach')
    assert task.name == 'extra_reach'
    assert task.path == (folder / 'extra_reach.yaml').resolve()


def test_task_path_environment_unset_does_not_find_extra_task(tmp_path, monkeypatch):
    write_task(tmp_path, embedded_data(), name='hidden_reach')
    monkeypatch.delenv('PSL_TASK_PATH', raising=False)
    assert 'hidden_reach' not in list_tasks()
    with pytest.raises(TaskError, match='unknown task'):
        load_task('hidden_reach')


# -- the model path: absolute, ~, or relative to the YAML's folder -----------------------------
def test_model_given_by_absolute_path(tmp_path):
    data = embedded_data()
    data['model'] = str(EMBEDDED_XML.resolve())
    task = load_task(str(write_task(tmp_path / 'elsewhere', data, copy_model=False)))
    assert task.model_path == EMBEDDED_XML.resolve()


def test_relative_model_path_is_relative_to_the_yaml_not_the_working_dir(tmp_path, monkeypatch):
    (tmp_path / 'robots').mkdir()
    shutil.copy(EMBEDDED_XML, tmp_path / 'robots' / 'arm.xml')
    data = embedded_data()
    data['model'] = '../robots/arm.xml'
    path = write_task(tmp_path / 'tasks', data, copy_model=False)
    monkeypatch.chdir(tmp_path)                 # from here '../robots/arm.xml' does not exist
    task = load_task(str(path))
    assert task.model_path == (tmp_path / 'robots' / 'arm.xml').resolve()


def test_model_path_with_home_folder(tmp_path, monkeypatch):
    monkeypatch.setenv('HOME', str(tmp_path / 'home'))
    (tmp_path / 'home').mkdir()
    shutil.copy(EMBEDDED_XML, tmp_path / 'home' / 'arm.xml')
    data = embedded_data()
    data['model'] = '~/arm.xml'
    task = load_task(str(write_task(tmp_path / 'tasks', data, copy_model=False)))
    assert task.model_path == (tmp_path / 'home' / 'arm.xml').resolve()


def test_task_id_is_the_name_when_the_name_finds_the_file(tmp_path, monkeypatch):
    monkeypatch.delenv('PSL_TASK_PATH', raising=False)
    assert task_id(load_task(DEFAULT_TASK)) == DEFAULT_TASK
    assert task_id(load_task(str(EMBEDDED_YAML))) == DEFAULT_TASK
    off_path = load_task(str(write_task(tmp_path, embedded_data(), name='my_robot_task')))
    assert task_id(off_path) == str(off_path.path)            # not on the search path
    assert load_task(task_id(off_path)) is off_path
    renamed = dict(embedded_data(), name='other_name')     # name differs from the file stem
    monkeypatch.setenv('PSL_TASK_PATH', str(tmp_path / 'on_path'))
    on_path = load_task(str(write_task(tmp_path / 'on_path', renamed, name='file_stem')))
    assert task_id(on_path) == str(on_path.path)


TOP_LEVEL_KEYS = ['model', 'end_effector_site', 'control_rate', 'duration', 'start_posture',
                  'goal_posture', 'task_parameters', 'controller', 'policy', 'demonstration',
                  'reward']


@pytest.mark.parametrize('key', TOP_LEVEL_KEYS)
def test_missing_top_level_key_raises(tmp_path, key):
    data = embedded_data()
    model_name = data['model']
    del data[key]
    shutil.copy(EMBEDDED_XML, tmp_path / model_name)
    path = write_task(tmp_path, data, copy_model=False)
    # the model and the end effector may also come from a robot section: the message says so
    words = {'model': 'give the model once, as robot.model',
             'end_effector_site': 'give the end effector once, as robot.end_effector'}
    with pytest.raises(TaskError, match=words.get(key, f'missing key {key!r}')):
        load_task(str(path))


@pytest.mark.parametrize('key', ['weights', 'success_threshold'])
def test_missing_reward_key_raises(tmp_path, key):
    data = embedded_data()
    del data['reward'][key]
    path = write_task(tmp_path, data)
    with pytest.raises(TaskError, match=f'missing key {key!r}'):
        load_task(str(path))


def _delete_nested(data, keys):
    node = data
    for k in keys[:-1]:
        node = node[k]
    del node[keys[-1]]


@pytest.mark.parametrize('keys', [
    ('controller', 'kp'), ('controller', 'kd'), ('demonstration', 'times'),
    ('demonstration', 'positions'), ('task_parameters', 0, 'low'),
    ('task_parameters', 1, 'high')])
def test_missing_nested_key_raises_task_error(tmp_path, keys):
    data = embedded_data()
    _delete_nested(data, keys)
    path = write_task(tmp_path, data)
    with pytest.raises(TaskError, match=str(keys[-1])):
        load_task(str(path))


def test_missing_model_file_raises(tmp_path):
    data = embedded_data()
    data['model'] = 'no_such_model.xml'
    path = write_task(tmp_path, data, copy_model=False)
    with pytest.raises(TaskError) as info:
        load_task(str(path))
    assert 'no_such_model.xml' in str(info.value)
    assert 'does not exist' in str(info.value)


def test_wrong_posture_length_raises(tmp_path):
    data = embedded_data()
    data['goal_posture'] = data['goal_posture'][:2]
    path = write_task(tmp_path, data)
    with pytest.raises(TaskError, match='goal_posture'):
        load_task(str(path))


def test_unknown_binding_kind_raises(tmp_path):
    data = embedded_data()
    data['task_parameters'][0]['binds']['kind'] = 'joint_damping'
    path = write_task(tmp_path, data)
    with pytest.raises(TaskError, match=r'task_parameters\[0\] \(obstacle_x\).binds: kind must be '
                                        "one of mocap_position, .*, got 'joint_damping'"):
        load_task(str(path))


def test_empty_range_raises(tmp_path):
    data = copy.deepcopy(embedded_data())
    data['task_parameters'][1]['low'] = data['task_parameters'][1]['high']
    path = write_task(tmp_path, data)
    with pytest.raises(TaskError, match='low < high'):
        load_task(str(path))


def test_invalid_yaml_raises(tmp_path):
    path = tmp_path / 'broken.yaml'
    path.write_text('name: [unclosed\n  - : :')
    with pytest.raises(TaskError, match='YAML'):
        load_task(str(path))


# -- sample_tau -------------------------------------------------------------------------------
def test_sample_tau_in_range_and_covers_it():
    task = load_task(DEFAULT_TASK)
    rng = np.random.default_rng(7)
    samples = np.array([task.sample_tau(rng) for _ in range(N_SAMPLES)])   # (N, 2)
    assert samples.shape == (N_SAMPLES, 2)
    assert np.all(samples >= TAU_LOW) and np.all(samples <= TAU_HIGH)
    for tau in samples[:50]:
        task.validate_tau(tau)
    width = TAU_HIGH - TAU_LOW
    assert np.all(samples.min(axis=0) < TAU_LOW + SAMPLE_COVERAGE * width)
    assert np.all(samples.max(axis=0) > TAU_HIGH - SAMPLE_COVERAGE * width)


def test_sample_tau_reproducible_with_seed():
    task = load_task(DEFAULT_TASK)
    first = [task.sample_tau(np.random.default_rng(123)) for _ in range(3)]
    np.testing.assert_array_equal(first[0], first[1])
    np.testing.assert_array_equal(first[0], first[2])
    rng_a, rng_b = np.random.default_rng(5), np.random.default_rng(5)
    seq_a = np.array([task.sample_tau(rng_a) for _ in range(20)])
    seq_b = np.array([task.sample_tau(rng_b) for _ in range(20)])
    np.testing.assert_array_equal(seq_a, seq_b)
    other = task.sample_tau(np.random.default_rng(124))
    assert not np.array_equal(first[0], other)


# -- the typed sections -----------------------------------------------------------------------
def test_sections_are_typed_with_their_defaults(tmp_path):
    from psl_task.task import ControllerSpec, PolicySpec, RewardSpec
    task = load_task(DEFAULT_TASK)
    assert isinstance(task.controller, ControllerSpec)
    assert isinstance(task.policy, PolicySpec) and isinstance(task.reward, RewardSpec)
    data = embedded_data()
    assert task.policy.n_basis == data['policy']['n_basis']
    assert task.reward.weights == data['reward']['weights']
    assert task.reward.arm_geoms == tuple(data['reward']['arm_geoms'])
    # optional keys left out take the defaults of the dataclasses
    for key in ('kind', 'k_s', 'canonical'):
        del data['policy'][key]
    del data['reward']['clearance_margin']
    bare = load_task(str(write_task(tmp_path, data)))
    assert (bare.policy.kind, bare.policy.k_s, bare.policy.canonical, bare.policy.feedforward) \
        == (PolicySpec.kind, PolicySpec.k_s, PolicySpec.canonical, PolicySpec.feedforward)
    assert bare.reward.clearance_margin == RewardSpec.clearance_margin


@pytest.mark.parametrize('section, key, meant', [('policy', 'n_basiss', 'n_basis'),
                                                 ('reward', 'weight', 'weights'),
                                                 ('reward', 'clearance', 'clearance_margin')])
def test_an_unknown_key_of_a_section_is_refused(tmp_path, section, key, meant):
    data = embedded_data()
    data[section][key] = 1
    with pytest.raises(TaskError, match=f"{section} has unknown key '{key}' "
                                        f"\\(did you mean {meant}\\?\\)"):
        load_task(str(write_task(tmp_path, data)))


@pytest.mark.parametrize('section, key, value, words', [
    ('policy', 'feedforward', 'yes', 'true or false'),
    ('policy', 'n_basis', 0, 'policy.n_basis must be >= 1, got 0'),
    ('reward', 'clearance_margin', -0.1, '>= 0'),
    ('reward', 'weights', [1.0], r'reward.weights must be a mapping of keys, got \[1.0\]'),
])
def test_a_bad_section_value_is_refused(tmp_path, section, key, value, words):
    data = embedded_data()
    data[section][key] = value
    with pytest.raises(TaskError, match=words):
        load_task(str(write_task(tmp_path, data)))


@pytest.mark.parametrize('times, words', [
    ([0.1, 0.75, 1.5], 'rise from 0 to duration'),
    ([0.0, 0.75, 2.0], 'rise from 0 to duration'),      # beyond the duration: silently cut before
    ([0.0, 1.0, 0.9], 'rise from 0 to duration'),
])
def test_demonstration_times_must_span_the_duration(tmp_path, times, words):
    data = embedded_data()
    data['demonstration']['times'] = times
    with pytest.raises(TaskError, match=words):
        load_task(str(write_task(tmp_path, data)))


def test_a_demonstration_row_of_the_wrong_length_names_both_counts(tmp_path):
    data = embedded_data()
    data['demonstration']['positions'] = [row + [0.0] for row in
                                          data['demonstration']['positions']]
    with pytest.raises(TaskError, match='rows of 3 joint angles, one per entry of start_posture'
                                        '.*found rows of 4'):
        load_task(str(write_task(tmp_path, data)))


def test_postures_outside_the_joint_ranges_are_refused_naming_the_joint(tmp_path):
    """reach_over_obstacle.xml gives every joint the range [-3, 3]."""
    from psl_task.arm_model import ArmModel
    data = embedded_data()
    data['goal_posture'] = [0.639, -3.2, -1.495]
    data['demonstration']['positions'][-1] = [0.639, -3.2, -1.495]
    with pytest.raises(TaskError, match="goal_posture puts joint 'joint2' at -3.2, outside its "
                                        r'range \[-3, 3\]'):
        ArmModel(load_task(str(write_task(tmp_path, data))))


def test_a_start_posture_of_the_wrong_length_names_the_models_joints(tmp_path):
    from psl_task.arm_model import ArmModel
    data = embedded_data()
    for key in ('start_posture', 'goal_posture'):
        data[key] = data[key] + [0.0]
    for key in ('kp', 'kd'):
        data['controller'][key] = data['controller'][key] + [1.0]
    data['demonstration']['positions'] = [row + [0.0] for row in
                                          data['demonstration']['positions']]
    with pytest.raises(TaskError, match='start_posture has 4 entries, the model drives 3 joints '
                                        r'\(joint1, joint2, joint3\)'):
        ArmModel(load_task(str(write_task(tmp_path, data))))


@pytest.mark.parametrize('row, key', [(0, 'start'), (-1, 'end')])
def test_the_demonstration_must_start_and_end_at_the_postures(tmp_path, row, key):
    data = embedded_data()
    data['demonstration']['positions'][row][0] += 0.1
    with pytest.raises(TaskError, match=f'the demonstration must {key} at'):
        load_task(str(write_task(tmp_path, data)))


# -- a typo anywhere ---------------------------------------------------------------------------
def _with_robot_scene_target(data: dict) -> dict:
    """The embedded task with its model in a robot section, a scene object and a target, so
    that every section is there to misspell."""
    data['robot'] = {'model': data.pop('model')}
    data['scene'] = [{'name': 'shelf', 'size': [0.1, 0.1, 0.01], 'position': [0.0, 0.0, 2.0]}]
    data['target'] = {'position': [0.5, 0.0, 0.5]}
    data.setdefault('homing', {})
    data.setdefault('safety', {})
    return data


@pytest.mark.parametrize('where, name, typo, meant', [
    ((), 'the top level', 'settle_tme', 'settle_time'),
    (('robot',), 'robot', 'gravity_compensaton', 'gravity_compensation'),
    (('controller',), 'controller', 'kpp', 'kp'),
    (('policy',), 'policy', 'n_basiss', 'n_basis'),
    (('demonstration',), 'demonstration', 'time', 'times'),
    (('scene', 0), 'scene[0]', 'positon', 'position'),
    (('target',), 'target', 'orientaton', 'orientation'),
    (('homing',), 'homing', 'settle_tme', 'settle_time'),
    (('safety',), 'safety', 'max_velocty', 'max_velocity'),
    (('reward',), 'reward', 'sucess_threshold', 'success_threshold'),
    (('task_parameters', 0), 'task_parameters[0]', 'defualt', 'default'),
    (('task_parameters', 0, 'binds'), 'task_parameters[0] (obstacle_x).binds', 'axs', 'axis'),
])
def test_a_typo_in_any_section_is_refused_with_the_nearest_key(tmp_path, where, name, typo,
                                                               meant):
    """The misspelt key is refused, named with its section and the valid key it is nearest
    to (psl_task.schema); before, only five sections were checked and a top-level
    settle_tme loaded without a word."""
    data = _with_robot_scene_target(embedded_data())
    section = data
    for part in where:
        section = section[part]
    section[typo] = 1
    shutil.copy(EMBEDDED_XML, tmp_path / data['robot']['model'])
    path = write_task(tmp_path, data, copy_model=False)
    with pytest.raises(TaskError) as info:
        load_task(str(path))
    message = str(info.value)
    assert f"{name} has unknown key '{typo}' (did you mean {meant}?)" in message, message


def test_a_misspelt_binding_kind_is_refused_with_the_nearest_kind(tmp_path):
    data = embedded_data()
    data['task_parameters'][0]['binds']['kind'] = 'mocap_positon'
    with pytest.raises(TaskError, match=r"got 'mocap_positon' \(did you mean mocap_position\?\)"):
        load_task(str(write_task(tmp_path, data)))


def test_every_embedded_and_example_task_loads():
    examples = Path(__file__).resolve().parents[3] / 'examples'
    for task in list_tasks() + [str(p) for p in sorted(examples.glob('*.yaml'))]:
        assert load_task(task).parameters, task
