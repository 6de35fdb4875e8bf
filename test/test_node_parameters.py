"""Every node parameter declared once: the running nodes declare exactly the fields of their
parameter dataclasses (psl_cli.node_parameters), with the dataclasses' defaults and
descriptions; `psl params` writes a file that gives back those defaults; a refused update says
the dataclass's reason; and each default is written once in the sources."""
import contextlib
import dataclasses
import re
from pathlib import Path

import pytest
import yaml
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient

from psl_cli.node_parameters import node_parameters, parameter_file, reported_parameters
from psl_ros.client import RosClient
from psl_ros.futures import ask, wait_for
from psl_ros.graph import NODES, Graph
from psl_ros.parameters import defaults

NAMESPACE = 'params_test'
ROOT = Path(__file__).resolve().parents[1]
ROS_OWN = {'use_sim_time', 'start_type_description_service'}   # rclpy declares these itself


@pytest.fixture(scope='module')
def running(tmp_path_factory):
    graph = Graph(namespace=NAMESPACE, log_dir=tmp_path_factory.mktemp('params_logs'))
    try:
        graph.start()
        with RosClient(NAMESPACE) as client:
            yield graph, client
    finally:
        graph.stop()


@contextlib.contextmanager
def parameter_client(client, node: str):
    """rclpy's AsyncParameterClient of a node of the graph, its service clients destroyed at
    the end (it has no destroy of its own in Jazzy)."""
    parameters = AsyncParameterClient(client.node, f'/{NAMESPACE}/{node}')
    try:
        assert parameters.wait_for_services(timeout_sec=30.0), f'{node} serves no parameters'
        yield parameters
    finally:
        for name, value in vars(parameters).items():
            if name.endswith('_client'):
                client.node.destroy_client(value)


def _expected(node: str) -> dict:
    out = {}
    for cls in node_parameters()[node]:
        out.update(defaults(cls))
    return out


def _asked(call, what: str):
    """The answer to a read-only parameter request, asked again after 10 s without one
    (`psl_ros.futures.ask`: a request sent while the server's reader has not yet matched this
    client's writer is lost, though the service counts as ready: seen once in CI for
    list_parameters)."""
    return ask(call, 10.0, what, attempts=4)


def _declared(client, node: str) -> tuple[dict, dict]:
    """(name -> value, name -> description) of what the running node declares."""
    with parameter_client(client, node) as parameters:
        listed = _asked(parameters.list_parameters, 'list_parameters').result.names
        names = [n for n in listed if n not in ROS_OWN]
        values = _asked(lambda: parameters.get_parameters(names), 'get_parameters').values
        described = _asked(lambda: parameters.describe_parameters(names),
                           'describe_parameters').descriptors
    return ({n: parameter_value_to_python(v) for n, v in zip(names, values)},
            {d.name: d.description for d in described})


@pytest.mark.parametrize('node', [name for name, _, _ in NODES])
def test_a_running_node_declares_its_dataclasses_fields(running, node):
    graph, client = running
    values, descriptions = _declared(client, node)
    expected = _expected(node)
    reported = reported_parameters().get(node, ())     # what a controller says of itself
    assert set(values) == set(expected) | set(reported), \
        (node, sorted(set(values) ^ (set(expected) | set(reported))))
    passed = graph.params(node)                 # what the launcher sets on the command line
    for name, default in expected.items():
        if name not in passed:
            got = values[name]
            got = got if isinstance(got, (str, bool, int, float)) else list(got)
            assert got == default, (node, name, got, default)
    for cls in node_parameters()[node]:
        for field in dataclasses.fields(cls):
            assert descriptions[field.name] == field.metadata['doc'], (node, field.name)


def test_an_update_is_refused_with_the_dataclasses_reason(running):
    _, client = running
    with parameter_client(client, 'sim') as parameters:
        (result,) = wait_for(parameters.set_parameters([Parameter('scene_rate', value=-1.0)]),
                             10.0, 'set_parameters').results
        assert not result.successful and result.reason == 'scene_rate must be >= 0 Hz'
        # a valid one is taken (the default again: the other tests see the defaults)
        default = _expected('sim')['scene_rate']
        (result,) = wait_for(parameters.set_parameters([Parameter('scene_rate',
                                                                  value=default)]),
                             10.0, 'set_parameters').results
        assert result.successful


@pytest.mark.parametrize('value', [[float('nan'), 1.0, 1.0], [-1.0, 1.0, 1.0], [1.0]])
def test_bad_gains_are_refused_and_the_controller_keeps_its_own(running, value):
    _, client = running
    with parameter_client(client, 'pd_controller') as parameters:
        (result,) = _asked(lambda: parameters.set_parameters(
            [Parameter('kp', value=value)]), 'set_parameters').results
        assert not result.successful and 'kp needs 3 finite values >= 0' in result.reason
        (kept,) = _asked(lambda: parameters.get_parameters(['kp']), 'get_parameters').values
        assert list(kept.double_array_value) == [0.0]


def test_the_controller_says_what_it_drives(running):
    """JTC's parameters joints (the task's, its order) and command_interfaces (effort)."""
    _, client = running
    from psl_task.arm_model import joint_names_of
    from psl_task.task import load_task
    with parameter_client(client, 'pd_controller') as parameters:
        joints, interfaces = _asked(lambda: parameters.get_parameters(
            ['joints', 'command_interfaces']), 'get_parameters').values
    assert list(joints.string_array_value) == joint_names_of(load_task('reach_over_obstacle'))
    assert list(interfaces.string_array_value) == ['effort']


@pytest.mark.parametrize('node', sorted(node_parameters()))
def test_psl_params_writes_the_defaults(node):
    written = yaml.safe_load(parameter_file(node))['/**']['ros__parameters'] or {}
    assert written == _expected(node)


def test_every_dataclass_field_is_described():
    for node, classes in node_parameters().items():
        for cls in classes:
            for field in dataclasses.fields(cls):
                assert field.metadata.get('doc'), f'{node}: {cls.__name__}.{field.name}'


@pytest.mark.parametrize('literal, home', [
    ("'reach_over_obstacle'", 'src/psl_task/psl_task/__init__.py'),
    ('120.0', 'src/psl_ros/psl_ros/timeouts.py'),
])
def test_a_default_is_written_once_in_the_sources(literal, home):
    """The default task and the rollout timeout: one place in the code (tests, task files and
    docs may name them)."""
    found = [str(path.relative_to(ROOT)) for path in sorted(ROOT.glob('src/*/psl_*/**/*.py'))
             if re.search(re.escape(literal) + r'(?![\d])', path.read_text())]
    assert found == [home]


def test_no_node_ships_a_parameter_file():
    """A shipped file (psl up passed them) would win over the dataclasses silently."""
    assert not sorted(ROOT.glob('src/*/config/*.yaml'))


def test_psl_params_names_the_nodes_for_an_unknown_one(capsys):
    from psl_cli.main import main
    assert main(['params', 'simulator']) == 2
    assert "no node 'simulator'; nodes: sim, pd_controller" in capsys.readouterr().err
    assert main(['params', 'learner']) == 0
    assert 'rollout_timeout: 120.0' in capsys.readouterr().out
