"""The reference of the graph benchmarks: a bare publish/answer round trip between two processes.

`measure_round_trip` publishes a small message to an echo process (`echo_main`, started and
ended here by PID) and waits for its answer, with the QoS of the robot loop's topics; one
lockstep control step is at least one such round trip (state out, command back).
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


def measure_round_trip(n: int) -> list[float]:
    """Round-trip times [s] of n publish/answer exchanges with an echo process."""
    import rclpy
    from rclpy.node import Node
    from std_msgs.msg import Float64MultiArray

    echo = subprocess.Popen([sys.executable, '-c', 'from psl_bench.round_trip import echo_main; '
                             'echo_main()'], start_new_session=True)
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = Node('bench_ping', context=context)
        got = []
        node.create_subscription(Float64MultiArray, ECHO_TOPICS[1], got.append, RELIABLE)
        pub = node.create_publisher(Float64MultiArray, ECHO_TOPICS[0], RELIABLE)
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() == 0 or node.count_publishers(ECHO_TOPICS[1]) == 0:
            if time.monotonic() > deadline:
                raise RuntimeError('the echo process did not come up')
            executor.spin_once(timeout_sec=0.05)
        time.sleep(0.5)
        msg = Float64MultiArray(data=[0.0, 0.0, 0.0])
        times = []
        for i in range(n + 50):
            got.clear()
            start = time.perf_counter()
            pub.publish(msg)
            while not got:
                executor.spin_once(timeout_sec=1.0)
                if not got and time.perf_counter() - start > 5:
                    raise RuntimeError('no pong within 5 s')
            if i >= 50:    # warm-up excluded
                times.append(time.perf_counter() - start)
        return times
    finally:
        rclpy.try_shutdown(context=context)
        echo.send_signal(2)
        try:
            echo.wait(timeout=5)
        except subprocess.TimeoutExpired:
            echo.kill()
            echo.wait()
