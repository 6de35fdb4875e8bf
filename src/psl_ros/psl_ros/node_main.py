"""The ``main()`` of every psl node (ros2/examples' minimal pattern, written once).

Init, build the node, spin (one thread, or a MultiThreadedExecutor for nodes whose callbacks
wait on other callbacks), end quietly on Ctrl-C or an external shutdown, destroy the node. A
node that cannot be built from its parameters (a ValueError while it is made: a task it cannot
load, a bad parameter value) says why in one line on stderr and exits with 1, no traceback.
"""
from __future__ import annotations

import sys
from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node


def run_node(make_node: Callable[[], Node], args=None, threads: int = 1) -> None:
    rclpy.init(args=args)
    node = None
    try:
        try:
            node = make_node()
        except ValueError as exc:       # e.g. psl_task.task.TaskError: the configuration's fault
            print(f'{getattr(make_node, "__name__", "node")}: cannot start: {exc}',
                  file=sys.stderr, flush=True)
            raise SystemExit(1) from None
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
