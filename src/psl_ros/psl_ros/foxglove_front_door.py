"""The view's public port: a WebSocket relay in front of the Foxglove SDK's server, so that
clients of the protocol's old subprotocol name connect too.

The SDK's server (foxglove-sdk, up to 0.30.3 at least) accepts only its own subprotocol names
(``foxglove.sdk.v1`` and, since 0.30, ``foxglove.sdk.v1.1``) and refuses a client offering only
``foxglove.websocket.v1`` with HTTP 400, and it has no option to accept that name. Lichtblick
(before its ``foxglove.sdk.v1`` support) and every client written for foxglove_bridge offer only
``foxglove.websocket.v1``. The two names stand for the same messages: the ws-protocol spec
(github.com/foxglove/ws-protocol, docs/spec.md, ``foxglove.websocket.v1``) and the SDK's ``v1``
protocol (rust/foxglove/src/protocol/v1) agree byte for byte on what a viewer uses, serverInfo,
advertise, unadvertise, status and message data (opcode 1: uint32 subscription id, uint64 log
time, payload) from the server, subscribe and unsubscribe from the client. (``foxglove.sdk.v1.1``
does differ: its advertise carries the schemas apart from the channels.)

So the relay lets the SDK decide: for each client it opens a connection to the SDK's server on
a loopback port, offering the subprotocols the client offered with ``foxglove.websocket.v1``
named ``foxglove.sdk.v1``; it answers the client's handshake with the SDK's answer (its refusal
as it is, its choice under the name the client offered) and then relays every frame both ways
unchanged, but for one thing: a client of ``foxglove.websocket.v1`` gets no server message the
v1 spec does not define (the SDK sends such only for capabilities the view does not declare,
e.g. playback state: dropped, said once in the log). A client that leaves closes its upstream
connection (the SDK then ends its subscriptions); an upstream connection that ends closes its
client, with the SDK's close code. Everything runs on one asyncio loop in one thread, ended by
`close`.
"""
from __future__ import annotations

import asyncio
import json
import threading

from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import InvalidHeader, InvalidStatus
from websockets.frames import EXTERNAL_CLOSE_CODES, CloseCode
from websockets.headers import parse_subprotocol

LEGACY = 'foxglove.websocket.v1'        # the protocol's name before the SDK (foxglove_bridge 0.x)
ALIASES = {LEGACY: 'foxglove.sdk.v1'}   # a client's name -> the SDK's name of the same protocol
# what a server sends under foxglove.websocket.v1 (ws-protocol docs/spec.md, "Sent by server")
V1_SERVER_OPS = frozenset({
    'serverInfo', 'status', 'removeStatus', 'advertise', 'unadvertise', 'parameterValues',
    'advertiseServices', 'unadvertiseServices', 'connectionGraphUpdate', 'serviceCallFailure'})
V1_SERVER_OPCODES = frozenset({1, 2, 3, 4})     # message data, time, service call / asset reply
OPEN_TIMEOUT = 10.0     # [s] for the SDK's server to answer a handshake (it is on this machine)
CLOSE_TIMEOUT = 2.0     # [s] for a peer to answer a close frame before the TCP connection ends


def _offered(request) -> list[str]:
    """The subprotocols a handshake request offers, in its order."""
    return [p for value in request.headers.get_all('Sec-WebSocket-Protocol')
            for p in parse_subprotocol(value)]


def _close_args(connection) -> tuple[int, str]:
    """The close code and reason to pass on from a connection that ended: its own when they may
    be sent (not 1005 'no status', 1006 'abnormal closure')."""
    code = connection.close_code
    if code in EXTERNAL_CLOSE_CODES or (code is not None and 3000 <= code < 5000):
        return code, connection.close_reason or ''
    if code == CloseCode.NO_STATUS_RCVD:
        return CloseCode.NORMAL_CLOSURE, ''
    return CloseCode.INTERNAL_ERROR, 'the Foxglove server ended the connection'


