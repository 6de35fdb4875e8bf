"""Damaged files the learning loop and psl teach's library read (issue 46): a checkpoint.json
that is no checkpoint, and bags that are cut short, overwritten or empty, each refused with a
ValueError that names the file and says what is wrong; nothing run, nothing written over."""
import json
import os

import numpy as np
import pytest

from psl_optimizer import teaching
from psl_optimizer.batch_rollout import BatchRollouts
from psl_optimizer.learning import (Learner, LearnSettings, SessionFolderError,
                                    holds_checkpoint)
from psl_optimizer.policy_search import SearchSettings
from psl_task.arm_model import joint_names_of
from psl_task.task import load_task

TASK = 'reach_over_obstacle'
SETTINGS = LearnSettings(strategy='bootstrap', num_tasks=2, seed=1, num_test=1,
                         search=SearchSettings(max_rollouts=2))


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


@pytest.fixture(scope='module')
def rollouts(task):
    return BatchRollouts(task)


def identity(task, rollouts, tmp_path) -> dict:
    """What a checkpoint of this session holds besides its tasks."""
    return Learner(task, SETTINGS, tmp_path / 'probe', rollouts)._identity()


GOOD_RECORD = {'index': 0, 'tau': [0.6, 0.15], 'rollouts': 1, 'fulfilled': True,
               'best_reward': -0.1, 'start_reward': -0.2, 'seconds': 0.5}


@pytest.mark.parametrize('tasks, words', [
    ('three', 'no list of tasks'),
    ([{key: v for key, v in GOOD_RECORD.items() if key != 'rollouts'}], "without 'rollouts'"),
    ([{**GOOD_RECORD, 'tau': 'x'}], 'a task record that is not one'),
    ([{**GOOD_RECORD, 'rollouts': None}], 'a task record that is not one'),
    (['a record'], 'a task record that is not one'),
])
def test_a_checkpoint_of_this_session_with_damaged_records_is_refused_naming_it(
        task, rollouts, tmp_path, tasks, words):
    """The checkpoint's settings are this session's (so it is not 'another session'), its
    records are damaged: refused naming the file, before any rollout, the file kept."""
    out = tmp_path / 'run'
    out.mkdir()
    text = json.dumps({**identity(task, rollouts, tmp_path), 'tasks': tasks})
    (out / 'checkpoint.json').write_text(text)
    simulated = rollouts.simulation_seconds
    with pytest.raises(SessionFolderError) as refused:
        Learner(task, SETTINGS, out, rollouts).run()
    message = str(refused.value)
    assert message.startswith(f'{out / "checkpoint.json"}: a damaged checkpoint ('), message
    assert words in message
    assert (out / 'checkpoint.json').read_text() == text
    assert sorted(p.name for p in out.iterdir()) == ['checkpoint.json']
    assert rollouts.simulation_seconds == simulated            # nothing ran


@pytest.mark.parametrize('make', ['directory', 'dangling link'])
def test_a_checkpoint_that_is_no_file_is_refused_not_written_over(task, rollouts, tmp_path,
                                                                  make):
    """Before: a folder named checkpoint.json was taken for no checkpoint, the session ran
    its first task and ended in IsADirectoryError writing its checkpoint."""
    out = tmp_path / 'run'
    out.mkdir()
    if make == 'directory':
        (out / 'checkpoint.json').mkdir()
    else:
        (out / 'checkpoint.json').symlink_to(tmp_path / 'gone.json')
    assert holds_checkpoint(out)
    simulated = rollouts.simulation_seconds
    with pytest.raises(SessionFolderError, match='checkpoint.json: a damaged checkpoint '
                                                 r'\(not a regular file\)'):
        Learner(task, SETTINGS, out, rollouts).run()
    assert rollouts.simulation_seconds == simulated
    assert sorted(p.name for p in out.iterdir()) == ['checkpoint.json']
    assert not holds_checkpoint(tmp_path)


