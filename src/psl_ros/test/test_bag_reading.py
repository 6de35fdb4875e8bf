"""`psl_ros.bag_reading`: a bag that cannot be read is one BagError (a ValueError) naming it,
whatever rosbags and its parsers raised; the recorder's summary reads through it."""
import numpy as np
import pytest

from psl_ros.bag_reading import BagError, open_bag
from psl_ros.bag_recorder import read_bag_summary


@pytest.fixture
def bag(tmp_path):
    """A small MCAP bag of std_msgs/String, written with rosbags as psl record writes."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    folder = tmp_path / 'bag'
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/text', 'std_msgs/msg/String', typestore=store)
        for k in range(200):
            writer.write(connection, k, store.serialize_cdr(
                store.types['std_msgs/msg/String'](data=f'message {k}'),
                'std_msgs/msg/String'))
    return folder


@pytest.mark.parametrize('how', ['truncated', 'corrupted', 'empty'])
def test_a_damaged_bag_is_one_bag_error_naming_it(bag, how):
    assert read_bag_summary(bag) == {'/text': ('std_msgs/msg/String', 200)}
    mcap = bag / 'bag.mcap'
    data = mcap.read_bytes()
    noise = np.random.default_rng(46).bytes(len(data))
    mcap.write_bytes({'truncated': data[:len(data) // 2],
                      'corrupted': data[:64] + noise[64:-64] + data[-64:],
                      'empty': b''}[how])
    with pytest.raises(BagError) as refused:
        with open_bag(bag) as reader:
            for _ in reader.messages():
                pass
    assert str(refused.value).startswith(f'{bag}: not a readable rosbag2 bag')
    with pytest.raises(ValueError, match='not a readable rosbag2 bag'):
        read_bag_summary(bag)


def test_a_refusal_raised_inside_passes_unchanged_and_no_bag_is_named(bag, tmp_path):
    with pytest.raises(BagError, match='^mine$'):
        with open_bag(bag):
            raise BagError('mine')
    with pytest.raises(BagError, match=f'^{tmp_path / "nothing"}: no such bag$'):
        with open_bag(tmp_path / 'nothing'):
            pass
