"""The reference of the graph benchmarks: a bare publish/answer round trip between two processes.

`RoundTrip` publishes a small message to an echo process (`echo_main`, started and ended
there by PID) and waits for its answer, with the QoS of the robot loop's topics, in chunks
between other work (`measure_round_trip`: one chunk); one lockstep control step is at least
one such round trip (state out, command back).
"""
from __future__ import annotations

import subprocess
import sys
import time

from psl_ros.qos import RELIABLE

ECHO_TOPICS = ('bench/ping', 'bench/pong')


def echo_main() -> None:
    """A second process that answers every ping with a pong (the reference round trip)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from std_msgs.msg import Float64MultiArray

    rclpy.init()
    node = Node('bench_echo')
    pub = node.create_publisher(Float64MultiArray, ECHO_TOPICS[1], RELIABLE)
    node.create_subscription(Float64MultiArray, ECHO_TOPICS[0], pub.publish, RELIABLE)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


class RoundTrip:
    """An echo process and a ping node, kept up so that round trips can be measured in
    chunks between other work (a context manager; the echo is ended by PID on exit).

    Raises:
        RuntimeError: the echo did not come up, or a pong did not come within 5 s.
    """

    def __enter__(self) -> 'RoundTrip':
        import rclpy
        from rclpy.node import Node
        from std_msgs.msg import Float64MultiArray

        self._echo = subprocess.Popen(
            [sys.executable, '-c', 'from psl_bench.round_trip import echo_main; echo_main()'],
            start_new_session=True)
        self._context = rclpy.Context()
        rclpy.init(context=self._context)
        try:
            node = Node('bench_ping', context=self._context)
            self._got: list = []
            node.create_subscription(Float64MultiArray, ECHO_TOPICS[1], self._got.append,
                                     RELIABLE)
            self._pub = node.create_publisher(Float64MultiArray, ECHO_TOPICS[0], RELIABLE)
            self._executor = rclpy.executors.SingleThreadedExecutor(context=self._context)
            self._executor.add_node(node)
            deadline = time.monotonic() + 20
            while (self._pub.get_subscription_count() == 0
                   or node.count_publishers(ECHO_TOPICS[1]) == 0):
                if time.monotonic() > deadline:
                    raise RuntimeError('the echo process did not come up')
                self._executor.spin_once(timeout_sec=0.05)
            time.sleep(0.5)
            self._msg = Float64MultiArray(data=[0.0, 0.0, 0.0])
            self.measure(50)                       # warm-up, not reported
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def measure(self, n: int) -> list[float]:
        """Round-trip times [s] of n publish/answer exchanges."""
        times = []
        for _ in range(n):
            self._got.clear()
            start = time.perf_counter()
            self._pub.publish(self._msg)
            while not self._got:
                self._executor.spin_once(timeout_sec=1.0)
                if not self._got and time.perf_counter() - start > 5:
                    raise RuntimeError('no pong within 5 s')
            times.append(time.perf_counter() - start)
        return times

    def __exit__(self, *exc) -> None:
        import rclpy
        rclpy.try_shutdown(context=self._context)
        self._echo.send_signal(2)
        try:
            self._echo.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self._echo.kill()
            self._echo.wait()


def measure_round_trip(n: int) -> list[float]:
    """Round-trip times [s] of n publish/answer exchanges with an echo process."""
    with RoundTrip() as round_trip:
        return round_trip.measure(n)
