"""control_msgs as psl builds it (src/control_msgs: a subset of Jazzy's control_msgs 5.8.0, or
the control_msgs of a ROS installation sourced before the set-up) is wire-compatible with
ROS 2 Jazzy's: same type hashes (REP-2011, RIHS01) and same result codes.

What a RIHS01 hash covers: the type names (package name included), the field names, their
order and types, and the same of every type referenced, recursively (trajectory_msgs,
geometry_msgs, builtin_interfaces, ... as installed). Not covered: comments, default values
and constants, so the result codes are checked on their own below."""
import hashlib
import json
import re
from pathlib import Path

import ament_index_python.packages as ament_index
import pytest

# control_msgs/action/FollowJointTrajectory on ROS 2 Jazzy (control_msgs 5.8.0), given by the
# issue that asked for this package
FOLLOW_JOINT_TRAJECTORY_HASH = (
    'RIHS01_738ebcb7a2d7cfa42f9f1001cc99ce3a4383d1cfe508015d9be8485e4b1c66f6')
# control_msgs/msg/JointTrajectoryControllerState on a ROS 2 Jazzy install (Debian packages),
# as printed by `ros2 topic info --verbose` for a joint_trajectory_controller's
# controller_state topic in public notes from August 2025 (the message has not changed since
# control_msgs 5.3.0, which added speed_scaling_factor)
JOINT_TRAJECTORY_CONTROLLER_STATE_HASH = (
    'RIHS01_51d8dd89cc624cbe9daaeeb4d80d6de9b86168ffdc3be41fefc0953e3c26e480')


def _description(interface: str) -> dict:
    """The generated type description (rosidl_generator_type_description) of
    control_msgs/<interface>, e.g. 'action/FollowJointTrajectory', from the installed
    package's share folder."""
    share = Path(ament_index.get_package_share_directory('control_msgs'))
    path = share / f'{interface}.json'
    assert path.is_file(), f'no generated type description {path}'
    return json.loads(path.read_text())


def _hash_of(description: dict, type_name: str) -> str:
    return {h['type_name']: h['hash_string'] for h in description['type_hashes']}[type_name]


def _rihs01(type_description_msg: dict) -> str:
    """REP-2011 RIHS01 of a serialized type description, computed here: SHA-256 of its
    JSON without the default values (the separators are libyaml's)."""
    hashable = json.loads(json.dumps(type_description_msg))
    for td in [hashable['type_description'], *hashable['referenced_type_descriptions']]:
        for field in td['fields']:
            del field['default_value']
    text = json.dumps(hashable, ensure_ascii=True, separators=(', ', ': '))
    return 'RIHS01_' + hashlib.sha256(text.encode('utf-8')).hexdigest()


def test_follow_joint_trajectory_has_jazzys_type_hash():
    d = _description('action/FollowJointTrajectory')
    name = 'control_msgs/action/FollowJointTrajectory'
    assert d['type_description_msg']['type_description']['type_name'] == name
    assert _hash_of(d, name) == FOLLOW_JOINT_TRAJECTORY_HASH
    # the file's hash is the hash of the description next to it
    assert _rihs01(d['type_description_msg']) == FOLLOW_JOINT_TRAJECTORY_HASH


def test_joint_trajectory_controller_state_has_jazzys_type_hash():
    d = _description('msg/JointTrajectoryControllerState')
    name = 'control_msgs/msg/JointTrajectoryControllerState'
    assert _hash_of(d, name) == JOINT_TRAJECTORY_CONTROLLER_STATE_HASH
    assert _rihs01(d['type_description_msg']) == JOINT_TRAJECTORY_CONTROLLER_STATE_HASH


@pytest.mark.parametrize('message', ['JointTolerance', 'JointComponentTolerance'])
def test_tolerances_are_those_follow_joint_trajectory_was_hashed_with(message):
    """No published hash to compare with; but FollowJointTrajectory's hash (Jazzy's, above)
    covers the tolerance messages' full descriptions, so theirs must be the ones referenced
    there, and their own hashes those of these descriptions."""
    name = f'control_msgs/msg/{message}'
    fjt = _description('action/FollowJointTrajectory')
    referenced = {td['type_name']: td
                  for td in fjt['type_description_msg']['referenced_type_descriptions']}
    own = _description(f'msg/{message}')
    assert own['type_description_msg']['type_description'] == referenced[name]
    assert re.fullmatch(r'RIHS01_[0-9a-f]{64}', _hash_of(own, name))
    assert _hash_of(own, name) == _hash_of(fjt, name) == _rihs01(own['type_description_msg'])


def test_follow_joint_trajectory_imports_with_jazzys_result_codes():
    from control_msgs.action import FollowJointTrajectory
    from control_msgs.msg import JointTolerance, JointTrajectoryControllerState  # noqa: F401

    result = FollowJointTrajectory.Result
    assert {code: getattr(result, code) for code in (
        'SUCCESSFUL', 'INVALID_GOAL', 'INVALID_JOINTS', 'OLD_HEADER_TIMESTAMP',
        'PATH_TOLERANCE_VIOLATED', 'GOAL_TOLERANCE_VIOLATED')} == {
        'SUCCESSFUL': 0, 'INVALID_GOAL': -1, 'INVALID_JOINTS': -2, 'OLD_HEADER_TIMESTAMP': -3,
        'PATH_TOLERANCE_VIOLATED': -4, 'GOAL_TOLERANCE_VIOLATED': -5}
    assert result(error_code=result.PATH_TOLERANCE_VIOLATED, error_string='x').error_code == -4
    goal = FollowJointTrajectory.Goal()
    assert goal.trajectory.joint_names == [] and goal.path_tolerance == []
