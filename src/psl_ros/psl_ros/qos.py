"""The QoS profiles of the graph's topics, defined once.

- `RELIABLE`: every per-step topic of the robot loop (states, commands, references,
  trajectories, evaluations): nothing may be lost in lockstep, where a lost message stalls
  the loop.
- `WHOLE_EPISODE`: the evaluator's subscriptions; it is not on the lockstep path and may lag
  behind the loop, so its history is longer than any episode.
- `LATCHED`: ``task_instance``: a late subscriber still gets the current episode.
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
WHOLE_EPISODE = QoSProfile(depth=20000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
