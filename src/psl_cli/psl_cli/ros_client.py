"""A small rclpy client for the CLI and the tests: run rollouts and reset the simulator."""
from __future__ import annotations

import threading
import time

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from psl_msgs.action import ExecuteRollout, LearnSkill
from psl_msgs.msg import RolloutEvaluation
from psl_msgs.srv import (AddSample, CompletePattern, LoadMemory, QuerySkill, ResetTask,
                          SaveMemory)
from psl_sim.action_client import ActionClient
from psl_sim.futures import wait_for
from std_srvs.srv import Trigger

MEMORY_SERVICES = {'query': QuerySkill, 'add_sample': AddSample, 'complete': CompletePattern,
                   'save': SaveMemory, 'load': LoadMemory, 'info': Trigger}


class RosClient:
    """Owns an rclpy context and a node spun in a background thread; use as a context
    manager. Service and action names are relative to ``namespace``."""

    def __init__(self, namespace: str = '', name: str = 'psl_cli'):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(f'{name}_{id(self) % 100000}', namespace=namespace or '/',
                         context=self.context)
        self.rollout_client = ActionClient(self.node, ExecuteRollout, 'execute_rollout')
        self.learn_client = ActionClient(self.node, LearnSkill, 'learn_skill')
        self.reset_client = self.node.create_client(ResetTask, 'sim/reset')
        self.memory_clients = {name: self.node.create_client(srv, f'skill_memory/{name}')
                               for name, srv in MEMORY_SERVICES.items()}
        self._ready = False      # the loop was seen complete once
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - the context was shut down under us
            pass

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(timeout=2.0)

    def __enter__(self) -> 'RosClient':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # topic -> (publishers, subscribers) the robot loop needs before its first episode
    LOOP_TOPICS = {'joint_states': (1, 2), 'effort_command': (1, 1), 'reference': (1, 1),
                   'task_instance': (1, 1), 'joint_trajectory': (1, 1),
                   'rollout_evaluation': (1, 1)}

    def graph_ready(self, timeout: float) -> bool:
        """True when the executor's action server, the simulator's reset service and every
        topic of the loop have their endpoints discovered."""
        if not (self.rollout_client.wait_for_server(timeout_sec=timeout)
                and self.reset_client.wait_for_service(timeout_sec=timeout)):
            return False
        if self.missing_endpoints():
            time.sleep(timeout)
            return False
        time.sleep(0.2)   # discovery seen from here; give the pairwise matching a moment
        return True

    def missing_endpoints(self) -> str:
        """What the loop still lacks, as text ('' when complete)."""
        missing = []
        if not self.rollout_client.server_is_ready():
            missing.append('execute_rollout action server')
        if not self.reset_client.service_is_ready():
            missing.append('sim/reset service')
        for topic, (pubs, subs) in self.LOOP_TOPICS.items():
            p, s = self.node.count_publishers(topic), self.node.count_subscribers(topic)
            if p < pubs or s < subs:
                missing.append(f'{topic} ({p}/{pubs} publishers, {s}/{subs} subscribers)')
        return ', '.join(missing)

    def wait_for_subscribers(self, topics, extra: int = 1, timeout: float = 15.0) -> None:
        """Wait until each topic of the loop has `extra` more subscribers than the graph's
        own (e.g. a recorder that just started); raise TimeoutError otherwise."""
        deadline = time.monotonic() + timeout
        for topic in topics:
            want = self.LOOP_TOPICS.get(topic.lstrip('/'), (0, 0))[1] + extra
            while self.node.count_subscribers(topic) < want:
                if time.monotonic() > deadline:
                    raise TimeoutError(f'{topic} has {self.node.count_subscribers(topic)} '
                                       f'subscribers, expected {want}')
                time.sleep(0.05)
        time.sleep(0.3)   # seen from here; give the pairwise matching a moment

    wait = staticmethod(wait_for)     # the future's result, or TimeoutError

    def memory(self, service: str, timeout: float = 10.0, **fields):
        """Call one of the skill memory's services (query, add_sample, complete, save, load,
        info) with the request fields given; returns the response."""
        client = self.memory_clients[service]
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f'the skill memory service skill_memory/{service} is not '
                               'available')
        request = MEMORY_SERVICES[service].Request(**fields)
        return self.wait(client.call_async(request), timeout, f'skill_memory/{service}')

    def reset(self, task: str, tau, timeout: float = 10.0) -> ResetTask.Response:
        if not self.reset_client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError('the simulator service sim/reset is not available')
        request = ResetTask.Request(task=task, tau=[float(x) for x in tau])
        return self.wait(self.reset_client.call_async(request), timeout, 'sim/reset')

    def rollout(self, task: str, tau, theta, timeout: float = 120.0,
                feedback=None) -> ExecuteRollout.Result:
        """One rollout through the graph; returns the action result (success, message,
        evaluation). Raises TimeoutError when the executor does not answer."""
        if not self._ready:
            deadline = time.monotonic() + min(timeout, 30.0)
            while not self.graph_ready(timeout=0.5):
                if time.monotonic() > deadline:
                    raise TimeoutError('the graph is not up: ' + self.missing_endpoints())
            self._ready = True
        goal = ExecuteRollout.Goal(task=task, tau=[float(x) for x in np.ravel(tau)],
                                   theta=[float(x) for x in np.ravel(theta)])
        start = time.monotonic()
        handle = self.wait(self.rollout_client.send_goal_async(goal, feedback_callback=feedback),
                            timeout, 'execute_rollout goal')
        if not handle.accepted:
            raise RuntimeError('the rollout goal was rejected')
        remaining = max(1.0, timeout - (time.monotonic() - start))
        return self.wait(handle.get_result_async(), remaining, 'execute_rollout result').result

    def send_learn_goal(self, timeout: float = 30.0, feedback=None, **fields):
        """Send a learn_skill goal (fields of psl_msgs/LearnSkill.Goal) to the learner node;
        returns the accepted goal handle (`.get_result_async()`, `.cancel_goal_async()`)."""
        if not self.learn_client.wait_for_server(timeout_sec=timeout):
            raise TimeoutError('the learner action server learn_skill is not available '
                               '(is the graph up?)')
        handle = self.wait(self.learn_client.send_goal_async(
            LearnSkill.Goal(**fields), feedback_callback=feedback), timeout, 'learn_skill goal')
        if not handle.accepted:
            raise RuntimeError('the learn_skill goal was rejected')
        return handle

    def learn(self, timeout: float = 3600.0, feedback=None, **fields) -> LearnSkill.Result:
        """One learning session through the learner node; returns its result."""
        handle = self.send_learn_goal(feedback=feedback, **fields)
        return self.wait(handle.get_result_async(), timeout, 'learn_skill result').result


def evaluation_dict(evaluation: RolloutEvaluation) -> dict:
    return {
        'task': evaluation.task,
        'tau': list(evaluation.tau),
        'reward': evaluation.reward,
        'fulfilled': evaluation.fulfilled,
        'components': dict(zip(evaluation.component_names, evaluation.component_values)),
        'tracking_error': evaluation.tracking_error,
        'num_steps': evaluation.num_steps,
    }
