"""The learner node: serves the ``learn_skill`` action (psl_msgs/LearnSkill).

One goal is one learning session of `psl_optimizer.learning.Learner`: for each task instance a
CMA-ES search started from the skill, the solution added to the skill memory at once. The skill
lives in the ``skill_memory`` node and is used through its services (query, add_sample, save,
load, create_skill), so other clients can query it while it learns. Rollouts run in batch mode
(in-process ``mujoco.rollout``, the default: fast) or, with ``mode: graph``, through the rollout
workers' ``execute_rollout`` action (`psl_optimizer.rollouts`: the one place a mode is chosen).

A session writes into ``<output_root>/<task>-<strategy>-seed<seed>``: after every task a
checkpoint (the memory node's memory saved there + the progress as JSON), at the end
``metrics.json``. Sending the same goal again, after a cancel, an abort or a crash of this
node, resumes from the checkpoint: the memory node is loaded from it, no finished task is
lost. Feedback comes after every batch of rollouts, and one psl_msgs/LearningProgress per
rollout on ``learning_progress`` (the learning curve: `psl_optimizer.progress_topic`). A bad
goal (unknown task or strategy, zero tasks, a skill of the task's name but other sizes in the
memory) ends with success=false and the reason; a skill the memory does not hold is created
from the task.
"""
from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
from rclpy.action import CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node

from psl_controller.policy import policy_for
from psl_msgs.action import LearnSkill
from psl_optimizer.learner_parameters import LearnerParameters
from psl_optimizer.learning import (CORRECTION_SUFFIX, Learner, LearnSettings,
                                     ResidualComposition, SessionFolderError,
                                     holds_checkpoint)
from psl_optimizer.policy_search import STRATEGIES, SearchSettings
from psl_optimizer.rollout_modes import make_rollouts
from psl_optimizer.rollouts import MODES, Rollouts, Stopped
from psl_optimizer.progress_topic import graph_session, progress_publisher
from psl_ros import names
from psl_ros.action_server import ActionServer
from psl_ros.client import MemoryClient, RolloutClient
from psl_ros.instance_source import InstanceStopped, TopicInstances
from psl_ros.node_main import run_node
from psl_ros.parameters import declare
from psl_task.task import TaskDefinition, TaskError, load_task


