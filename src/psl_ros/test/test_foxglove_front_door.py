"""The view's front door (psl_ros.foxglove_front_door) before a bare Foxglove SDK server, no ROS:
either subprotocol name is served and a client of neither is refused as the SDK refuses; a
client that leaves ends its upstream connection (the SDK ends its subscriptions) and the SDK's
end closes the client; a ``foxglove.websocket.v1`` client gets no message that protocol lacks;
`close` leaves no thread and no connection."""
import json
import socket
import threading

import foxglove
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from psl_ros.foxglove_front_door import LEGACY, FrontDoor

SDK = 'foxglove.sdk.v1'
WAIT = 10.0                 # s, for a handshake, a message or a close on this machine
TOPIC = '/t'
PAYLOAD = b'\x00\x01\x00\x00\x05\x00\x00\x00'      # CDR of an int32 5


class Listener:
    """The SDK's server listener: subscriptions as they come and go."""

    def __init__(self):
        self.subscribed, self.unsubscribed = threading.Event(), threading.Event()

    def on_subscribe(self, client, channel):
        self.subscribed.set()

    def on_unsubscribe(self, client, channel):
        self.unsubscribed.set()


@pytest.fixture
def listener():
    return Listener()


@pytest.fixture
def sdk(listener):
    """The SDK's server on a free loopback port with one channel, playback control declared (so
    that it sends a message foxglove.websocket.v1 lacks: the playback state, opcode 5)."""
    context = foxglove.Context()
    server = foxglove.start_server(name='sdk', host='127.0.0.1', port=0, context=context,
                                   server_listener=listener, playback_time_range=(0, 10**9))
    channel = foxglove.Channel(TOPIC, message_encoding='cdr', context=context,
                               schema=foxglove.Schema(name='a/B', encoding='ros2msg',
                                                      data=b'int32 x'))
    try:
        yield server, channel
    finally:
        server.stop()


@pytest.fixture
def door(sdk):
    warnings = []
    door = FrontDoor('127.0.0.1', 0, f'ws://127.0.0.1:{sdk[0].port}', warn=warnings.append)
    door.warnings = warnings
    try:
        yield door
    finally:
        door.close()
    assert not [t for t in threading.enumerate() if t.name == 'view_front_door']


def open_client(door, subprotocols):
    return connect(f'ws://127.0.0.1:{door.port}', subprotocols=subprotocols,
                   open_timeout=WAIT, proxy=None)


def receive_json(ws, op: str) -> dict:
    """The next text message of `op` (others skipped); TimeoutError past WAIT."""
    while True:
        frame = ws.recv(timeout=WAIT)
        if isinstance(frame, str) and json.loads(frame)['op'] == op:
            return json.loads(frame)


@pytest.mark.parametrize('offered, taken', [
    ([LEGACY], LEGACY), ([SDK], SDK), ([LEGACY, SDK], SDK), ([SDK, LEGACY], SDK)])
def test_either_name_is_served_and_a_message_relayed(door, sdk, listener, offered, taken):
    server, channel = sdk
    with open_client(door, offered) as ws:
        assert ws.subprotocol == taken
        assert receive_json(ws, 'serverInfo')['name'] == 'sdk'
        [advertised] = receive_json(ws, 'advertise')['channels']
        assert (advertised['topic'], advertised['schema']) == (TOPIC, 'int32 x')
        ws.send(json.dumps({'op': 'subscribe',
                            'subscriptions': [{'id': 7, 'channelId': advertised['id']}]}))
        assert listener.subscribed.wait(WAIT)
        channel.log(PAYLOAD, log_time=123)
        frame = ws.recv(timeout=WAIT)
        assert frame == b'\x01' + (7).to_bytes(4, 'little') + (123).to_bytes(8, 'little') \
            + PAYLOAD
    # the client gone: its upstream connection closed, so the SDK ended its subscription
    assert listener.unsubscribed.wait(WAIT)


@pytest.mark.parametrize('offered', [['foxglove.websocket.v2'], None], ids=['unknown', 'none'])
def test_a_client_of_neither_name_is_refused_as_the_sdk_refuses(door, offered):
    with pytest.raises(InvalidStatus) as refused:
        open_client(door, offered).close()
    assert refused.value.response.status_code == 400


def test_the_sdk_ending_closes_the_client(door, sdk):
    with open_client(door, [LEGACY]) as ws:
        receive_json(ws, 'serverInfo')
        sdk[0].stop()
        with pytest.raises(ConnectionClosed):
            while True:
                ws.recv(timeout=WAIT)


def test_a_legacy_client_gets_no_message_its_protocol_lacks(door, sdk):
    server, _ = sdk
    with open_client(door, [LEGACY]) as legacy, open_client(door, [SDK]) as current:
        receive_json(legacy, 'serverInfo')
        receive_json(current, 'serverInfo')
        server.broadcast_playback_state(foxglove.websocket.PlaybackState(
            status=foxglove.websocket.PlaybackStatus.Playing, current_time=1,
            playback_speed=1.0, did_seek=False, request_id=None))
        while not isinstance(frame := current.recv(timeout=WAIT), bytes):
            pass
        assert frame[0] == 5        # the SDK's client gets it
        server.publish_status('after', foxglove.websocket.StatusLevel.Info, 'mark')
        seen = []
        while not (isinstance(frame := legacy.recv(timeout=WAIT), str)
                   and json.loads(frame)['op'] == 'status'):
            seen.append(frame)
        assert not [f for f in seen if isinstance(f, bytes)], seen
        assert door.warnings == [f"not relaying 'binary opcode 5' messages to {LEGACY} "
                                 'clients (not in that protocol)']


def test_close_ends_every_connection(door):
    with open_client(door, [SDK]) as ws:
        receive_json(ws, 'serverInfo')
        door.close()
        with pytest.raises(ConnectionClosed):
            while True:
                ws.recv(timeout=WAIT)
        assert ws.close_code == 1001        # going away
    door.close()                            # again: nothing


def test_a_taken_port_is_an_os_error(door, sdk):
    with pytest.raises(OSError):
        FrontDoor('127.0.0.1', door.port, f'ws://127.0.0.1:{sdk[0].port}')
    with socket.create_connection(('127.0.0.1', door.port), timeout=WAIT):
        pass                                # the first one still listens
