"""psl up --view: the running graph live in Foxglove, checked with a WebSocket client of the
Foxglove protocol (psl_bench.foxglove_client) against what the graph published in ROS.

The view node offers every topic with its message definition; it subscribes to a topic in ROS
only while a viewer watches it; a viewer receives the very bytes the graph published (compared
with the test's own ROS subscriptions) and decodes them with the advertised schemas; the
learning progress of a graph-mode session arrives rollout by rollout and agrees with the
session's metrics; a viewer joining later gets the latched scene; a viewer of a graph that
has run no rollout yet is offered every topic of the layout and gets the scene as the simulator
started; the shipped layout names topics and fields the graph has. A viewer offering either
name of the subprotocol (``foxglove.websocket.v1``: Lichtblick, clients of foxglove_bridge;
``foxglove.sdk.v1``: the Foxglove app) is served the same; one offering neither is refused."""
import json
import re
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from psl_bench.foxglove_client import SUBPROTOCOLS, FoxgloveClient
from psl_controller.policy import policy_for
from psl_ros import names
from psl_ros.bag_recorder import import_message_class
from psl_ros.foxglove_layout import layout_json
from psl_ros.graph import Graph, find_executable, pid_alive
from psl_sim.scene import END_EFFECTOR_PATH, Scene
from psl_task.arm_model import ArmModel
from psl_task.task import load_task

ROOT = Path(__file__).resolve().parents[1]
SHIPPED_LAYOUT = ROOT / 'docs' / 'foxglove' / 'psl.layout.json'
TASK = 'reach_over_obstacle'
VIEWED = ['/' + t for t in (names.SCENE, names.JOINT_STATES, names.PSL_CONTROLLER_STATE,
                            names.TASK_INSTANCE, names.LEARNING_PROGRESS)]
LATCHED = {'/' + names.SCENE, '/' + names.TASK_INSTANCE}
SESSION = dict(task=TASK, strategy='bootstrap', num_tasks=2, max_rollouts_per_task=6, seed=1,
               mode='graph', num_test=1)
WAIT = 30.0                 # s, for a process, a port or a delivery
IDLE = 'idle_view'          # namespace of a graph of its own that runs no rollout
POSE_TOLERANCE = 1e-9       # m, a marker's position against the scene computed here


@pytest.fixture(scope='module')
def graph_options(tmp_path_factory):
    """The graph with the view node on a free port, the memory and sessions in a folder."""
    root = tmp_path_factory.mktemp('view_memory')
    return {'view_port': 0, 'extra_params': {'skill_memory': {'memory_dir': str(root)},
                                             'learner': {'output_root': str(root / 'runs')}}}


@pytest.fixture(scope='module')
def url(graph):
    return graph.view_url(WAIT)


class Published:
    """The test's own ROS subscriptions (raw bytes) to the viewed topics: what the graph
    published, to compare the viewer's messages with."""

    def __init__(self, node, topics):
        self.lock, self.messages = threading.Lock(), {t: [] for t in topics}
        self.subscriptions = []
        for topic in topics:
            msgtype = dict(node.get_topic_names_and_types())[topic][0]
            qos = QoSProfile(history=HistoryPolicy.KEEP_ALL,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=(DurabilityPolicy.TRANSIENT_LOCAL if topic in LATCHED
                                         else DurabilityPolicy.VOLATILE))
            self.subscriptions.append(node.create_subscription(
                import_message_class(msgtype), topic,
                lambda data, t=topic: self._keep(t, data), qos, raw=True))

    def matched(self) -> bool:
        """Every subscription has matched its topic's publishers (none is missed from now)."""
        return all(s.get_publisher_count() > 0 for s in self.subscriptions)

    def _keep(self, topic, data) -> None:
        with self.lock:
            self.messages[topic].append(bytes(data))

    def of(self, topic) -> list[bytes]:
        with self.lock:
            return list(self.messages[topic])


def stamp_of(msg_class, data: bytes):
    """The header stamp of a serialised message (None for a type without a header)."""
    from rclpy.serialization import deserialize_message

    msg = deserialize_message(data, msg_class)
    header = getattr(msg, 'header', None)
    return None if header is None else (header.stamp.sec, header.stamp.nanosec)


def view_subscribes(client, topic: str) -> bool:
    return any(info.node_name == 'view'
               for info in client.node.get_subscriptions_info_by_topic(topic))


