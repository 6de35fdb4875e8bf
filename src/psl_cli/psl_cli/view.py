"""``psl view``: the running graph live in the Foxglove app, or its layout.

Starts the view node (`psl_ros.view_node`) in this process, joining the graph that runs in this
ROS domain (``psl up --view`` starts the same node with the graph): a Foxglove WebSocket server
on ws://127.0.0.1:8765, the Foxglove app's default connection. ``--layout FILE`` writes the
Foxglove layout of the graph's topics (`psl_ros.foxglove_layout`) and exits.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from psl_cli import options
from psl_cli.options import fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    from psl_ros.view_parameters import DEFAULT_PORT, ViewParameters

    p.add_argument('--port', type=options.port,
                   help=f'TCP port of the WebSocket server (default ${options.VIEW_PORT_VARIABLE}'
                   f", else {DEFAULT_PORT}, the Foxglove app's; 0 = a free one, logged)")
    p.add_argument('--host', default=ViewParameters.host,
                   help=f'address to bind (default {ViewParameters.host}: this machine only)')
    p.add_argument('--namespace', default='', help="the graph's namespace (psl up --namespace)")
    p.add_argument('--max-rate', type=options.non_negative_float,
                   default=ViewParameters.max_rate,
                   help='most messages per second forwarded of one topic (default '
                   f'{ViewParameters.max_rate:g}; 0 = all)')
    p.add_argument('--topics', nargs='+', metavar='TOPIC',
                   help="topics to offer (default: every topic of the graph)")
    p.add_argument('--layout', metavar='FILE',
                   help='write the Foxglove layout of the graph (in --namespace) to FILE and '
                   'exit; import it in the app (Layouts, Import from file)')


def run(args: argparse.Namespace) -> int:
    if args.layout:
        from psl_ros.foxglove_layout import layout_json

        try:
            Path(args.layout).write_text(layout_json(args.namespace))
        except OSError as exc:
            return fail('psl view', exc, 1)
        print(f'wrote the Foxglove layout to {args.layout}')
        return 0
    from psl_ros.node_main import run_node
    from psl_ros.view_node import ViewNode

    try:
        port = options.view_port(args.port)
    except ValueError as exc:
        return fail('psl view', exc, 2)

    ros_args = ['psl view', '--ros-args', '-p', f'port:={port}', '-p',
                f'host:={args.host}', '-p', f'max_rate:={float(args.max_rate)}']
    if args.namespace.strip('/'):
        ros_args += ['-r', f'__ns:=/{args.namespace.strip("/")}']
    if args.topics:
        ros_args += ['-p', 'topics:=[' + ','.join(args.topics) + ']']
    try:
        run_node(ViewNode, ros_args)
    except SystemExit as exc:       # the node could not start (it said why)
        return int(exc.code or 1)
    return 0
