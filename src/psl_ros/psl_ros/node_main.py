"""The ``main()`` of every psl node (ros2/examples' minimal pattern, written once).

Init, build the node, spin (one thread, or a MultiThreadedExecutor for nodes whose callbacks
wait on other callbacks), end quietly on Ctrl-C or an external shutdown, destroy the node.
"""
from __future__ import annotations

from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node


def run_node(make_node: Callable[[], Node], args=None, threads: int = 1) -> None:
    rclpy.init(args=args)
    node = None
    try:
        node = make_node()
        if threads == 1:
            rclpy.spin(node)
        else:
            executor = MultiThreadedExecutor(num_threads=threads)
            executor.add_node(node)
            executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