def view_subscriptions(client) -> set[str] | None:
    """The topics the view node subscribes to in ROS, as the graph sees it; None while the
    node is not discovered."""
    from rclpy._rclpy_pybind11 import NodeNameNonExistentError
    try:
        return {name for name, _ in
                client.node.get_subscriber_names_and_types_by_node('view', '/')}
    except NodeNameNonExistentError:
        return None


def nobody_watches(client, wait_until) -> None:
    """Until the view subscribes to nothing (a viewer of an earlier test gone: every test
    starts and ends so, in whatever order they run)."""
    assert wait_until(lambda: view_subscriptions(client) == set(), WAIT), \
        view_subscriptions(client)


def test_a_topic_is_subscribed_in_ros_only_while_a_viewer_watches_it(url, client, wait_until):
    nobody_watches(client, wait_until)
    viewer = FoxgloveClient(url)
    try:
        assert viewer.wait_channels(VIEWED, WAIT), sorted(viewer.channels)
        assert view_subscriptions(client) == set()     # channels offered, nothing subscribed
        viewer.subscribe(['/' + names.JOINT_STATES])
        # that topic and only that one
        assert wait_until(lambda: view_subscriptions(client) == {'/' + names.JOINT_STATES},
                          WAIT), view_subscriptions(client)
    finally:
        viewer.close()
    nobody_watches(client, wait_until)


def test_a_viewer_sees_the_session_as_the_graph_published_it(url, client, graph,
                                                            wait_until):
    nobody_watches(client, wait_until)
    assert wait_until(lambda: set(VIEWED) <= set(dict(client.node.get_topic_names_and_types())),
                      WAIT)
    published = Published(client.node, VIEWED)
    assert wait_until(published.matched, WAIT)
    viewer = FoxgloveClient(url)
    try:
        assert viewer.subprotocol in SUBPROTOCOLS and viewer.server_info['name'] == 'psl'
        assert viewer.wait_channels(VIEWED, WAIT)
        types = dict(client.node.get_topic_names_and_types())
        for topic in VIEWED:             # each channel: the topic's type and its definition
            channel = viewer.channels[topic]
            assert [channel['schemaName']] == types[topic], topic
            assert (channel['encoding'], channel['schemaEncoding']) == ('cdr', 'ros2msg')
        viewer.subscribe(VIEWED)
        assert wait_until(lambda: all(view_subscribes(client, t) for t in VIEWED), WAIT)

        began = client.node.get_clock().now().nanoseconds
        result = client.learn(timeout=300, **SESSION,
                              output_dir=str(Path(graph.params('learner')['output_root'])
                                             / 'viewed'))
        assert result.success, result.message
        ended = client.node.get_clock().now().nanoseconds
        metrics = json.loads(Path(result.metrics_path).read_text())
        rollouts = sum(task['rollouts'] for task in metrics['tasks'])
        progress = '/' + names.LEARNING_PROGRESS
        assert wait_until(lambda: len(published.of(progress)) == rollouts, WAIT)
        assert viewer.pump(lambda: len(viewer.messages.get(progress, [])) == rollouts, WAIT)
        assert viewer.pump(lambda: all(viewer.messages.get(t) for t in VIEWED), WAIT), \
            {t: len(viewer.messages.get(t, [])) for t in VIEWED}

        # the very bytes the graph published (of a latched topic, whose publisher keeps only
        # its newest message, a reader may miss one in a quick succession: the newest, then);
        # the learning curve complete and in order
        for topic in VIEWED:
            sent = published.of(topic)
            seen = [data for _, data in viewer.messages[topic]]
            if topic in LATCHED:
                assert viewer.pump(lambda: viewer.messages[topic][-1][1] == sent[-1], WAIT), \
                    topic
            else:       # in the order sent, none twice (at most max_rate a second of them)
                position = {data: k for k, data in enumerate(sent)}
                # a message this test's own reader lost (a busy machine: the publisher's
                # history moved on before it was taken) is one of a stamp it never received
                missed = [data for data in seen if data not in position]
                msg_class = import_message_class(types[topic][0])
                received = {stamp_of(msg_class, d) for d in sent}
                assert all(stamp_of(msg_class, data) not in received - {None}
                           and stamp_of(msg_class, data) is not None for data in missed), topic
                order = [position[data] for data in seen if data in position]
                assert order == sorted(set(order)), topic
        assert [d for _, d in viewer.messages[progress]] == published.of(progress)

        # decoded with the advertised schema: the session's learning curve
        points = viewer.decoded(progress)
        assert [p.rollout for p in points] == list(range(1, rollouts + 1))
        for record in metrics['tasks']:
            mine = [p for p in points if p.task_index == record['index']]
            assert len(mine) == record['rollouts']
            assert record['best_reward'] in [p.reward for p in mine]   # the answer's rollout
            assert mine[-1].best_reward >= record['best_reward']
            assert bool(mine[-1].task_fulfilled) == record['fulfilled']
            assert [list(p.tau) for p in mine] == [record['tau']] * len(mine)
        assert all(p.task == TASK for p in points)
        stamps = [p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in points]
        # stamped by the learner as they came (a batch's rollouts together), in the session
        assert all(a <= b for a, b in zip(stamps, stamps[1:]))
        assert began <= stamps[0] and stamps[-1] <= ended
        scenes = viewer.decoded('/' + names.SCENE)
        assert all(m.header.frame_id == names.WORLD_FRAME
                   for scene in scenes for m in scene.markers)
        states = viewer.decoded('/' + names.JOINT_STATES)
        assert all(len(s.position) == len(s.name) > 0 for s in states)

        # a viewer joining now (no episode runs, nothing new is published) gets the scene
        late = FoxgloveClient(url)
        try:
            assert late.wait_channels(LATCHED, WAIT)
            late.subscribe(sorted(LATCHED))
            assert late.pump(lambda: all(late.messages.get(t) for t in LATCHED), WAIT)
            for topic in LATCHED:
                assert late.messages[topic][-1][1] == published.of(topic)[-1], topic
        finally:
            late.close()
    finally:
        viewer.close()
        for subscription in published.subscriptions:
            client.node.destroy_subscription(subscription)
    nobody_watches(client, wait_until)


