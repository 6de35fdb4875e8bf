"""A node's ROS parameters from one dataclass: declared, described, validated and read once.

Each node's parameters are a dataclass in a module of its package that imports no ROS (as
`psl_memory.skill_config.SkillConfig`): a field per parameter, its default, and in its metadata
``doc`` (the description ``ros2 param describe`` shows) and ``dynamic`` (the parameter may be
set while the node runs; otherwise it is read-only). The dataclass's ``__post_init__``
validates. `declare` makes the node's parameters from it, so a default lives in exactly one
place; nodes ship no parameter files (``--params-file`` and ``-p`` still override, and
`psl params` prints a file to start from).
"""
from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node

T = TypeVar('T')


def field_default(field: dataclasses.Field) -> Any:
    """A field's default as a ROS parameter value (a tuple becomes a list)."""
    if field.default is not dataclasses.MISSING:
        value = field.default
    elif field.default_factory is not dataclasses.MISSING:
        value = field.default_factory()
    else:
        raise TypeError(f'parameter {field.name} has no default')
    return list(value) if isinstance(value, tuple) else value


def defaults(cls: type) -> dict[str, Any]:
    """Parameter name -> default of a parameter dataclass, as ROS parameter values."""
    return {field.name: field_default(field) for field in dataclasses.fields(cls)}


def declare(node: Node, cls: type[T]) -> T:
    """Declare one parameter per field of `cls` on `node` (default, description, read-only
    unless ``dynamic``), and return the dataclass of their values (its ``__post_init__``
    validates). ValueError naming the node and the parameter when a value is refused."""
    for field in dataclasses.fields(cls):
        node.declare_parameter(field.name, field_default(field), ParameterDescriptor(
            description=field.metadata.get('doc', ''),
            read_only=not field.metadata.get('dynamic', False)))
    return read(node, cls)


def read(node: Node, cls: type[T]) -> T:
    """The dataclass of the node's current values of `cls`'s parameters (validated)."""
    values = {}
    for field in dataclasses.fields(cls):
        value = node.get_parameter(field.name).value
        if isinstance(field_default(field), list):     # an array parameter: a tuple field
            value = tuple(value)
        values[field.name] = value
    try:
        return cls(**values)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{node.get_name()} parameters: {exc}') from None


def check_update(node: Node, cls: type, params) -> SetParametersResult:
    """An ``add_on_set_parameters_callback`` answer: the update (also a declaration) is
    accepted when the dataclass takes the node's values with it (its ``__post_init__``, the
    one place the values are checked), else refused with the dataclass's reason."""
    fields = {field.name: field for field in dataclasses.fields(cls)}
    values = {name: (node.get_parameter(name).value if node.has_parameter(name)
                     else field_default(field)) for name, field in fields.items()}
    for param in params:
        if param.name in fields:
            values[param.name] = param.value
    for name, field in fields.items():
        if isinstance(field_default(field), list):
            values[name] = tuple(values[name])
    try:
        cls(**values)
    except (TypeError, ValueError) as exc:
        return SetParametersResult(successful=False, reason=str(exc))
    return SetParametersResult(successful=True)
