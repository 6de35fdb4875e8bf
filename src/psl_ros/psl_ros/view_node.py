"""The view node: the running graph live in the Foxglove app (`psl_ros.foxglove_view`).

``psl up --view`` starts it with the graph; ``psl view`` starts it alone, joining a graph that
runs already (same ROS domain). Connect the Foxglove app to ``ws://localhost:8765`` (its
default; parameter ``port``) and open the layout ``psl view --layout`` writes.
"""
from __future__ import annotations

from rclpy.node import Node

from psl_ros.foxglove_view import FoxgloveView
from psl_ros.node_main import run_node
from psl_ros.parameters import declare
from psl_ros.view_parameters import SERVING, ViewParameters


class ViewNode(Node):
    def __init__(self):
        super().__init__('view')
        self.parameters = declare(self, ViewParameters)
        try:
            self.view = FoxgloveView(self, self.parameters)
        except RuntimeError as exc:      # the port is taken: the configuration's fault
            raise ValueError(str(exc)) from None
        self.get_logger().info(SERVING.format(
            url=f'ws://{self.parameters.host}:{self.view.port}'))

    def destroy_node(self):
        self.view.close()
        super().destroy_node()


def main(args=None):
    run_node(ViewNode, args)


if __name__ == '__main__':
    main()