def layout_topics(namespace: str = '') -> set[str]:
    """The topics the layout of the graph under `namespace` names (its panels' topics and the
    topics of its message paths)."""
    return {topic for topic, _ in re.findall(r'"(/[a-z_/]+)(?:\.([a-z_]+))?',
                                             layout_json(namespace))}


def test_a_viewer_of_a_graph_that_has_run_no_rollout_sees_the_layouts_topics_and_the_scene(
        tmp_path):
    """A graph of its own, just started (its namespace; no rollout, no session: only what its
    nodes publish at start): a viewer is offered every topic of the layout, the scene, the
    arm's joint states and its controller's reference, the task instance and the learning
    progress, and gets the scene at once: the arm in the posture the simulator starts in (the
    model's default), the world as the model places it."""
    graph = Graph(task=TASK, namespace=IDLE, log_dir=tmp_path / 'logs', view_port=0,
                  extra_params={'skill_memory': {'memory_dir': str(tmp_path)},
                                'learner': {'output_root': str(tmp_path / 'runs')}})
    viewer = None
    try:
        graph.start()
        graph.wait_ready(timeout=60)
        viewer = FoxgloveClient(graph.view_url(WAIT))
        wanted = layout_topics(IDLE)
        assert wanted == {f'/{IDLE}/{t}' for t in (
            names.SCENE, names.JOINT_STATES, names.PSL_CONTROLLER_STATE, names.TASK_INSTANCE,
            names.LEARNING_PROGRESS)}
        assert viewer.wait_channels(wanted, WAIT), sorted(viewer.channels)
        scene = f'/{IDLE}/{names.SCENE}'
        viewer.subscribe([scene])
        assert viewer.pump(lambda: viewer.messages.get(scene), WAIT), \
            'no scene before the first rollout'
        [array] = viewer.decoded(scene)       # the one the simulator published at start
    finally:
        if viewer is not None:
            viewer.close()
        graph.stop()
        left = [p.name for p in graph.processes if pid_alive(p.pid)]
        assert not left, f'processes left behind: {left}'
    task = load_task(TASK)
    arm = ArmModel(task)                      # as the simulator starts: the model's default
    expected = Scene(arm.model)
    poses = expected.poses(expected.forward(arm.data))
    markers = {(m.ns, m.id): m for m in array.markers}
    assert {m.header.frame_id for m in array.markers} == {names.WORLD_FRAME}
    assert set(markers) == {(s.namespace, s.marker_id) for s in expected.shapes} | {
        (END_EFFECTOR_PATH, 0)}
    for k, shape in enumerate(expected.shapes):
        p = markers[shape.namespace, shape.marker_id].pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], poses.position[k], atol=POSE_TOLERANCE)
    # stamped with the simulator's time as it starts, one control period in
    assert {(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec) for m in array.markers} \
        == {task.control_period_ns}


