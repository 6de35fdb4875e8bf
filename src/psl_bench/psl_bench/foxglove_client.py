"""A viewer of the Foxglove WebSocket protocol (test/test_view.py, psl bench graph --view),
written from the protocol's specification (github.com/foxglove/ws-protocol, docs/spec.md), not
from the SDK the view serves with: JSON
text frames (``serverInfo``, ``advertise``, ``unadvertise``; ``subscribe``, ``unsubscribe``)
and binary frames (opcode 1, message data: uint32 subscription id, uint64 log time in ns, both
little-endian, then the message's bytes). The subprotocol is offered under both names it has
had, ``foxglove.websocket.v1`` and ``foxglove.sdk.v1`` (or under those given); which one the
server took is kept.

Messages are decoded with a typestore built only from the schemas the server advertised
(``ros2msg``: a type's definition, then ``MSG: <type>`` sections of its dependencies), so a
decoded message shows that the advertised schema describes the bytes.
"""
from __future__ import annotations

import json
import struct
import time

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

SUBPROTOCOLS = ('foxglove.websocket.v1', 'foxglove.sdk.v1')
MESSAGE_DATA = 0x01
SEPARATOR = '=' * 80


def types_from_ros2msg(name: str, text: str) -> dict:
    """The rosbags type definitions of a ``ros2msg`` schema (the type and its dependencies)."""
    types = {}
    sections = text.split(SEPARATOR + '\n')
    types.update(get_types_from_msg(sections[0], name))
    for section in sections[1:]:
        header, _, body = section.partition('\n')
        assert header.startswith('MSG: '), header
        types.update(get_types_from_msg(body, header[len('MSG: '):].strip()))
    return types


class FoxgloveClient:
    """One viewer: connects and waits for the server's ``serverInfo``, then collects the
    advertised channels and the messages of its subscriptions while `pump` runs (a single
    thread: the caller's). A context manager; `close` ends the connection.

    Raises:
        TimeoutError: no ``serverInfo`` within `timeout` s; OSError: no server at `url`;
        websockets.exceptions.InvalidStatus: the server refused the handshake (e.g. HTTP 400:
        none of `subprotocols`).
    """

    def __init__(self, url: str, timeout: float = 10.0, subprotocols=SUBPROTOCOLS):
        self.ws = connect(url, subprotocols=list(subprotocols) if subprotocols else None,
                          open_timeout=timeout, max_size=None, proxy=None).__enter__()
        self.subprotocol = self.ws.subprotocol
        self.server_info: dict | None = None
        self.channels: dict[str, dict] = {}          # topic -> advertised channel
        self.messages: dict[str, list[tuple[int, bytes]]] = {}   # topic -> (log ns, bytes)
        self._subscriptions: dict[int, str] = {}     # subscription id -> topic
        self._next_id = 1
        self.typestore = get_typestore(Stores.EMPTY)
        if not self.pump(lambda: self.server_info is not None, timeout):
            self.close()
            raise TimeoutError(f'{url} sent no serverInfo within {timeout} s')

    def pump(self, until=lambda: False, timeout: float = 10.0) -> bool:
        """Receive until `until()` is true (True) or `timeout` s passed (False).
        ConnectionError when the server closes the connection (e.g. it drops a viewer that
        does not keep up)."""
        deadline = time.monotonic() + timeout
        while not until():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            try:
                frame = self.ws.recv(timeout=min(left, 0.1))
            except TimeoutError:
                continue
            except ConnectionClosed as exc:
                raise ConnectionError(f'the server closed the connection: {exc}') from None
            self._take(frame)
        return True

    def _take(self, frame) -> None:
        if isinstance(frame, str):
            message = json.loads(frame)
            if message['op'] == 'serverInfo':
                self.server_info = message
            elif message['op'] == 'advertise':
                for channel in message['channels']:
                    self.channels[channel['topic']] = channel
            elif message['op'] == 'unadvertise':
                gone = set(message['channelIds'])
                self.channels = {t: c for t, c in self.channels.items() if c['id'] not in gone}
            return
        if frame[0] == MESSAGE_DATA:
            subscription, log_time = struct.unpack_from('<IQ', frame, 1)
            topic = self._subscriptions.get(subscription)
            if topic is not None:
                self.messages.setdefault(topic, []).append((log_time, bytes(frame[13:])))

    def wait_channels(self, topics, timeout: float = 30.0) -> bool:
        return self.pump(lambda: set(topics) <= set(self.channels), timeout)

    def subscribe(self, topics) -> None:
        subscriptions = []
        for topic in topics:
            channel = self.channels[topic]
            self._subscriptions[self._next_id] = topic
            subscriptions.append({'id': self._next_id, 'channelId': channel['id']})
            self._next_id += 1
            self._register(channel)
        self.ws.send(json.dumps({'op': 'subscribe', 'subscriptions': subscriptions}))

    def _register(self, channel: dict) -> None:
        assert channel['schemaEncoding'] == 'ros2msg' and channel['encoding'] == 'cdr', channel
        types = types_from_ros2msg(channel['schemaName'], channel['schema'])
        new = {name: t for name, t in types.items() if name not in self.typestore.fielddefs}
        if new:
            self.typestore.register(new)

    def decoded(self, topic: str) -> list:
        """The messages of a topic, decoded with the advertised schema."""
        msgtype = self.channels[topic]['schemaName']
        return [self.typestore.deserialize_cdr(data, msgtype)
                for _, data in self.messages.get(topic, [])]

    def close(self) -> None:
        self.ws.close()

    def __enter__(self) -> 'FoxgloveClient':
        return self

    def __exit__(self, *exc) -> None:
        self.close()
