"""The QoS profiles of the graph's topics, defined once.

- `RELIABLE`: every per-step topic of the robot loop (states, commands, references, poses,
  the clock, trajectories, evaluations): nothing may be lost in lockstep, where a lost message
  stalls the loop. Its depth is what a publisher keeps for a reader that falls behind (a bag
  recorder starved of CPU): a reliable keep-last writer overwrites what a reader has not
  acknowledged once its history is full, and the reader loses it (Fast DDS: a keep-all
  writer would block the publishing node instead, for at most 100 ms, and then fail).
  Measured with one core busy: a recorder lost 42 of 6006 /clock messages from a depth-10
  publisher and none from the depth-100 ones; under a load of 11 on 2 cores one lost 16 of
  10010 from a depth-1000 one. 5000 is about three seconds of the lockstep loop; with a
  recorder's keep-all subscription (5000 more) a reader may fall 10000 messages behind.
- `WHOLE_EPISODE`: the evaluator's subscriptions; it is not on the lockstep path and may lag
  behind the loop, so its history is longer than any episode.
- `LATCHED`: ``task_instance``: a late subscriber still gets the current episode.
- `SERVICES`: every service and every client of one. A service's answers travel on one topic
  that every client of the service reads (each keeps only the answers to its own requests), so
  with rclpy's default keep-last 10 a client that falls behind while other clients are being
  answered loses its own answer among theirs and waits in vain. Measured with 8 querying and
  2 adding client processes (`psl bench memory-load`): 31 of 4,200 answers lost with the
  default, on every run; none with this depth on the clients (the server's depth made no
  difference).
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

RELIABLE = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
WHOLE_EPISODE = QoSProfile(depth=20000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
SERVICES = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
