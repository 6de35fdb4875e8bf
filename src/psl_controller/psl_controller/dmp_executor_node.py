"""The DMP executor node: serves the ``execute_rollout`` action (psl_msgs/ExecuteRollout).

One rollout: check the goal, roll out the policy for theta on the control grid, check the
reference against the task's safety limits (`psl_task.safety_check`: a refused candidate is
never sent, no episode runs, the result carries the penalty and the reason in ``refused``),
then run the episode (`psl_controller.episode.Episode`: the beginning, homing if the arm is
driven, and the primitive, each one ``control_msgs/FollowJointTrajectory`` goal to the
``controller``, on the ``clock`` of the robot: `psl_controller.robot_link`), and have the
reward evaluator score it (its ``~/evaluate``). Rollouts run one at a time; a bad goal gets
``success=false`` and a message. An episode whose goal a goal that is not psl's preempted (its
controller serves someone else too) ends with ``success=false`` and the reason in
``preempted``: nothing was scored, and the session runs the candidate again. What the episode
says for people (an arm homed back inside its joint ranges, a goal change) is logged and
joins the result's message. The node adds nothing to the episode but ROS: parameters, the
action, the evaluator, the controller's gains.

The controller is checked against the rollout's task before anything moves: it must drive the
task's joints, and take effort if the task's policy learns a feed-forward (a position
interface is refused with one line naming it). psl's own controller (``pd_controller``) gets a
rollout's task's gains when they differ from the gains it runs (its parameter service,
validated there): two tasks of different gains share one running controller; a robot's own
controller keeps its gains.

Goal changes (`TaskPolicy.reference_with_new_goal`: the DMP's attractor moves smoothly to a new
goal from a switch time on): known before the start (the action goal's ``new_goal``,
``new_goal_time``): the reference is computed with the change (deterministic, as a batch
recomputation); live (psl_msgs/GoalUpdate on ``goal_update`` while a rollout runs): the running
goal is replaced from a switch step ahead of the episode (`Episode.change_goal`); an update
that comes too late, names another episode, holds a bad goal or a time outside the episode, or
whose spliced reference the safety check refuses changes nothing, and the result message says
why. Either way the evaluator scores the episode against the goal that ran.
"""
from __future__ import annotations

import threading

import numpy as np
from rclpy.action import CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter

from psl_controller.episode import Episode, Outcome, Preempted, RobotError
from psl_controller.parameters import ExecutorParameters
from psl_controller.policy import TaskPolicy, policy_for
from psl_controller.robot_link import ACK_TIMEOUT, PARAMETER_TIMEOUT, RobotLink, trajectory_msg
from psl_msgs.action import ExecuteRollout
from psl_msgs.msg import GoalUpdate, RolloutEvaluation, TaskInstance
from psl_msgs.srv import EvaluateEpisode
from psl_ros import names
from psl_ros.action_server import ActionServer
from psl_ros.futures import ask, wait_for
from psl_ros.matching import MatchReport
from psl_ros.node_main import run_node
from psl_ros.parameters import check_update, declare
from psl_ros.qos import SERVICES
from psl_ros.stamps import time_msg, to_ns
from psl_task.arm_model import ArmModel, joint_names_of
from psl_task.safety_check import SafetyCheck, Verdict
from psl_task.task import TaskDefinition, TaskError, load_task, task_id

EVALUATION_TIMEOUT = 30.0   # s for the evaluator's answer beyond the time it waits for states


