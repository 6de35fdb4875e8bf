"""The controller's watchdog on its own ticks (psl_controller.pd_controller_node): it looks
every control period and fires at its first look past ``state_timeout`` without a joint state,
never before, once, and is armed again by the next state.

Held on the node in this process, its clock (the module's ``time.monotonic``) set by the test
look by look: the graph tests (test/conftest.py `check_watchdog_silence`) can hold only that it
never fires early, since a silence measured on a busy process's clock is late by whatever the
load keeps that process from running, and has no upper bound worth asserting."""
import re
from types import SimpleNamespace

import pytest
import rclpy
from sensor_msgs.msg import JointState

from psl_controller import pd_controller_node
from psl_controller.pd_controller_node import PDController

START = 1000.0      # [s] the test's clock when the first state comes


@pytest.fixture
def controller(monkeypatch, private_ros_domain):
    """A controller node (watchdog on: its default state_timeout) in this process, on a domain
    of its own (conftest.py), its clock the test's; its timer is never spun, so the watchdog
    looks only when the test calls it."""
    monkeypatch.setenv('ROS_DOMAIN_ID', str(private_ros_domain))
    clock = SimpleNamespace(now=START)
    monkeypatch.setattr(pd_controller_node, 'time', SimpleNamespace(monotonic=lambda: clock.now))
    rclpy.init(args=['pd_controller', '--ros-args', '-p', 'state_timeout:=0.3'])
    node = None
    try:
        node = PDController()
        node.clock = clock
        node.reasons = []
        stop = node.controller.stop
        monkeypatch.setattr(node.controller, 'stop',
                            lambda reason: node.reasons.append(reason) or stop(reason))
        yield node
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


def state(node) -> JointState:
    return JointState(name=list(node.joint_names), position=[0.0] * node.n_joints,
                      velocity=[0.0] * node.n_joints)


def silent_looks(node) -> list[float]:
    """Look every control period after now until the watchdog fires: the silences (on the
    test's clock, since the last state) of the looks that did not fire, then of the one that
    did."""
    looks = []
    last = node.clock.now
    while not node.reasons:
        assert len(looks) < 10 * node.state_timeout / node.period, 'the watchdog never fired'
        node.clock.now += node.period
        looks.append(node.clock.now - last)
        node.on_watchdog()
    return looks


def test_the_watchdog_looks_every_control_period(controller):
    assert controller.state_timeout == 0.3
    assert controller.watchdog.timer_period_ns == round(controller.period * 1e9)


def test_the_watchdog_fires_at_its_first_look_past_its_timeout_once(controller):
    timeout = controller.state_timeout
    controller.clock.now += 10 * timeout
    controller.on_watchdog()                # no state yet: not armed, nothing to lose
    assert not controller.reasons
    controller.on_state(state(controller))
    looks = silent_looks(controller)
    assert all(silence <= timeout for silence in looks[:-1]) and looks[-1] > timeout
    found = re.search(r'none for ([0-9.]+) s \(state_timeout 0.3 s\)', controller.reasons[0])
    assert found and float(found[1]) == pytest.approx(looks[-1], abs=5e-4)
    controller.clock.now += controller.period
    controller.on_watchdog()                # the silence goes on: no second abort
    assert len(controller.reasons) == 1
    # a state again: armed again, from that state on
    controller.on_state(state(controller))
    controller.reasons.clear()
    looks = silent_looks(controller)
    assert all(silence <= timeout for silence in looks[:-1]) and looks[-1] > timeout
