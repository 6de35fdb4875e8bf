"""Waiting for rclpy futures: `wait_for` names what did not answer; `ask` sends an idempotent
request again after a lost answer and gives up after its attempts."""
import pytest
from rclpy.task import Future

from psl_ros.futures import ask, wait_for

SHORT = 0.05        # s: a timeout the tests wait out on purpose


def answered(value) -> Future:
    future = Future()
    future.set_result(value)
    return future


def test_wait_for_returns_the_result_or_names_what_did_not_answer():
    assert wait_for(answered(3), SHORT, 'x') == 3
    with pytest.raises(TimeoutError, match='no answer from the server'):
        wait_for(Future(), SHORT, 'the server')


def test_ask_sends_again_after_a_lost_answer():
    sent = []

    def call():
        sent.append(len(sent))
        return Future() if len(sent) < 3 else answered('at last')   # two answers lost
    assert ask(call, SHORT, 'the server', attempts=3) == 'at last'
    assert len(sent) == 3


def test_ask_gives_up_after_its_attempts():
    sent = []

    def call():
        sent.append(1)
        return Future()
    with pytest.raises(TimeoutError, match='the server to 2 requests'):
        ask(call, SHORT, 'the server', attempts=2)
    assert len(sent) == 2
