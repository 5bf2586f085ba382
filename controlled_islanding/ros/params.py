"""Node parameters with their ranges and meaning, the snapshot size limits, and message types by name."""

from __future__ import annotations

import importlib

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterValueException
from rclpy.node import Node

from controlled_islanding.wire.messages import Limits


class NodeSetupError(ValueError):
    """A node's parameters or message types are unusable."""


def message_class(type_name: str) -> type:
    """Return the rclpy message class of a full ROS 2 type name such as 'std_msgs/msg/String'.

    Raises:
        NodeSetupError: The type name is malformed or its package is not installed.

    """
    parts = type_name.split('/')
    if len(parts) != 3:
        raise NodeSetupError(f'message type {type_name!r} is not of the form package/msg/Name')
    try:
        return getattr(importlib.import_module(f'{parts[0]}.{parts[1]}'), parts[2])
    except (ImportError, AttributeError) as exc:
        raise NodeSetupError(f'message type {type_name!r} is not installed: {exc}') from exc


def declare_bounded(node: Node, name: str, default: float | int, low: float | int, high: float | int,
                    description: str, read_only: bool = False) -> float | int:
    """Declare a parameter with its range and meaning (read-only: never changed at run time); return its value.

    Raises:
        NodeSetupError: The configured value is outside [low, high].

    """
    if isinstance(default, int):
        bound = {'integer_range': [IntegerRange(from_value=int(low), to_value=int(high), step=1)]}
    else:
        bound = {'floating_point_range': [FloatingPointRange(from_value=float(low), to_value=float(high))]}
    try:
        node.declare_parameter(name, default,
                               ParameterDescriptor(description=description, read_only=read_only, **bound))
    except InvalidParameterValueException as exc:
        raise NodeSetupError(f'parameter {name}: {exc}; it must be in [{low}, {high}]') from exc
    return node.get_parameter(name).value


def declare_limits(node: Node) -> Limits:
    """Declare the snapshot size caps as parameters; return them as Limits."""
    default = Limits()
    return Limits(**{
        field: int(declare_bounded(node, field, getattr(default, field), 1, 10 * getattr(default, field),
                                   f'largest number of {field[4:]} accepted in one network snapshot; a '
                                   'larger one is refused (too_large) before any per-element work'))
        for field in ('max_buses', 'max_branches', 'max_generators', 'max_loads')})