# -- bags ------------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def bag(task, tmp_path_factory):
    """A bag of the task's joint states (rosbags, MCAP), as psl record writes one."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    msgtype = 'sensor_msgs/msg/JointState'
    types = store.types
    folder = tmp_path_factory.mktemp('bags') / 'good'
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/joint_states', msgtype, typestore=store)
        for k in range(500):
            ns = 2_000_000 * k
            msg = types[msgtype](
                header=types['std_msgs/msg/Header'](stamp=types['builtin_interfaces/msg/Time'](
                    sec=ns // 10**9, nanosec=ns % 10**9), frame_id=''),
                name=joint_names_of(task), position=task.start_posture + 1e-3 * k,
                velocity=np.zeros(0), effort=np.zeros(0))
            writer.write(connection, ns, store.serialize_cdr(msg, msgtype))
    return folder


def damaged_bag(good, folder, how: str):
    """A copy of the bag whose MCAP file is cut in half, overwritten in its middle with
    random bytes (its first and last 64 bytes kept, the magic of both ends) or empty."""
    import shutil
    shutil.copytree(good, folder)
    mcap = folder / 'good.mcap'
    data = mcap.read_bytes()
    noise = np.random.default_rng(46).bytes(len(data))
    mcap.write_bytes({'truncated': data[:len(data) // 2],
                      'corrupted': data[:64] + noise[64:-64] + data[-64:],
                      'empty': b''}[how])
    return folder


@pytest.mark.parametrize('how', ['truncated', 'corrupted', 'empty'])
def test_a_damaged_bag_is_a_value_error_naming_it(task, bag, tmp_path, how):
    """Before: rosbags' ReaderError, an OverflowError or a MemoryError, none a ValueError
    (psl teach printed their tracebacks)."""
    from psl_ros.bag_reading import BagError
    damaged = damaged_bag(bag, tmp_path / how, how)
    assert len(teaching.read_joint_states(bag, '/joint_states', joint_names_of(task)).t) == 500
    for read in (lambda: teaching.read_joint_states(damaged, '/joint_states',
                                                    joint_names_of(task)),
                 lambda: teaching.read_announcements(damaged, '/joint_states')):
        with pytest.raises(BagError) as refused:
            read()
        assert isinstance(refused.value, ValueError)
        assert str(refused.value).startswith(f'{damaged}: not a readable rosbag2 bag')
        assert '\n' not in str(refused.value)


def test_a_topic_of_another_type_is_refused_naming_it(task, bag, tmp_path):
    """Joint states asked of a topic of another type (before: an AttributeError)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    folder = tmp_path / 'strings'
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/joint_states', 'std_msgs/msg/String',
                                           typestore=store)
        for k in range(3):
            writer.write(connection, k, store.serialize_cdr(
                store.types['std_msgs/msg/String'](data='x'), 'std_msgs/msg/String'))
    with pytest.raises(ValueError, match=f'{folder}: /joint_states holds std_msgs/msg/String, '
                                         'not sensor_msgs/msg/JointState'):
        teaching.read_joint_states(folder, '/joint_states', joint_names_of(task))


def test_no_bag_and_a_folder_that_is_none_are_refused_naming_them(task, tmp_path):
    os.mkdir(tmp_path / 'folder')
    for path, words in ((tmp_path / 'missing', 'no such bag'),
                        (tmp_path / 'folder', 'not a readable rosbag2 bag')):
        with pytest.raises(ValueError, match=f'{path}: {words}'):
            teaching.read_joint_states(path, '/joint_states', joint_names_of(task))


def test_a_topic_of_a_type_psl_does_not_know_is_refused_naming_it(tmp_path):
    """A tau topic of a package not installed here: said so, not taken for a damaged bag."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg('float64 x', 'their_msgs/msg/Thing'))
    folder = tmp_path / 'theirs'
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/thing', 'their_msgs/msg/Thing', typestore=store)
        writer.write(connection, 1, store.serialize_cdr(
            store.types['their_msgs/msg/Thing'](x=1.0), 'their_msgs/msg/Thing'))
    with pytest.raises(ValueError, match=f'^{folder}: /thing holds their_msgs/msg/Thing, a type '
                                         'psl does not know'):
        teaching.read_announcements(folder, '/thing')
