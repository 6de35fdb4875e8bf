"""The simulator takes a command only as the answer to its latest state (lockstep) or to a
state of the running episode (realtime): a command the controller published before that state
answers an older one (the last state of the episode before, delivered late under load) and
must not drive the new episode. The node runs in this process; commands are handed to its
callback with the message info the middleware would give (source timestamp, wall clock ns)."""
import time

import pytest
import rclpy
from std_msgs.msg import Float64MultiArray

from psl_msgs.srv import ResetTask
from psl_sim.sim_node import SimNode


@pytest.fixture(params=['lockstep', 'realtime'])
def sim(request, monkeypatch, private_ros_domain):
    """A simulator node of the given mode in this process, on a domain of its own (conftest.py:
    it publishes nothing anyone here listens to, and no graph of the run commands it); its
    realtime loop is not started, so nothing but the test consumes a pending command."""
    monkeypatch.setenv('ROS_DOMAIN_ID', str(private_ros_domain))
    rclpy.init(args=['sim', '--ros-args', '-p', f'mode:={request.param}'])
    node = None
    try:
        node = SimNode()
        yield node
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


def reset(node: SimNode) -> None:
    response = node.on_reset(ResetTask.Request(task='reach_over_obstacle',
                                               tau=[0.675, 0.16]), ResetTask.Response())
    assert response.success, response.message


def command(node: SimNode, published_ns: int) -> None:
    node.on_command(Float64MultiArray(data=[1.0, 1.0, 1.0]),
                    {'source_timestamp': published_ns})


def test_a_command_published_before_the_state_is_not_its_answer(sim):
    stale = time.time_ns()                   # e.g. the answer to the last episode's last state
    reset(sim)
    if sim.mode == 'lockstep':
        steps, t0 = sim.steps_left, sim.t_ns
        command(sim, stale)                  # dropped: the state still waits for its answer
        assert (sim.steps_left, sim.t_ns, sim.stale_commands) == (steps, t0, 1)
        command(sim, time.time_ns())         # published after the state: its answer
        assert (sim.steps_left, sim.t_ns) == (steps - 1, t0 + sim.arm.task.control_period_ns)
    else:                                    # the realtime loop runs on: only the counts
        command(sim, stale)
        assert sim.stale_commands == 1
        command(sim, time.time_ns())
    assert sim.stale_commands == 1


class AnswerOnRelease:
    """The node's lock, but the controller's answer to the start state comes the instant the
    reset releases it (what a busy machine may schedule): a command handed to the node right
    after the lock's release, once."""

    def __init__(self, node: SimNode):
        self.node, self.lock, self.armed = node, node._lock, True

    def __enter__(self):
        return self.lock.__enter__()

    def __exit__(self, *exc):
        released = self.lock.__exit__(*exc)
        if self.armed:
            self.armed = False
            command(self.node, time.time_ns())
        return released


@pytest.mark.parametrize('sim', ['lockstep'], indirect=True)     # a command steps at once
def test_a_resets_stamp_is_its_episodes_start_even_when_the_answer_comes_at_once(sim):
    sim._lock = AnswerOnRelease(sim)
    response = sim.on_reset(ResetTask.Request(task='reach_over_obstacle', tau=[0.675, 0.16]),
                            ResetTask.Response())
    assert response.success, response.message
    assert sim.t_ns == sim.episode['t0'] + sim.arm.task.control_period_ns   # it stepped
    stamp = response.stamp.sec * 10**9 + response.stamp.nanosec
    assert stamp == sim.episode['t0'], (stamp, sim.episode['t0'])