class ServiceSkill(ResidualComposition):
    """The skill `name` inside the skill_memory node, with the interface Learner expects; a
    skill continued from a memory file is continued the residual way (`ResidualComposition`:
    its correction is a second skill in the node, claimed with it)."""

    continuations = ('residual',)

    def __init__(self, node: 'LearnerNode', task: TaskDefinition, timeout: float,
                 continuing: bool):
        self.node, self.task, self.timeout = node, task, timeout
        # the session continues a skill (its goal's continue_from): the residual way; the
        # node may hold a correction of an earlier session in any case (a memory saved by
        # the node holds every skill it has), so that is no sign
        self.continuing = continuing
        self.name, self.correction = task.name, task.name + CORRECTION_SUFFIX
        self.owner = node.get_fully_qualified_name()     # this session's claim on the skill
        self.claimed = False

    def _call(self, service: str, **fields):
        try:
            response = self.node.memory.call(service, self.timeout, **fields)
        except TimeoutError as exc:
            raise RuntimeError(str(exc)) from exc
        if not response.success:
            raise RuntimeError(f'skill_memory/{service}: {response.message}')
        return response

    def _query(self, skill: str, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        response = self._call('query', skill=skill, tau=[float(x) for x in tau])
        return (np.asarray(response.theta),
                np.asarray(response.variance) if response.variance else None)

    def _add(self, skill: str, tau: np.ndarray, theta: np.ndarray) -> None:
        self._call('add_sample', skill=skill, tau=[float(x) for x in tau],
                   theta=[float(x) for x in theta], owner=self.owner)

    def save(self, path: Path) -> None:
        self._call('save', path=str(Path(path).resolve()))

    def _create(self, skill: str, replace: bool) -> None:
        task = self.task
        self._call('create_skill', skill=skill, tau_low=task.tau_low.tolist(),
                   tau_high=task.tau_high.tolist(),
                   theta_reference=self._reference.tolist(), replace=replace,
                   owner=self.owner)

    @property
    def _reference(self) -> np.ndarray:
        return policy_for(self.task).default_theta

    def _skills(self) -> dict:
        return json.loads(self._call('info').message)

    def start(self, continue_from: str) -> None:
        """A new session: the memory node's skill of the task replaced by an empty one, or
        (continue_from, a memory file of the node's memory_dir) loaded from that file and
        continued the residual way. The session claims the skill and its correction first:
        nobody else writes to them until `release`. A new session empties a correction an
        earlier one left in the node (a file saved later answers this session's skill)."""
        self.claim()
        if continue_from:
            self._call('load', path=continue_from, replace=True, owner=self.owner)
        self._create(self.name, replace=not continue_from)
        if continue_from or self.correction in self._skills():
            self._create(self.correction, replace=not continue_from)
        self._c0 = self._reference if continue_from else None

    def restore(self, path: Path) -> None:
        """A resumed session: the checkpoint's memory loaded into the memory node (the skill
        claimed first, as in `start`), with its correction if the session continues a skill."""
        self.claim()
        self._call('load', path=str(Path(path).resolve()), replace=True, owner=self.owner)
        self._c0 = self._reference if self.continuing else None

    def claim(self) -> None:
        for skill in (self.name, self.correction):
            self._call('claim', skill=skill, owner=self.owner)
        self.claimed = True

    def release(self) -> None:
        """End the session's claims (best effort: a claim lapses anyway when this node
        leaves the graph)."""
        if self.claimed:
            try:
                for skill in (self.name, self.correction):
                    self._call('claim', skill=skill, owner=self.owner, release=True)
                self.claimed = False
            except RuntimeError as exc:
                self.node.get_logger().warning(f'releasing the claim on {self.name!r}: {exc}')


class LearnerNode(Node):

    def __init__(self):
        super().__init__('learner')
        self.parameters = declare(self, LearnerParameters)
        self.mode = self.parameters.mode
        clients = ReentrantCallbackGroup()
        self.memory = MemoryClient(self, callback_group=clients)
        self.rollout_clients = [RolloutClient(self, worker, callback_group=clients)
                                for worker in self.parameters.workers]
        # the learning curve, one message per rollout (psl view plots it; psl record keeps it)
        self.pub_progress = progress_publisher(self)
        self._busy = threading.Lock()
        self._batch: dict[Path, Rollouts] = {}     # batch mode's rollouts per task
        self._server = ActionServer(
            self, LearnSkill, names.LEARN_SKILL, execute_callback=self.execute,
            # a second goal while a session runs is refused at once (the client hears it)
            goal_callback=lambda goal: (GoalResponse.REJECT if self._busy.locked()
                                        else GoalResponse.ACCEPT),
            cancel_callback=lambda handle: CancelResponse.ACCEPT,
            callback_group=ReentrantCallbackGroup())
        self.get_logger().info(f'serving learn_skill ({self.mode} mode)')

    # -- the action ---------------------------------------------------------------------------
    def execute(self, goal_handle) -> LearnSkill.Result:
        goal = goal_handle.request
        result = LearnSkill.Result()
        if not self._busy.acquire(blocking=False):
            goal_handle.abort()
            result.message = 'a learning session is running; cancel it or wait'
            return result
        try:
            try:
                task, settings, out, mode = self._session(goal)
            except (TaskError, ValueError) as exc:
                goal_handle.abort()
                result.message = str(exc)
                return result
            result.metrics_path = str((out / 'metrics.json').resolve())
            self.get_logger().info(f'learning {task.name} with {settings.strategy}, seed '
                                   f'{settings.seed}, {settings.num_tasks} tasks, {mode} '
                                   f'mode -> {out}')
            skill = ServiceSkill(self, task, self.parameters.service_timeout,
                                 continuing=bool(settings.continue_from))
            instances = None
            try:
                if not holds_checkpoint(out):
                    # the memory node writes the session's memory file: it checks the folder
                    # (inside its memory_dir) before any work, and makes it
                    skill.save(out / 'memory.npz')
                instances = None if settings.task_selection != 'given' else TopicInstances(
                    self, self.parameters.tau_topic, task.validate_tau,
                    self.parameters.tau_timeout, lambda: goal_handle.is_cancel_requested)
                learner = graph_session(
                    task, settings, out, self._rollouts(task, mode, goal_handle), self,
                    publisher=self.pub_progress, skill=skill, instances=instances,
                    should_stop=lambda: goal_handle.is_cancel_requested,
                    on_points=lambda points: goal_handle.publish_feedback(LearnSkill.Feedback(
                        task_index=points[-1].task_index, rollouts=points[-1].rollout,
                        best_reward=points[-1].best_reward,
                        fulfilled=points[-1].task_fulfilled)))
            except (TaskError, ValueError, RuntimeError) as exc:
                skill.release()
                if instances is not None:
                    self.destroy_subscription(instances.subscription)
                goal_handle.abort()
                result.message = str(exc)
                return result
            try:
                metrics = learner.run()
            except (Stopped, InstanceStopped):
                goal_handle.canceled()
                result.message = self._stopped('cancelled', learner)
                return result
            except SessionFolderError as exc:   # another session's checkpoint, or a damaged one
                goal_handle.abort()
                result.message = str(exc)
                return result
            except Exception as exc:  # noqa: BLE001 - report it, keep serving
                goal_handle.abort()
                result.message = self._stopped(f'stopped by an error ({exc})', learner)
                self.get_logger().error(result.message)
                return result
            finally:
                skill.release()
                if instances is not None:
                    self.destroy_subscription(instances.subscription)
            summary = metrics.summary
            goal_handle.succeed()
            result.success = True
            result.message = (f"{summary.total_rollouts} rollouts over {settings.num_tasks} "
                              f"tasks; held-out zero-shot success "
                              f"{100 * summary.zero_shot_success_rate:.0f} %")
            return result
        finally:
            self._busy.release()

    def _session(self, goal) -> tuple[TaskDefinition, LearnSettings, Path, str]:
        mode = goal.mode or self.mode
        if mode not in MODES:
            raise ValueError(f'unknown mode {mode!r}; known: {", ".join(MODES)}')
        if goal.strategy not in STRATEGIES:
            raise ValueError(f'unknown strategy {goal.strategy!r}; known: '
                             f'{", ".join(STRATEGIES)}')
        p = self.parameters
        if goal.num_test > p.max_tasks:
            raise ValueError(f'num_test must be at most {p.max_tasks} (the learner\'s '
                             f'max_tasks), got {goal.num_test}')
        if not 1 <= goal.num_tasks <= p.max_tasks:
            raise ValueError(f'num_tasks must be between 1 and {p.max_tasks} (the learner\'s '
                             f'max_tasks), got {goal.num_tasks}')
        budget = int(goal.max_rollouts_per_task or SearchSettings.max_rollouts)   # 0: default
        if budget > p.max_rollouts_per_task:
            raise ValueError(f'max_rollouts_per_task must be at most '
                             f'{p.max_rollouts_per_task} (0 = the default '
                             f'{SearchSettings.max_rollouts}), got {budget}')
        task = load_task(goal.task)
        settings = LearnSettings(strategy=goal.strategy, num_tasks=int(goal.num_tasks),
                                 seed=int(goal.seed),
                                 num_test=int(goal.num_test) or p.test_tasks,
                                 search=p.search(budget),
                                 task_selection=goal.task_selection or 'random',
                                 continue_from=goal.continue_from)
        out = Path(goal.output_dir or Path(p.output_root)
                   / f'{task.name}-{goal.strategy}-seed{goal.seed}')
        return task, settings, out, mode

    @staticmethod
    def _stopped(why: str, learner: Learner) -> str:
        return (f'{why} after {len(learner.done)} of {learner.settings.num_tasks} tasks; the '
                f'checkpoint in {learner.out} keeps them: send the same goal to resume')

    # -- rollouts -----------------------------------------------------------------------------
    def _rollouts(self, task: TaskDefinition, mode: str, goal_handle) -> Rollouts:
        """The session's rollouts (`make_rollouts`): batch mode in this process (built once
        per task) or graph mode through the rollout workers (stopping between two rollouts
        on a cancel)."""
        if mode == 'graph':
            return make_rollouts(mode, task, workers=self.rollout_clients,
                                 timeout=self.parameters.rollout_timeout,
                                 should_stop=lambda: goal_handle.is_cancel_requested)
        if task.path not in self._batch:
            self._batch[task.path] = make_rollouts(mode, task)
        return self._batch[task.path]


def main(args=None):
    run_node(LearnerNode, args, threads=4)    # its action waits on other callbacks


if __name__ == '__main__':
    main()