class FrontDoor:
    """A WebSocket server on ``host``:``port`` relaying each client to ``upstream_url`` (the
    SDK's server), under either subprotocol name (module docstring). ``warn`` takes a line for
    the log. `port` is the port it listens on (``port`` 0: a free one).

    Raises:
        OSError: it cannot listen (e.g. the port is taken).
    """

    def __init__(self, host: str, port: int, upstream_url: str, warn=lambda line: None):
        self.upstream_url = upstream_url
        self._warn = warn
        self._dropped: set = set()                  # kinds of message dropped (said once)
        self._upstreams: dict[ServerConnection, object] = {}   # client -> its upstream
        self._ties: set[asyncio.Task] = set()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name='view_front_door',
                                        daemon=True)
        self._thread.start()
        try:
            self._server = asyncio.run_coroutine_threadsafe(self._serve(host, port),
                                                            self._loop).result()
        except BaseException:
            self._stop_loop()
            raise
        self.port = self._server.sockets[0].getsockname()[1]

    async def _serve(self, host: str, port: int):
        return await serve(self._relay, host, port, process_request=self._open_upstream,
                           select_subprotocol=self._select_subprotocol, compression=None,
                           max_size=None, ping_interval=None, close_timeout=CLOSE_TIMEOUT)

    # -- the handshake: the SDK's answer --------------------------------------------------------
    async def _open_upstream(self, client: ServerConnection, request):
        """Connect to the SDK's server offering what the client offers (``foxglove.websocket.v1``
        under its new name); refuse the client as the SDK refused (None: go on)."""
        try:
            offered = _offered(request)
        except InvalidHeader as exc:
            return client.respond(400, f'{exc}\n')
        wanted = list(dict.fromkeys(ALIASES.get(p, p) for p in offered))
        try:
            upstream = await connect(self.upstream_url, subprotocols=wanted or None,
                                     compression=None, max_size=None, proxy=None,
                                     ping_interval=None, open_timeout=OPEN_TIMEOUT,
                                     close_timeout=CLOSE_TIMEOUT)
        except InvalidStatus as exc:
            return client.respond(exc.response.status_code,
                                  (exc.response.body or b'').decode(errors='replace'))
        except (OSError, TimeoutError) as exc:
            return client.respond(503, f'the Foxglove server is not reachable: {exc}\n')
        self._upstreams[client] = upstream
        tie = asyncio.create_task(self._tie(client, upstream))
        self._ties.add(tie)
        tie.add_done_callback(self._ties.discard)
        return None

    def _select_subprotocol(self, client: ServerConnection, offered) -> str | None:
        """The SDK's choice, under the name the client offered it."""
        chosen = self._upstreams[client].subprotocol
        if chosen is None or chosen in offered:
            return chosen
        return next(p for p in offered if ALIASES.get(p) == chosen)

    async def _tie(self, client: ServerConnection, upstream) -> None:
        """The upstream connection ends with its client (also one whose handshake failed after
        the upstream connection was made)."""
        try:
            await client.wait_closed()
            await upstream.close()
        finally:
            self._upstreams.pop(client, None)

    # -- the open connection: frames both ways ------------------------------------------------
    async def _relay(self, client: ServerConnection) -> None:
        upstream = self._upstreams.get(client)
        if upstream is None:            # the client left already: nothing to relay
            return
        legacy = client.subprotocol == LEGACY
        tasks = [asyncio.create_task(self._down(upstream, client, legacy)),
                 asyncio.create_task(self._up(client, upstream))]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await upstream.close()
            await client.close(*_close_args(upstream))   # no-op once the client closed

    @staticmethod
    async def _up(client, upstream) -> None:
        async for message in client:
            await upstream.send(message)

    async def _down(self, upstream, client, legacy: bool) -> None:
        async for message in upstream:
            if legacy and not self._in_v1(message):
                continue
            await client.send(message)

    def _in_v1(self, message) -> bool:
        """Whether a message of the SDK's server is one foxglove.websocket.v1 defines."""
        if isinstance(message, str):
            try:
                kind = json.loads(message).get('op')
            except (ValueError, AttributeError):
                kind = None
            known = kind in V1_SERVER_OPS
        else:
            kind = f'binary opcode {message[0]}' if message else 'empty binary'
            known = bool(message) and message[0] in V1_SERVER_OPCODES
        if not known and kind not in self._dropped:
            self._dropped.add(kind)
            self._warn(f'not relaying {kind!r} messages to {LEGACY} clients (not in that '
                       'protocol)')
        return known

    # -- the end --------------------------------------------------------------------------------
    def close(self) -> None:
        """Close every connection (code 1001, going away), stop listening, end the thread."""
        if self._loop.is_closed():
            return
        try:
            asyncio.run_coroutine_threadsafe(self._close(), self._loop).result()
        finally:
            self._stop_loop()

    async def _close(self) -> None:
        self._server.close()
        await self._server.wait_closed()            # every client closed, every relay ended
        for upstream in list(self._upstreams.values()):
            await upstream.close()
        if self._ties:
            await asyncio.gather(*self._ties, return_exceptions=True)

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join()
        self._loop.close()
