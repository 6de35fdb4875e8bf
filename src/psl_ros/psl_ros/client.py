"""One Python client for the graph's services and actions, shared by the CLI, the learner node,
the benchmarks and the tests.

- `MemoryClient`: the skill memory's services (query, add_sample, complete, create_skill,
  save, load, info) on any node;
- `RolloutClient`: one rollout worker's ``execute_rollout`` action (with an optional goal
  change) and ``sim/reset`` service, whether its loop is connected, and live goal updates of
  the rollout that runs (``goal_update``);
- `LearnClient`: the learner's ``learn_skill`` action;
- `RosClient`: all three on a node of its own, in its own rclpy context, spun in a background
  thread (for programs that are not nodes: the CLI, benchmarks, tests); a context manager.

Calls are made from a thread that does not spin the node and wait on the future
(`psl_ros.futures.wait_for`), never with ``rclpy.spin_until_future_complete`` (which gets
slower with every call in rclpy 7.1.6); every wait has a timeout that names what did not answer.
Waits for a server poll every `DISCOVERY_POLL` s (rclpy's ``wait_for_service`` and
``wait_for_server`` sleep 0.25 s between looks, an eighth of a second lost per command on
average). `RosClient.close` ends the client's DDS participant at once, not at interpreter exit.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from psl_msgs.action import ExecuteRollout, LearnSkill
from psl_msgs.msg import GoalUpdate, RolloutEvaluation
from psl_msgs.srv import (AddSample, ClaimSkill, CompletePattern, CreateSkill,
                          EvaluateEpisode, LoadMemory, QuerySkill, ResetTask, SaveMemory)
from psl_ros import names
from psl_ros.action_server import GOAL_ANSWER_PATIENCE
from psl_ros.timeouts import GOAL_TIMEOUT, ROLLOUT_TIMEOUT, SERVICE_TIMEOUT
from psl_ros.action_client import ActionClient
from psl_ros.futures import wait_for
from psl_ros.matching import PUBLISHER, SUBSCRIPTION, MatchedEndpoints
from psl_ros.qos import SERVICES
from psl_ros.stamps import time_msg

# s without a goal response before a rollout goal is sent again: longer than a psl action
# server tries to answer (it answers within that, or drops the goal unexecuted), so a resend
# never runs a goal twice; what it recovers is a request lost before the client's writer had
# matched the server (was 2 s: a slow answer then ran a rollout twice, seen 19 evaluations for
# 18 rollouts)
RESEND_AFTER = GOAL_ANSWER_PATIENCE + 1.0
RESULT_POLL = 5.0      # s between result requests while a goal runs (an answer can be lost)
GONE_AFTER = 2.0       # s an action server may be unseen before a wait for it ends
DISCOVERY_POLL = 0.01  # s between looks while waiting for a server to be discovered

MEMORY_SERVICES = {'query': QuerySkill, 'add_sample': AddSample, 'complete': CompletePattern,
                   'create_skill': CreateSkill, 'save': SaveMemory, 'load': LoadMemory,
                   'claim': ClaimSkill, 'info': Trigger}


def _floats(values) -> list[float]:
    return [float(x) for x in np.ravel(values)]


def wait_until(ready, timeout: float, context) -> bool:
    """Call `ready` every DISCOVERY_POLL s until it is true (True), `timeout` s have passed
    or `context` (an rclpy Context) is shut down (False then)."""
    deadline = time.monotonic() + timeout
    while not ready():
        if time.monotonic() >= deadline or not context.ok():
            return False
        time.sleep(DISCOVERY_POLL)
    return True


def wait_for_server(action_client: ActionClient, timeout: float) -> bool:
    """``ActionClient.wait_for_server`` with a finer poll (`wait_until`)."""
    return wait_until(action_client.server_is_ready, timeout, action_client._node.context)


def wait_for_service(client, timeout: float) -> bool:
    """``Client.wait_for_service`` with a finer poll (`wait_until`)."""
    return wait_until(client.service_is_ready, timeout, client.context)


class Stopped(Exception):
    """A wait ended because the caller's `stop` event was set (e.g. Ctrl-C)."""


