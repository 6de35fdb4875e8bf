"""The Foxglove layout of a psl graph: the scene in 3-D, the learning curve, the joints.

Built with the Foxglove SDK's layout types (`foxglove.layouts`) from the graph's topic names
(`psl_ros.names`), so it names exactly what the graph publishes; the same topics live
(`psl_ros.foxglove_view`) and in a bag of `psl record`, so one layout serves both. ``psl view
--layout FILE`` writes it for a namespace; the repository ships the one of the root namespace
(docs/foxglove/psl.layout.json, checked against this function by test/test_view.py). Import it
in the Foxglove app: Layouts, Import from file.

The panels: a 3-D panel on the simulator's scene (the arm, the obstacles and targets, the hand's
path) displayed in the frame ``world``; plots against the session's rollout count of each
rollout's reward and the best on its task, of the rollouts per task and the tasks solved, and
of the skill's predictive variance at each task's instance; the first joint's measured and
reference angle over time; and the current task instance as a message.
"""
from __future__ import annotations

import foxglove.layouts as fl

from psl_ros import names

JOINTS_PLOTTED = 1      # joints shown measured against reference (the first ones)


def _topic(namespace: str, name: str) -> str:
    return '/' + names.under(namespace.strip('/'), name)


def psl_layout(namespace: str = '') -> fl.Layout:
    """The layout of the graph running under `namespace` ('' = the root)."""
    progress = _topic(namespace, names.LEARNING_PROGRESS)
    rollout = fl.PlotXAxisPath(value=f'{progress}.rollout')

    def curve(title: str, fields: list[tuple[str, str]]) -> fl.PlotPanel:
        return fl.PlotPanel(title=title, config=fl.PlotConfig(
            x_axis_val='custom', x_axis_path=rollout, x_axis_label='rollout',
            paths=[fl.PlotSeries(value=f'{progress}.{name}', label=label,
                                 timestamp_method='receiveTime') for name, label in fields]))

    scene = fl.ThreeDeePanel(title='scene (frame world)', config=fl.ThreeDeeConfig(
        follow_tf=names.WORLD_FRAME,
        topics={_topic(namespace, names.SCENE): fl.BaseRendererRosMarkerTopicSettings(
            visible=True)}))
    joints = fl.PlotPanel(title='joints: measured and reference [rad]', config=fl.PlotConfig(
        x_axis_val='timestamp', paths=[
            fl.PlotSeries(value=f'{_topic(namespace, topic)}{field}[{k}]',
                          label=f'{label} {k}', timestamp_method='receiveTime')
            for k in range(JOINTS_PLOTTED)
            for topic, field, label in (
                (names.JOINT_STATES, '.position', 'measured'),
                (names.PSL_CONTROLLER_STATE, '.reference.positions', 'reference'))]))
    instance = fl.RawMessagesPanel(title='task instance', config=fl.RawMessagesConfig(
        topic_path=_topic(namespace, names.TASK_INSTANCE), expansion='all'))
    plots = fl.SplitContainer(direction='column', items=[
        fl.SplitItem(content=curve('learning curve', [('reward', 'reward'),
                                                      ('best_reward', 'best on the task')])),
        fl.SplitItem(content=curve('tasks', [('rollouts_on_task', 'rollouts on the task'),
                                             ('tasks_solved', 'tasks solved'),
                                             ('task_index', 'task')])),
        fl.SplitItem(content=curve('skill variance at the instance',
                                   [('skill_variance', 'mean predictive variance')])),
        fl.SplitItem(content=joints)])
    left = fl.SplitContainer(direction='column', items=[
        fl.SplitItem(proportion=3, content=scene), fl.SplitItem(content=instance)])
    return fl.Layout(content=fl.SplitContainer(direction='row', items=[
        fl.SplitItem(proportion=3, content=left), fl.SplitItem(proportion=2, content=plots)]))


def layout_json(namespace: str = '') -> str:
    """`psl_layout` as the JSON the Foxglove app imports (indented, ending in a newline)."""
    import json

    return json.dumps(json.loads(psl_layout(namespace).to_json()), indent=2) + '\n'
