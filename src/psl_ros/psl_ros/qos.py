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
  default, on every run; none with depth 1,000 on the clients. The depth is how many answers
  to *other* clients a client may fall behind (its process starved of CPU: each answer costs
  it an executor turn, ~0.35 ms of Python) and still get its own; the skill memory answers
  350-650 calls/s under that load, so 1,000 was 1.5-3 s, less than a call's timeout (5-10 s):
  a client that was not run for 4 s lost its answer in 1 run of 6, one whose executor took
  at most ~200 answers/s lost 1 of 100 calls in each of 5 runs (the requests executed, the
  answers sent and pushed out of its reader). With 5,000: none lost in 6 and in 3 such runs
  (the throttled client's answers all arrived, 3-5 of them after its 5 s timeout: slow, not
  lost). 5,000 is 8-14 s of answers and Fast DDS's default `max_samples` (a deeper keep-last
  history of a keyless topic would stop at 5,000 and behave like keep-all); a client further
  behind than its timeout has failed anyway. Memory grows only with the answers held. On the
  server, the same depth bounds how many answers a client's reader may leave unacknowledged
  before the writer drops them.
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

RELIABLE = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
WHOLE_EPISODE = QoSProfile(depth=20000, reliability=ReliabilityPolicy.RELIABLE)
# the newest message only: a reader that watches a stream it need not take whole (the executor
# watching a robot's joint states) never works through a backlog of old ones (seen: 4 s behind)
NEWEST = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
# the poses of an observed body (names.world_pose): the last 2000 (4 s at 500 Hz) kept for a
# reader that subscribes once an episode has begun (the evaluator, at its first episode of the
# task: within a second); more would be more than a keep-all reader takes at once (a recorder
# joining after a long session got part of 20000 and never the rest)
WORLD_POSES = QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
SERVICES = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
