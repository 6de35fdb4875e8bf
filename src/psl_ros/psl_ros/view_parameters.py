"""The parameters of the view node (`psl_ros.view_node`; `psl_ros.parameters.declare` makes
them; imports no ROS). ``('',)`` stands for "not given" in the topic list: a ROS parameter
cannot be declared as an empty list of strings."""
from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import field

ALL_TOPICS = ('',)
DEFAULT_PORT = 8765             # the Foxglove app's default connection: ws://localhost:8765
SERVING = 'serving Foxglove on {url}'          # the view node's log line once it listens
_SERVING = re.compile(r'serving Foxglove on (ws://[0-9A-Za-z.:\[\]-]+:\d+)')


def serving_url(log: str) -> str | None:
    """The URL a view node's log says it serves on (the last one), None before it listens."""
    found = _SERVING.findall(log)
    return found[-1] if found else None


@dataclasses.dataclass(frozen=True)
class ViewParameters:
    """Where the Foxglove WebSocket server listens and what it forwards."""

    host: str = field(default='127.0.0.1', metadata={'doc': (
        'the address the Foxglove WebSocket server binds to; 127.0.0.1 = this machine only '
        '(0.0.0.0 opens it to the network)')})
    port: int = field(default=DEFAULT_PORT, metadata={'doc': (
        'its TCP port (the Foxglove app connects to ws://localhost:8765 by default); 0 = a '
        'free port, logged')})
    topics: tuple[str, ...] = field(default=ALL_TOPICS, metadata={'doc': (
        "the ROS topics offered as channels (relative names resolve in the node's "
        "namespace); [''] = every topic of the graph but /rosout, /parameter_events and "
        'hidden ones')})
    max_rate: float = field(default=60.0, metadata={'doc': (
        'the most messages per second forwarded of one topic to the viewers (wall clock; '
        'latched topics always in full); 0 = every message')})

    def __post_init__(self):
        if not isinstance(self.port, int) or isinstance(self.port, bool) \
                or not 0 <= self.port <= 65535:
            raise ValueError(f'port must be 0..65535, got {self.port!r}')
        if not (isinstance(self.max_rate, (int, float)) and math.isfinite(self.max_rate)
                and self.max_rate >= 0.0):
            raise ValueError(f'max_rate must be a finite rate >= 0 Hz, got {self.max_rate!r}')
        if not self.host:
            raise ValueError('host must be an address, e.g. 127.0.0.1')

    @property
    def topic_names(self) -> tuple[str, ...]:
        """The topics asked for; () = all."""
        return tuple(t for t in self.topics if t)