class GoalRejected(RuntimeError):
    """An action server answered a goal by rejecting it (`send_goal`)."""


class ServerWatch:
    """Whether an action server has gone: unseen for GONE_AFTER s (its process ended: Fast DDS
    drops a dead participant after its lease, 4 s with the profile scripts/env.sh sets)."""

    def __init__(self, action_client: ActionClient, what: str):
        self.action_client, self.what = action_client, what
        self._unseen_since: float | None = None

    def check(self, doing: str) -> None:
        """Raises RuntimeError when the server has gone while `doing`."""
        if self.action_client.server_is_ready():
            self._unseen_since = None
            return
        now = time.monotonic()
        self._unseen_since = self._unseen_since or now
        if now - self._unseen_since > GONE_AFTER:
            raise RuntimeError(f'the action server {self.what} has gone (its node ended?) '
                               f'{doing}')


def send_goal(action_client: ActionClient, goal, timeout: float, what: str, feedback=None,
              resend: bool = False):
    """The goal handle of an accepted goal. With `resend`, a goal without a response after
    RESEND_AFTER s (doubling) is sent again: a psl server (`psl_ros.action_server`) answers
    within GOAL_ANSWER_PATIENCE or drops the goal unexecuted, so what is resent is a goal
    lost on its way (sent before the client's request writer matched the server) or dropped;
    only a server slower than that to answer runs a goal twice — for idempotent goals only.
    The wait ends as soon as the server has gone (`ServerWatch`).

    Raises:
        TimeoutError: no server, or no answer within `timeout`; GoalRejected (a RuntimeError):
        rejected; RuntimeError: the server has gone.
    """
    deadline = time.monotonic() + timeout
    if not wait_for_server(action_client, timeout):
        raise TimeoutError(f'the action server {what} is not available (waited '
                           f'{timeout:g} s)')
    watch = ServerWatch(action_client, what)
    wait = RESEND_AFTER if resend else timeout
    while True:
        future = action_client.send_goal_async(goal, feedback_callback=feedback)
        answered = threading.Event()
        future.add_done_callback(lambda _: answered.set())
        give_up = min(time.monotonic() + wait, deadline)
        while not answered.wait(0.1) and time.monotonic() < give_up:
            watch.check('while the goal was sent')
        if answered.is_set():
            handle = future.result()
            break
        if time.monotonic() >= deadline:
            raise TimeoutError(f'no answer from {what} (goal) within {timeout:.0f} s')
        wait *= 2
    if not handle.accepted:
        raise GoalRejected(f'{what} rejected the goal (is it busy with another one?)')
    return handle


def wait_for_result(action_client: ActionClient, handle, timeout: float, what: str,
                    stop=None):
    """The result of an accepted goal. The result is asked for again every RESULT_POLL s (an
    answer can be lost like any), and the wait ends as soon as the server has gone
    (`ServerWatch`), or when `stop` (a threading.Event) is set.

    Raises:
        TimeoutError: no result within `timeout`; RuntimeError: the server has gone;
        Stopped: `stop` was set.
    """
    deadline = time.monotonic() + timeout
    answered = threading.Event()
    futures = []
    watch = ServerWatch(action_client, what)

    def ask() -> None:
        futures.append(handle.get_result_async())
        futures[-1].add_done_callback(lambda _: answered.set())
    ask()
    asked = time.monotonic()
    while True:
        done = next((f for f in futures if f.done()), None)
        if done is not None:
            return done.result().result
        now = time.monotonic()
        if now > deadline:
            raise TimeoutError(f'no answer from {what} (result) within {timeout:.0f} s')
        if stop is not None and stop.is_set():
            raise Stopped(f'{what}: stopped while waiting for the result')
        watch.check('while the goal ran')
        if now - asked > RESULT_POLL:
            ask()
            asked = now
        answered.wait(0.1)


