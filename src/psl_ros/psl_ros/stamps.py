"""Time stamps: builtin_interfaces Time / Duration <-> integer nanoseconds.

The graph keys states, references and evaluations by their stamp in nanoseconds (an exact
integer, no float rounding), so every node converts the same way.
"""
from __future__ import annotations

from builtin_interfaces.msg import Duration, Time

NS_PER_S = 1_000_000_000


def to_ns(stamp: Time | Duration) -> int:
    """Nanoseconds of a Time or Duration message."""
    return stamp.sec * NS_PER_S + stamp.nanosec


def time_msg(t_ns: int) -> Time:
    """A Time message of t_ns >= 0 nanoseconds."""
    return Time(sec=t_ns // NS_PER_S, nanosec=t_ns % NS_PER_S)


def duration_msg(t_ns: int) -> Duration:
    """A Duration message of t_ns >= 0 nanoseconds."""
    return Duration(sec=t_ns // NS_PER_S, nanosec=t_ns % NS_PER_S)
