"""builtin_interfaces/Time (a header's stamp) -> numbers; duck-typed, no ROS import."""

from __future__ import annotations

NS_PER_S = 1_000_000_000


def stamp_to_ns(stamp) -> int:
    """A builtin_interfaces/Time (anything with ``sec`` and ``nanosec``) -> nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def stamp_to_seconds(stamp) -> float:
    """A builtin_interfaces/Time -> seconds (float)."""
    return int(stamp.sec) + int(stamp.nanosec) * 1e-9


def ns_to_stamp(ns: int, time_cls):
    """Nanoseconds -> a builtin_interfaces/Time of class ``time_cls`` (rclpy's or a type
    store's)."""
    return time_cls(sec=int(ns) // NS_PER_S, nanosec=int(ns) % NS_PER_S)


def clock_message(ns: int, clock_cls, time_cls):
    """A rosgraph_msgs/Clock carrying ``ns`` (the player's /clock)."""
    return clock_cls(clock=ns_to_stamp(ns, time_cls))