class MemoryClient:
    """The skill memory node's services, relative to the node's namespace."""

    def __init__(self, node: Node, callback_group=None):
        self.node = node
        self.clients = {name: node.create_client(srv, names.under(names.SKILL_MEMORY, name),
                                                 callback_group=callback_group,
                                                 qos_profile=SERVICES)
                        for name, srv in MEMORY_SERVICES.items()}

    def call(self, service: str, timeout: float = SERVICE_TIMEOUT, **fields):
        """Call one service with the request fields given; returns the response (check its
        ``success``). Raises TimeoutError when the service is not there or does not answer."""
        client = self.clients[service]
        if not wait_for_service(client, timeout):
            name = self.node.resolve_service_name(client.srv_name)
            raise TimeoutError(f'the skill memory service {name} is not available (waited '
                               f'{timeout:g} s)')
        request = MEMORY_SERVICES[service].Request(**fields)
        return wait_for(client.call_async(request), timeout, client.srv_name)


class RolloutClient:
    """One rollout worker: its executor's ``execute_rollout`` and its simulator's reset, under
    ``worker`` (relative to the node's namespace; '' = the node's own)."""

    def __init__(self, node: Node, worker: str = '', callback_group=None):
        self.node, self.worker = node, worker
        self.name = names.under(worker, names.EXECUTE_ROLLOUT)
        self.rollout_client = ActionClient(node, ExecuteRollout, self.name,
                                           callback_group=callback_group)
        self.reset_client = node.create_client(ResetTask, names.under(worker, names.RESET),
                                               callback_group=callback_group,
                                               qos_profile=SERVICES)
        self.evaluate_client = node.create_client(EvaluateEpisode,
                                                  names.under(worker, names.EVALUATE),
                                                  callback_group=callback_group,
                                                  qos_profile=SERVICES)
        self._callback_group = callback_group
        self._clock = ''
        self._matched: MatchedEndpoints | None = None
        self._ready = False      # the loop was seen complete once
        self._goal_publisher = None

    @property
    def matched(self) -> MatchedEndpoints:
        """The worker's nodes' reports of what their endpoints matched (`psl_ros.matching`),
        subscribed to on first use."""
        if self._matched is None:
            self._matched = MatchedEndpoints(self.node, self.worker, self._callback_group)
        return self._matched

    def topic(self, name: str) -> str:
        """The resolved name of one of the worker's topics (an absolute name as it is)."""
        return self.node.resolve_topic_name(name if name.startswith('/')
                                            else names.under(self.worker, name))

    def unmatched(self, topic: str, subscribers: int, publishers: int = 1) -> str:
        """'' when `topic` (resolved) has `publishers` publishers that report (`matched`)
        each having matched at least `subscribers` subscriptions; else what is missing."""
        reports = self.matched.counts(PUBLISHER, topic)
        short = {node: n for node, n in reports.items() if n < subscribers}
        if len(reports) < publishers or short:
            return (f'{topic} ({len(reports)}/{publishers} publishers matched '
                    f'{subscribers} subscribers{": " if short else ""}'
                    + ', '.join(f'{node} {n}' for node, n in short.items()) + ')')
        return ''

    def clock(self) -> str:
        """The worker's executor's ``clock`` (``simulator``: psl's simulator runs its
        episodes; ``robot``: a robot's own clock), as its latched report on
        ``matched_endpoints`` states it (`psl_ros.matching`); '' while none has come."""
        if not self._clock:
            executor = self.node.resolve_topic_name(names.under(self.worker, 'dmp_executor'))
            self._clock = self.matched.fact(executor, 'clock')
        return self._clock

    def missing_endpoints(self) -> str:
        """What the worker's loop still lacks, as text ('' when complete): the action server,
        the evaluator's service, with psl's simulator its reset service, and for every topic
        of the loop its endpoints discovered and matched on both sides (each publisher has
        matched every subscriber of the loop, each subscription every publisher). On a
        robot's own clock its joint states are the robot's: only psl's subscriptions to them
        are checked (the controller is the executor's to check, each rollout)."""
        missing = []
        if not self.rollout_client.server_is_ready():
            missing.append(f'{self.node.resolve_service_name(self.name)} action server')
        clock = self.clock()
        if not clock:
            return ', '.join(missing + ['the dmp_executor\'s report of its clock'])
        simulated = clock == 'simulator'
        if simulated and not self.reset_client.service_is_ready():
            missing.append(f'{self.node.resolve_service_name(self.reset_client.srv_name)} '
                           'service')
        if not self.evaluate_client.service_is_ready():
            missing.append(f'{self.node.resolve_service_name(self.evaluate_client.srv_name)} '
                           'service')
        for name, (pubs, subs) in (names.LOOP_TOPICS if simulated
                                   else names.ROBOT_LOOP_TOPICS).items():
            if not simulated and name == names.JOINT_STATES:
                # the robot's, wherever it was remapped: its publisher reports nothing, psl's
                # subscriptions say what they matched
                readers = self.matched.counts(SUBSCRIPTION, name, as_asked=True)
                if len(readers) < subs or any(n < pubs for n in readers.values()):
                    missing.append(f'the robot\'s joint states ({len(readers)}/{subs} '
                                   f'subscriptions matched {pubs} publisher)')
                continue
            topic = self.topic(name)
            p, s = self.node.count_publishers(topic), self.node.count_subscribers(topic)
            if p < pubs or s < subs:
                missing.append(f'{topic} ({p}/{pubs} publishers, {s}/{subs} subscribers)')
                continue
            missing.append(self.unmatched(topic, subs, pubs))
            readers = self.matched.counts(SUBSCRIPTION, topic)
            if len(readers) < subs or any(n < pubs for n in readers.values()):
                missing.append(f'{topic} ({len(readers)}/{subs} subscriptions matched {pubs} '
                               'publishers)')
        return ', '.join(filter(None, missing))

    def ready(self, timeout: float) -> bool:
        """True when the action server, the services and every topic of the loop are matched
        (`missing_endpoints`; waits up to about `timeout` s)."""
        deadline = time.monotonic() + timeout

        def left() -> float:
            return max(0.0, deadline - time.monotonic())
        return (wait_for_server(self.rollout_client, timeout)
                and wait_until(lambda: not self.missing_endpoints(), left(),
                               self.node.context))

    def wait_until_ready(self, timeout: float) -> None:
        """Block until `ready`; TimeoutError naming what is missing after `timeout` s."""
        deadline = time.monotonic() + timeout
        while not self.ready(timeout=min(0.5, max(0.0, deadline - time.monotonic()))):
            if time.monotonic() >= deadline:
                where = self.node.resolve_topic_name(names.under(self.worker, 'x'))[:-2]
                raise TimeoutError(f'the rollout worker in {where or "/"} is not up within '
                                   f'{timeout:g} s: missing ' + self.missing_endpoints())
        self._ready = True

    def reset(self, task: str, tau, timeout: float = SERVICE_TIMEOUT) -> ResetTask.Response:
        if not wait_for_service(self.reset_client, timeout):
            raise TimeoutError(f'the simulator service {self.reset_client.srv_name} is not '
                               f'available (waited {timeout:g} s)')
        request = ResetTask.Request(task=task, tau=_floats(tau))
        return wait_for(self.reset_client.call_async(request), timeout,
                        self.reset_client.srv_name)

    def rollout(self, task: str, tau, theta, timeout: float = ROLLOUT_TIMEOUT,
                feedback=None, new_goal=None,
                new_goal_time: float = -1.0) -> ExecuteRollout.Result:
        """One rollout; returns the action result (success, message, evaluation). With
        `new_goal` (the DMP's space: joint angles, or the hand point of an end-effector-space
        task) the goal moves to it from `new_goal_time` s after the episode start, known
        before the start (deterministic). The first call waits until the loop is connected.
        Raises TimeoutError when the worker does not answer, RuntimeError when it rejects
        the goal."""
        if not self._ready:
            self.wait_until_ready(min(timeout, 30.0))
        goal = ExecuteRollout.Goal(task=task, tau=_floats(tau), theta=_floats(theta),
                                   new_goal=[] if new_goal is None else _floats(new_goal),
                                   new_goal_time=float(new_goal_time))
        start = time.monotonic()
        # a rollout may run twice (a late goal answer), never change the result
        handle = send_goal(self.rollout_client, goal, timeout, self.name, feedback, resend=True)
        remaining = max(1.0, timeout - (time.monotonic() - start))
        try:
            return wait_for_result(self.rollout_client, handle, remaining, self.name)
        except BaseException:          # Ctrl-C, a timeout, a server gone: the goal ends too
            handle.cancel_goal_async()
            raise

    def wait_for_subscribers(self, topics, extra: int = 1, timeout: float = 15.0,
                             subscriptions=()) -> None:
        """Wait until the graph's publisher of each topic has matched `extra` subscriptions
        more than the graph's own (`names.OWN_SUBSCRIBERS`: e.g. a recorder that just
        started, or this client's `subscriptions`), and each of `subscriptions` (rclpy
        Subscriptions of this client) has matched those publishers: from then on every
        message published reaches them. Raises TimeoutError naming what is missing."""
        deadline = time.monotonic() + timeout
        for topic in topics:
            resolved = self.topic(topic)
            want = names.OWN_SUBSCRIBERS.get(
                topic, names.OWN_SUBSCRIBERS.get(topic.lstrip('/'), 0)) + extra
            mine = [s for s in subscriptions if s.topic_name == resolved]

            def missing() -> str:
                gap = self.unmatched(resolved, want)
                publishers = len(self.matched.counts(PUBLISHER, resolved))
                short = [s for s in mine if s.get_publisher_count() < publishers]
                return gap or (f'{resolved}: a subscription of this client matched '
                               f'{short[0].get_publisher_count()} of {publishers} publishers'
                               if short else '')
            if not wait_until(lambda: not missing(), max(0.0, deadline - time.monotonic()),
                              self.node.context):
                raise TimeoutError(f'not matched within {timeout:g} s: {missing()}')

    def update_goal(self, goal, time_from_start: float, episode_ns: int = 0,
                    timeout: float = 5.0) -> None:
        """Ask the worker's executor (topic ``goal_update``, reliable) to move the goal of
        the rollout that runs (`episode_ns`: its first state's time in ns, 0 = whichever
        runs) to `goal` from `time_from_start` s on, or later if the episode has nearly
        passed that time; the rollout's result message and evaluation (``goal_change_time``)
        say what it did. Each call waits until the publisher and the executor's subscription
        have matched each other (TimeoutError after `timeout` s)."""
        if self._goal_publisher is None:
            self._goal_publisher = self.node.create_publisher(
                GoalUpdate, names.under(self.worker, names.GOAL_UPDATE), 10)
        publisher = self._goal_publisher
        topic = publisher.topic_name

        def matched() -> bool:    # both halves: ours, and the executor's (its report)
            readers = self.matched.counts(SUBSCRIPTION, topic)
            return (publisher.get_subscription_count() > 0 and bool(readers)
                    and min(readers.values()) >= self.node.count_publishers(topic))
        if not wait_until(matched, timeout, self.node.context):
            raise TimeoutError(f'no dmp_executor has matched {topic} within {timeout:g} s')
        publisher.publish(GoalUpdate(stamp=time_msg(int(episode_ns)), goal=_floats(goal),
                                     time_from_start=float(time_from_start)))