class DMPExecutor(Node):

    def __init__(self):
        super().__init__('dmp_executor')
        # every update (and declaration) checked by ExecutorParameters (one place)
        self.add_on_set_parameters_callback(
            lambda params: check_update(self, ExecutorParameters, params))
        self.parameters = declare(self, ExecutorParameters)
        group = ReentrantCallbackGroup()
        # what its endpoints matched, and the clock of its episodes (read by clients)
        self.matches = MatchReport(self, {'clock': self.parameters.clock})
        self.link = RobotLink(self, self.parameters.controller, self.parameters.clock, group,
                              self.parameters.command_interface,
                              self.parameters.timeout_margin, self.matches)
        self.evaluator = self.create_client(EvaluateEpisode, names.EVALUATE,
                                            callback_group=group, qos_profile=SERVICES)
        self.matches.create_subscription(GoalUpdate, names.GOAL_UPDATE, self.on_goal_update,
                                         10, callback_group=group)
        self._rollout_lock = threading.Lock()
        self._safety_checks: dict = {}          # task path -> SafetyCheck
        self._gains: tuple | None = None        # (kp, kd) psl's controller runs; () not psl's
        self._live_lock = threading.Lock()      # guards _running, _pending
        self._running: tuple[Episode, ExecuteRollout.Goal, list[str]] | None = None
        self._pending: GoalUpdate | None = None     # a live update before the episode ran
        self._server = ActionServer(
            self, ExecuteRollout, names.EXECUTE_ROLLOUT, execute_callback=self.execute,
            goal_callback=lambda goal: GoalResponse.ACCEPT,
            cancel_callback=lambda handle: CancelResponse.ACCEPT, callback_group=group)
        self.get_logger().info(
            f'serving execute_rollout: controller {self.link.controller}, clock '
            f'{self.parameters.clock}')

    def destroy_node(self):
        self.link.destroy()
        super().destroy_node()

    def execute(self, goal_handle) -> ExecuteRollout.Result:
        with self._rollout_lock:
            result = ExecuteRollout.Result()
            try:
                result.evaluation, notes, result.refused, result.aborted = self._rollout(
                    goal_handle)
                done = ('refused by the safety check' if result.refused else
                        result.aborted if result.aborted else 'rollout done')
                result.success, result.message = True, '; '.join([done] + notes)
                goal_handle.succeed()
            except Preempted as exc:        # someone else's goal: not the candidate's doing
                result.success, result.message, result.preempted = False, str(exc), str(exc)
                self.get_logger().warning(f'rollout preempted: {exc}')
                goal_handle.abort()
            except (TaskError, ValueError, RuntimeError, TimeoutError) as exc:
                result.success, result.message = False, str(exc)
                self.get_logger().warning(f'rollout failed: {exc}')
                if goal_handle.is_cancel_requested:
                    goal_handle.canceled()
                else:
                    goal_handle.abort()
            return result

    def _rollout(self, goal_handle) -> tuple[RolloutEvaluation, list[str], str, str]:
        """(evaluation, notes, the safety check's reason or '', the controller's reason for an
        aborted episode or '')."""
        goal = goal_handle.request
        task = load_task(goal.task)
        tau, theta = np.asarray(goal.tau, dtype=float), np.asarray(goal.theta, dtype=float)
        task.validate_tau(tau)
        policy = policy_for(task)
        changes = len(goal.new_goal) > 0
        reference = (policy.reference_with_new_goal(theta, tau, goal.new_goal_time,
                                                    np.asarray(goal.new_goal))
                     if changes else policy.reference(theta, tau))
        safety = self._safety(task)
        verdict = safety.check(tau, reference.q, reference.qd, reference.u_ffwd)
        if not verdict.safe:        # never sent: no goal, no episode
            self.get_logger().info(f'candidate refused by the safety check: {verdict.reason}')
            return (penalty_evaluation(goal.task, goal.tau, task, 'safety_violation', verdict),
                    [verdict.reason], verdict.reason, '')
        joints = joint_names_of(task)
        link = self.link
        link.prepare(task_id(task), tau, joints, task.control_period)
        link.check(joints, policy.has_feedforward, task.name)
        kp = self._set_gains(task)
        reset = self.get_parameter('reset').value or task.homing.reset
        if not link.can_teleport:
            reset = 'drive'             # a robot is driven to the start posture
        arm = safety.arm
        episode = Episode(link, task, tau, policy, safety,
                          lambda q, qd, qdd: arm.inverse_dynamics(tau, q, qd, qdd), kp,
                          task_id(task), self.get_parameter('timeout_margin').value,
                          log=self.get_logger().warning,
                          cancelled=lambda: goal_handle.is_cancel_requested)
        notes = episode.notes           # what its beginning says (a homing back inside), then
        episode.begin(reset)            # the live goal changes
        if goal_handle.is_cancel_requested:
            raise RuntimeError('rollout canceled')
        with self._live_lock:
            self._running, self._pending = (episode, goal, notes), None
        try:
            outcome = episode.run(reference, reset, started=self._take_pending,
                                  change=(goal.new_goal_time, np.asarray(goal.new_goal))
                                  if changes else None,
                                  progress=lambda done: goal_handle.publish_feedback(
                                      ExecuteRollout.Feedback(progress=done)))
        finally:
            with self._live_lock:
                self._running = None
        evaluation = self._evaluate(task, outcome)
        aborted = outcome.result.error_string if outcome.aborted else ''
        return evaluation, notes + outcome.notes, '', aborted

    def _safety(self, task: TaskDefinition) -> SafetyCheck:
        if task.path not in self._safety_checks:
            self._safety_checks[task.path] = SafetyCheck(ArmModel(task))
        return self._safety_checks[task.path]

    def _evaluate(self, task: TaskDefinition, outcome: Outcome) -> RolloutEvaluation:
        """The evaluator's score of the episode (RuntimeError when it cannot give one)."""
        client = self.evaluator
        if not client.wait_for_service(timeout_sec=ACK_TIMEOUT):
            raise RuntimeError(f'the reward_evaluator service {client.srv_name} is not '
                               'available')
        link = self.link
        request = EvaluateEpisode.Request(
            episode=TaskInstance(stamp=time_msg(outcome.start_ns), task=link.task_name,
                                 tau=link.tau.tolist(), num_steps=outcome.num_steps,
                                 control_period=task.control_period),
            trajectory=trajectory_msg(link.joint_names, outcome.reference, outcome.start_ns,
                                      effort=True, at_rest=False))
        if outcome.change_time is not None:
            request.goal_change_time = float(outcome.change_time)
            request.goal_change = np.asarray(outcome.new_goal, dtype=float).tolist()
        if outcome.aborted:
            request.path_tolerance = float(task.safety.max_tracking_error)
        timeout = outcome.num_steps * task.control_period + EVALUATION_TIMEOUT
        response = wait_for(client.call_async(request), timeout, client.srv_name)
        if not response.success:
            raise RuntimeError(response.message)
        return response.evaluation

    # -- live goal changes ---------------------------------------------------------------
    def on_goal_update(self, msg: GoalUpdate) -> None:
        with self._live_lock:
            if self._running is None:
                self.get_logger().warning('goal update ignored: no rollout runs')
                return
            episode = self._running[0]
            if episode.handle is None:
                self._pending = msg         # applied once the primitive runs
                return
        self._change_live(msg)

    def _take_pending(self) -> None:
        with self._live_lock:
            pending, self._pending = self._pending, None
        if pending is not None:
            self._change_live(pending)

    def _change_live(self, msg: GoalUpdate) -> None:
        """Apply a live goal update to the running episode, or note why not in the rollout's
        result message."""
        with self._live_lock:
            if self._running is None:
                return
            episode, goal, notes = self._running
        stamp = to_ns(msg.stamp)
        start = episode.outcome.start_ns if episode.outcome is not None else None
        if stamp not in (0, start):
            notes.append(f'goal update ignored: it names the episode at {stamp} ns, the one '
                         f'that runs started at {start} ns')
            return
        try:
            note = episode.change_goal(np.asarray(goal.theta), np.asarray(msg.goal),
                                       msg.time_from_start)
        except ValueError as exc:
            note = f'goal update ignored: {exc}'
        except RobotError as exc:
            note = f'goal update failed: {exc}'
        notes.append(note)
        self.get_logger().info(note)

    # -- psl's controller's gains ---------------------------------------------------------
    def _set_gains(self, task: TaskDefinition) -> np.ndarray:
        """The task's proportional gains, after psl's controller got the task's gains
        (``controller.kp/kd``) if it ran those of another task (at first: the task it was
        started with; gains set by hand stay as long as the rollouts' tasks have its gains);
        a robot's own controller keeps its own (the task's kp stands for them)."""
        wanted = (tuple(task.controller.kp.tolist()), tuple(task.controller.kd.tolist()))
        parameters = self.link.parameters
        if self._gains is None:
            response = ask(lambda: parameters.get_parameters(['kp', 'kd', 'task']),
                           PARAMETER_TIMEOUT, f'{self.link.controller}/get_parameters')
            values = list(response.values)      # a controller without them answers fewer
            if len(values) < 3 or values[0].type == 0 or values[2].type == 0:
                self._gains = ()                # not declared: not psl's controller
            else:           # the gains of the task it was started with (or set by hand)
                start = load_task(values[2].string_value)
                self._gains = (tuple(start.controller.kp.tolist()),
                               tuple(start.controller.kd.tolist()))
        if self._gains == () or wanted == self._gains:
            return np.asarray(wanted[0])
        response = ask(lambda: parameters.set_parameters([
            Parameter('kp', value=list(wanted[0])), Parameter('kd', value=list(wanted[1]))]),
            PARAMETER_TIMEOUT, f'{self.link.controller}/set_parameters')
        refused = [r.reason for r in response.results if not r.successful]
        if refused:
            raise ValueError(f'the controller refused the gains of task {task.name!r}: '
                             f'{refused[0]}')
        self._gains = wanted
        return np.asarray(wanted[0])


def penalty_evaluation(task_id_: str, tau, task: TaskDefinition, component: str,
                       verdict: Verdict) -> RolloutEvaluation:
    """The evaluation of a candidate the safety check refused: the task's penalty minus the
    violation (`Verdict.penalty`), not fulfilled, the violation as its one component."""
    return RolloutEvaluation(task=task_id_, tau=list(tau), reward=verdict.penalty(
        task.safety.penalty), fulfilled=False, component_names=[component],
        component_values=[verdict.violation])


def main(args=None):
    run_node(DMPExecutor, args, threads=4)    # its action waits on other callbacks


if __name__ == '__main__':
    main()