@pytest.mark.parametrize('subprotocol', SUBPROTOCOLS)
def test_a_viewer_of_either_subprotocol_decodes_what_the_graph_published(url, client, graph,
                                                                         wait_until,
                                                                         subprotocol):
    """The old name (Lichtblick, clients of foxglove_bridge) and the SDK's name alike: a
    rollout's evaluation arrives as the very bytes the evaluator published, and decodes."""
    nobody_watches(client, wait_until)
    evaluation = '/' + names.ROLLOUT_EVALUATION
    assert wait_until(lambda: evaluation in dict(client.node.get_topic_names_and_types()),
                      WAIT)
    published = Published(client.node, [evaluation])
    viewer = None
    try:
        assert wait_until(published.matched, WAIT)
        viewer = FoxgloveClient(url, subprotocols=[subprotocol])
        assert viewer.subprotocol == subprotocol and viewer.server_info['name'] == 'psl'
        assert viewer.wait_channels([evaluation], WAIT)
        viewer.subscribe([evaluation])
        assert wait_until(lambda: view_subscribes(client, evaluation), WAIT)
        task = load_task(TASK)
        result = client.rollout(TASK, task.tau_default, policy_for(task).default_theta)
        assert result.success, result.message
        assert wait_until(lambda: len(published.of(evaluation)) == 1, WAIT)
        assert viewer.pump(lambda: viewer.messages.get(evaluation), WAIT)
        assert [data for _, data in viewer.messages[evaluation]] == published.of(evaluation)
        [decoded] = viewer.decoded(evaluation)
        assert (decoded.task, list(decoded.tau)) == (TASK, task.tau_default.tolist())
        assert decoded.reward == result.evaluation.reward
        assert decoded.num_steps == result.evaluation.num_steps
    finally:
        if viewer is not None:
            viewer.close()
        for subscription in published.subscriptions:
            client.node.destroy_subscription(subscription)
    # the viewer gone, its connection to the SDK's server behind the front door went too: the
    # view no longer subscribes in ROS
    nobody_watches(client, wait_until)


@pytest.mark.parametrize('offered', [['foxglove.websocket.v2'], None],
                         ids=['unknown', 'none'])
def test_a_viewer_offering_no_known_subprotocol_is_refused(url, offered):
    with pytest.raises(InvalidStatus) as refused:
        FoxgloveClient(url, subprotocols=offered).close()
    assert refused.value.response.status_code == 400


def test_the_shipped_layout_is_generated_and_names_what_the_graph_publishes(client,
                                                                          wait_until):
    assert wait_until(lambda: set(VIEWED) <= set(dict(client.node.get_topic_names_and_types())),
                      WAIT)
    assert SHIPPED_LAYOUT.read_text() == layout_json(), \
        'regenerate it: psl view --layout docs/foxglove/psl.layout.json'
    types = dict(client.node.get_topic_names_and_types())
    text = SHIPPED_LAYOUT.read_text()
    paths = set(re.findall(r'"(/[a-z_/]+)(?:\.([a-z_]+))?', text))
    assert {topic for topic, _ in paths} == set(VIEWED)
    for topic, field in paths:
        assert topic in types, f'the layout names {topic}, which the graph does not publish'
        if field:
            fields = import_message_class(types[topic][0]).get_fields_and_field_types()
            assert field in fields, f'{topic} has no field {field}'


def test_a_second_view_on_a_taken_port_says_so_and_exits(url):
    port = url.rsplit(':', 1)[1]
    process = subprocess.Popen([str(find_executable('psl_ros', 'view')), '--ros-args', '-p',
                                f'port:={port}'], stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, start_new_session=True)
    try:
        out, _ = process.communicate(timeout=WAIT)
        assert process.returncode == 1
        assert f'cannot serve Foxglove on 127.0.0.1:{port}' in out.decode()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