class LearnClient:
    """The learner node's ``learn_skill`` action."""

    def __init__(self, node: Node, callback_group=None):
        self.learn_client = ActionClient(node, LearnSkill, names.LEARN_SKILL,
                                         callback_group=callback_group)

    def send_goal(self, timeout: float = GOAL_TIMEOUT, feedback=None, **fields):
        """Send a goal (fields of psl_msgs/LearnSkill.Goal); returns the accepted goal handle
        (`.get_result_async()`, `.cancel_goal_async()`; `wait_for_result`). A session is not
        idempotent: the goal is sent once."""
        return send_goal(self.learn_client, LearnSkill.Goal(**fields), timeout,
                         names.LEARN_SKILL, feedback)

    def result(self, handle, timeout: float = 3600.0, stop=None) -> LearnSkill.Result:
        """`wait_for_result` of a learn_skill goal."""
        return wait_for_result(self.learn_client, handle, timeout, names.LEARN_SKILL, stop)


class RosClient:
    """A node of its own (rclpy context, background spin thread) with the graph's clients;
    service and action names relative to ``namespace``. Use as a context manager."""

    def __init__(self, namespace: str = '', name: str = 'psl_cli'):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(f'{name}_{id(self) % 100000}', namespace=namespace or '/',
                         context=self.context)
        self.memory_client = MemoryClient(self.node)
        self.worker = RolloutClient(self.node)
        self.learner = LearnClient(self.node)
        self.rollout_client, self.reset_client = (self.worker.rollout_client,
                                                  self.worker.reset_client)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        """Spin until the context ends. An entity destroyed by another thread while its
        message is being taken makes rclpy's executor raise (InvalidHandle); that must not
        end the thread, or every later call of this client waits in vain."""
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except Exception:  # noqa: BLE001 - a destroyed entity, or the context ended
                if not self.context.ok():
                    return
                time.sleep(0.001)

    def close(self) -> None:
        """Stop the spin thread, destroy the node and end the context. The action clients are
        destroyed first: each holds the node's handle, and with it the DDS participant, which
        would otherwise live on until interpreter exit."""
        self.executor.shutdown(timeout_sec=1.0)
        self.rollout_client.destroy()
        self.learner.learn_client.destroy()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(timeout=2.0)

    def __enter__(self) -> 'RosClient':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    wait = staticmethod(wait_for)     # the future's result, or TimeoutError

    def memory(self, service: str, timeout: float = SERVICE_TIMEOUT, **fields):
        """`MemoryClient.call`: one of the skill memory's services."""
        return self.memory_client.call(service, timeout, **fields)

    def rollout(self, task: str, tau, theta, timeout: float = ROLLOUT_TIMEOUT,
                feedback=None, new_goal=None,
                new_goal_time: float = -1.0) -> ExecuteRollout.Result:
        """`RolloutClient.rollout` on the rollout worker of this namespace."""
        return self.worker.rollout(task, tau, theta, timeout, feedback, new_goal,
                                   new_goal_time)

    def update_goal(self, goal, time_from_start: float, episode_ns: int = 0,
                    timeout: float = 5.0) -> None:
        """`RolloutClient.update_goal` on the rollout worker of this namespace."""
        self.worker.update_goal(goal, time_from_start, episode_ns, timeout)

    def reset(self, task: str, tau, timeout: float = SERVICE_TIMEOUT) -> ResetTask.Response:
        return self.worker.reset(task, tau, timeout)

    def graph_ready(self, timeout: float) -> bool:
        return self.worker.ready(timeout)

    def missing_endpoints(self) -> str:
        return self.worker.missing_endpoints()

    def wait_for_subscribers(self, topics, extra: int = 1, timeout: float = 15.0,
                             subscriptions=()) -> None:
        """`RolloutClient.wait_for_subscribers` on the rollout worker of this namespace."""
        self.worker.wait_for_subscribers(topics, extra, timeout, subscriptions)

    def send_learn_goal(self, timeout: float = GOAL_TIMEOUT, feedback=None, **fields):
        """`LearnClient.send_goal`."""
        return self.learner.send_goal(timeout, feedback, **fields)

    def learn(self, timeout: float = 3600.0, feedback=None, **fields) -> LearnSkill.Result:
        """One learning session through the learner node; returns its result."""
        handle = self.send_learn_goal(feedback=feedback, **fields)
        return self.learner.result(handle, timeout)


def evaluation_dict(evaluation: RolloutEvaluation) -> dict:
    """A RolloutEvaluation as plain data (JSON-able)."""
    return {
        'task': evaluation.task,
        'tau': list(evaluation.tau),
        'reward': evaluation.reward,
        'fulfilled': evaluation.fulfilled,
        'components': dict(zip(evaluation.component_names, evaluation.component_values)),
        'tracking_error': evaluation.tracking_error,
        'failure': evaluation.failure,
        'num_steps': evaluation.num_steps,
        'goal_position': [float(x) for x in evaluation.goal_position],
        'goal_change_time': (None if evaluation.goal_change_time < 0
                             else evaluation.goal_change_time),
    }
