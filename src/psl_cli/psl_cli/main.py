"""``psl``: start the node graph, run rollouts, learn skills, query the memory, plot, record
bags, run the demo and benchmarks.

Bad input gets one line on stderr and a non-zero exit code (2 for a bad argument or file, 1
when the graph cannot do it), never a traceback: a refusal of psl's own (`is_refusal`: a damaged
file, a bad task) that a command does not catch itself ends in `main` the same way. Output cut
short by a closed pipe (``psl ... | head``) ends quietly with exit code 141 (128 + SIGPIPE, as
a shell reports it). Only the options of the command given are built, so a command imports
what it needs and no more.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Callable, NamedTuple

from psl_cli import options
from psl_cli.options import fail
from psl_ros.timeouts import ROLLOUT_TIMEOUT

SIGPIPE_EXIT = 128 + signal.SIGPIPE       # what a shell reports for a process ended by SIGPIPE


# -- psl up ----------------------------------------------------------------------------------
def cmd_up(args) -> int:
    from psl_ros.graph import Graph

    try:
        log_dir = None if args.log_dir is None else options.output_folder(args.log_dir)
    except ValueError as exc:
        return fail('psl up', exc, 2)
    try:                    # a task the nodes would refuse: say so before starting them
        warn_about('psl up', check_task(args.task), args.task)
    except ValueError as exc:
        return fail('psl up', exc, 2)
    if args.memory_dir is not None:
        os.environ['PSL_MEMORY_DIR'] = os.path.abspath(args.memory_dir)  # the memory node's
    if args.controller:
        given = [flag for flag, value in (('--effort-command', args.effort_command),
                                         ('--command-joints', args.command_joints),
                                         ('--state-timeout', args.state_timeout)) if value]
        if given:
            return fail('psl up', f'{", ".join(given)}: for psl\'s controller on a robot that '
                        'takes torques; with --controller the robot\'s own controller runs', 2)
    extra = {}
    if args.command_joints:
        extra['pd_controller'] = {'command_joints': '[' + ','.join(args.command_joints) + ']'}
    if args.state_timeout is not None:
        extra.setdefault('pd_controller', {})['state_timeout'] = args.state_timeout
    if args.command_interface:
        extra['dmp_executor'] = {'command_interface': args.command_interface}
    if args.robot_param:
        extra['robot'] = dict(args.robot_param)
    try:
        view_port = None if args.view is None else options.view_port(args.view)
    except ValueError as exc:
        return fail('psl up', exc, 2)
    topics = {name: topic for name, topic in (('joint_states', args.joint_states),
                                              ('effort_command', args.effort_command)) if topic}
    try:
        graph = Graph(task=args.task, mode=args.mode, namespace=args.namespace,
                      workers=args.workers, log_dir=log_dir, reset=args.reset,
                      robot=args.robot, robot_topics=topics, extra_params=extra,
                      view_port=view_port, controller=args.controller)
    except ValueError as exc:           # e.g. a controller given for psl's simulator
        return fail('psl up', exc, 2)
    if args.controller:                 # the robot's own: can it run the task?
        why = controller_misfit(args.task, args.controller, args.command_interface,
                                args.namespace)
        if why:
            return fail('psl up', why, 2)
    names = {name for name, *_ in graph.nodes_spec}
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        try:
            graph.start()
        except OSError as exc:        # a log folder that cannot be made, a missing executable
            return fail('psl up', exc, 1)
        for p in graph.processes:
            print(f'started {p.name:18s} pid {p.pid}')
        print(f'logs in {graph.log_dir}; Ctrl-C ends the graph', flush=True)
        try:
            graph.wait_ready(timeout=60, stop=stop)
            if 'skill_memory' in names and not stop.is_set():
                print(create_task_skill(args.task, graph.namespace), flush=True)
            if args.view is not None and not stop.is_set():
                print(f'view: {graph.view_url()} (the Foxglove app: Open connection, Foxglove '
                      'WebSocket; its layout: psl view --layout FILE)', flush=True)
        except (RuntimeError, TimeoutError) as exc:
            print(exc, file=sys.stderr)
            return 1
        if not stop.is_set():
            print('graph ready', flush=True)
        while not stop.wait(0.2):
            dead = graph.dead()
            fatal = [p for p in dead if not p.worker]
            if fatal:
                print(graph.describe_death(fatal[0]), file=sys.stderr)
                return 1
            for worker in sorted({p.worker for p in dead}):
                # a worker that fails fails alone: the learner sends its rollout elsewhere
                node = next(p for p in dead if p.worker == worker)
                print(f'psl up: {graph.describe_death(node)}', file=sys.stderr)
                if args.worker_death == 'restart':
                    new = graph.restart_worker(worker)
                    print(f'restarted worker {worker}: ' + ', '.join(
                        f'{p.name} pid {p.pid}' for p in new), flush=True)
                else:
                    graph.drop_worker(worker)
                    left = {p.worker for p in graph.processes} - {''}
                    print(f'dropped worker {worker}; {len(left)} left', flush=True)
                    if not left:
                        print('psl up: no rollout worker left', file=sys.stderr)
                        return 1
        return 0
    finally:
        graph.stop()
        print('graph ended', flush=True)


def check_task(task_name: str) -> list[str]:
    """Load the task, its model and its policy as the nodes will; ValueError (TaskError) with
    the cause and the fix otherwise. Returns the warnings of ``psl check`` (what runs but
    costs: gravity sag, torque saturation)."""
    from psl_controller.policy import policy_for
    from psl_optimizer.robot_check import check_robot
    from psl_task.task import load_task

    task = load_task(task_name)
    policy_for(task)
    return check_robot(task).warnings


def warn_about(command: str, warnings: list[str], task_name: str) -> None:
    """psl check's warnings, one line each on stderr, before a command starts work."""
    for warning in warnings:
        print(f'{command}: warning: {warning} (psl check --task {task_name})', file=sys.stderr)


def controller_misfit(task_name: str, controller: str, interface: str = '',
                      namespace: str = '') -> str:
    """Why a robot's own JointTrajectoryController cannot run the task ('' if it can): asked
    for its joints and command interface (its parameters; reading them moves nothing), it
    must drive the task's joints and take effort if the task's policy learns a feed-forward
    torque. A controller that does not answer is the reason."""
    from psl_controller.episode import RobotError
    from psl_controller.policy import policy_for
    from psl_controller.robot_link import ask_controller, misfit
    from psl_ros.client import RosClient
    from psl_task.arm_model import joint_names_of
    from psl_task.task import load_task
    from rclpy.parameter_client import AsyncParameterClient

    task = load_task(task_name)
    with RosClient(namespace) as client:
        try:
            info = ask_controller(AsyncParameterClient(client.node, controller), controller,
                                  interface)
        except RobotError as exc:
            return str(exc)
    return misfit(info, controller, joint_names_of(task), policy_for(task).has_feedforward,
                  task.name)


def create_task_skill(task_name: str, namespace: str = '', timeout: float = 30.0) -> str:
    """Create the task's skill in the graph's skill memory (tau ranges and default policy from
    the task; kept as it is if it exists): the memory knows no tasks. Returns its answer;
    RuntimeError if it refuses, TimeoutError if it does not answer."""
    from psl_controller.policy import policy_for
    from psl_ros.client import RosClient
    from psl_task.task import load_task

    task = load_task(task_name)
    with RosClient(namespace) as client:
        response = client.memory('create_skill', timeout=timeout, skill=task.name,
                                 tau_low=task.tau_low.tolist(), tau_high=task.tau_high.tolist(),
                                 theta_reference=policy_for(task).default_theta.tolist())
    if not response.success:
        raise RuntimeError(f'the skill memory did not create the skill of task {task.name!r}: '
                           f'{response.message}')
    return response.message


def _robot_param(text: str) -> tuple[str, str]:
    key, sep, value = text.partition(':=')
    if not sep or not key:
        raise argparse.ArgumentTypeError(f'{text!r}: give NAME:=VALUE (a standard_robot '
                                         'parameter, psl params standard_robot)')
    return key, value


def _up_options(p: argparse.ArgumentParser) -> None:
    from psl_controller.parameters import COMMAND_INTERFACES, STATE_TIMEOUT
    from psl_ros.graph import LOG_ROOT_VARIABLE, ROBOT_KINDS, ROBOTS, SIM_MODES
    from psl_ros.view_parameters import DEFAULT_PORT
    from psl_task.schema import RESETS

    options.add_task(p)
    p.add_argument('--mode', choices=SIM_MODES, default=SIM_MODES[0])
    p.add_argument('--namespace', default='')
    p.add_argument('--workers', type=options.non_negative_int, default=0,
                   help='N rollout workers (sim, controller, executor, evaluator) under '
                   '<namespace>/worker0..N-1; the learner spreads a population over them')
    p.add_argument('--reset', choices=RESETS, default='',
                   help="how each episode begins: teleport the arm to the start posture "
                   '(simulation only) or drive it there through the controller (a homing '
                   "quintic within the task's homing limits, then settled); default: the "
                   "task's homing.reset (teleport)")
    p.add_argument('--robot', choices=ROBOTS, default=ROBOTS[0],
                   help='; '.join(f'{name}: {kind.doc}' for name, kind in ROBOT_KINDS.items())
                   + ' (docs/your_robot.md)')
    p.add_argument('--controller', metavar='NODE', default='',
                   help="with --robot external: the robot's own JointTrajectoryController, "
                   'the node that serves NODE/follow_joint_trajectory (e.g. '
                   '/fr3_arm_controller); psl then starts neither simulator nor controller')
    p.add_argument('--command-interface', choices=COMMAND_INTERFACES, default='',
                   help="the controller's command interface, if its parameters do not say "
                   '(command_interfaces); a position interface runs kinematic tasks only')
    p.add_argument('--joint-states', metavar='TOPIC', default='',
                   help="the robot's JointState topic (e.g. /joint_states); default: "
                   'joint_states in the namespace')
    p.add_argument('--effort-command', metavar='TOPIC', default='',
                   help="a robot that takes torques only: its Float64MultiArray torque topic "
                   "(e.g. /effort_controller/commands), which psl's pd_controller commands; "
                   'default: effort_command in the namespace')
    p.add_argument('--command-joints', nargs='+', metavar='JOINT',
                   help="the joint order of the robot's torque command (its "
                   "forward_command_controller's joints); default: the task's order")
    p.add_argument('--state-timeout', type=options.positive_float, metavar='S',
                   help="psl's controller stops commanding (zero torque) when no joint state "
                   f'came for S seconds; default on a robot: {STATE_TIMEOUT:g}')
    p.add_argument('--robot-param', type=_robot_param, action='append', metavar='NAME:=VALUE',
                   help='a parameter of the standard robot (--robot standard), e.g. '
                   'position_noise:=0.001, latency_periods:=1, '
                   "model_error:='mass_scale=1.3,frictionloss=0.05,damping=0.3'")
    p.add_argument('--worker-death', choices=('restart', 'drop'), default='restart',
                   help='with --workers N > 1, when a node of one worker dies: restart that '
                   "worker's nodes (default) or go on without it; the learner re-sends its "
                   'unanswered rollout to another worker either way')
    p.add_argument('--log-dir', metavar='DIR',
                   help="folder for the nodes' output, one <node>.log each (default: a new "
                   f'folder named by the start time under ${LOG_ROOT_VARIABLE}, or when that is '
                   'unset under ./log/graph in the current working directory)')
    p.add_argument('--view', nargs='?', type=options.port, const=options.THE_DEFAULT_PORT,
                   metavar='PORT',
                   help='also start the view node: the graph live in the Foxglove app, a '
                   f'WebSocket server on ws://127.0.0.1:PORT (default ${options.VIEW_PORT_VARIABLE}'
                   f', else {DEFAULT_PORT}); psl view --layout writes its layout')
    p.add_argument('--memory-dir', metavar='DIR',
                   help="the skill memory's folder: psl memory save/load, checkpoints of "
                   'graph-mode sessions and autosave stay inside it (default: $PSL_MEMORY_DIR, '
                   'or the current working directory)')


# -- psl rollout -----------------------------------------------------------------------------
def format_evaluation(ev: dict) -> str:
    lines = [f"reward {ev['reward']:.4f}  fulfilled {ev['fulfilled']}  "
             f"steps {ev['num_steps']}  tracking error {ev['tracking_error']:.4f} rad"]
    goal = ' '.join(f'{x:.4f}' for x in ev['goal_position'])
    changed = ev['goal_change_time']
    lines.append(f'  goal at [{goal}] m' + ('' if changed is None
                                            else f', changed at {changed:g} s'))
    if ev.get('failure'):
        lines.append(f"  failed: {ev['failure']}")
    lines += [f'  {name:15s} {value:.6g}' for name, value in ev['components'].items()]
    return '\n'.join(lines)


def cmd_rollout(args) -> int:
    from psl_cli.vectors import load_vector
    from psl_controller.policy import policy_for
    from psl_ros.client import RosClient, evaluation_dict
    from psl_task.task import load_task, task_id

    try:
        task = load_task(args.task)
        tau = task.tau_default if args.tau is None else task.validate_tau(args.tau)
        theta = (policy_for(task).default_theta if args.theta_file is None
                 else load_vector(args.theta_file))
        if (args.new_goal is None) != (args.new_goal_at is None):
            raise ValueError('--new-goal and --new-goal-at go together')
        if args.new_goal is not None:      # refused here as the executor would refuse it
            policy_for(task).reference_with_new_goal(theta, tau, args.new_goal_at,
                                                     args.new_goal)
    except ValueError as exc:          # TaskError too
        return fail('psl rollout', exc, 2)
    with RosClient(args.namespace) as client:
        try:
            # by name, or by absolute path: the graph's processes have their own working dir
            result = client.rollout(task_id(task), tau, theta, timeout=args.timeout,
                                    new_goal=args.new_goal,
                                    new_goal_time=(-1.0 if args.new_goal_at is None
                                                   else args.new_goal_at))
        except (TimeoutError, RuntimeError) as exc:
            return fail('psl rollout', exc, 1)
    if not result.success:
        return fail('psl rollout', result.message, 1)
    if result.message != 'rollout done':        # what the episode says: on stderr, one line
        print(f'psl rollout: {result.message}', file=sys.stderr)
    ev = evaluation_dict(result.evaluation)
    print(json.dumps(ev) if args.json else format_evaluation(ev))
    return 0


def _rollout_options(p: argparse.ArgumentParser) -> None:
    options.add_task(p)
    options.add_tau(p)
    options.add_theta_file(p)
    p.add_argument('--new-goal-at', type=float, metavar='T',
                   help='with --new-goal: the goal starts moving T s after the episode start '
                   '(the first control period at or after T)')
    p.add_argument('--new-goal', type=float, nargs='+', metavar='V',
                   help="the DMP's new goal: one joint angle [rad] per joint, or the hand "
                   'point x y z [m] of an end-effector-space task; the evaluation scores '
                   'against it')
    options.add_graph(p, timeout=ROLLOUT_TIMEOUT, waits_for='the rollout worker and its result')
    p.add_argument('--json', action='store_true', help='the evaluation as JSON')


# -- psl query, psl memory -------------------------------------------------------------------
def _floats(values) -> list[float]:
    return [float(v) for v in values]


def cmd_memory(args) -> int:
    """psl query / psl memory add|complete|save|load|info: one call to the skill memory."""
    action = 'query' if args.command == 'query' else args.action
    command = 'psl query' if action == 'query' else f'psl memory {action}'
    if action == 'query':
        service, fields = 'query', {'skill': args.skill, 'tau': _floats(args.tau)}
    elif action == 'add':
        if (args.theta is None) == (args.theta_file is None):
            return fail(command, 'give --theta or --theta-file', 2)
        try:
            if args.theta is not None:
                theta = args.theta
            else:
                from psl_cli.vectors import load_vector
                theta = load_vector(args.theta_file)
        except ValueError as exc:
            return fail(command, exc, 2)
        service, fields = 'add_sample', {'skill': args.skill, 'tau': _floats(args.tau),
                                         'theta': _floats(theta)}
    elif action == 'complete':
        if set(args.known) - {'0', '1'}:
            return fail(command, '--known is a string of 0 and 1, one per entry', 2)
        service, fields = 'complete', {'skill': args.skill, 'pattern': _floats(args.pattern),
                                       'known': [c == '1' for c in args.known]}
    elif action in ('save', 'load'):
        # as given: the memory node resolves a name or relative path inside its memory folder
        # (and says why it refuses one: outside it, a directory, a link, ...)
        service, fields = action, {'path': args.path}
        if action == 'load':
            fields['replace'] = args.replace
    else:
        service, fields = 'info', {}
    from psl_ros.client import RosClient

    with RosClient(args.namespace) as client:
        try:
            response = client.memory(service, timeout=args.timeout, **fields)
        except TimeoutError as exc:
            return fail(command, exc, 1)
    if not response.success:
        return fail(command, response.message, 1)
    result = {'message': response.message}
    for key in ('theta', 'variance', 'pattern', 'num_samples'):
        if hasattr(response, key):
            value = getattr(response, key)
            result[key] = value if isinstance(value, int) else list(value)
    if service == 'info':
        result = json.loads(response.message)
    if args.json:
        print(json.dumps(result))
    else:
        for key, value in result.items():
            print(f'{key}: {value}')
    return 0


def _memory_call_options(p: argparse.ArgumentParser) -> None:
    """The options every call of the skill memory has."""
    options.add_graph(p, timeout=10.0, waits_for="the skill memory's answer")
    p.add_argument('--json', action='store_true', help='the answer as JSON')


def _query_options(p: argparse.ArgumentParser) -> None:
    _memory_call_options(p)
    p.add_argument('--skill', required=True)
    options.add_tau(p, required=True)


def _memory_options(p: argparse.ArgumentParser) -> None:
    actions = p.add_subparsers(dest='action', required=True)

    def action(name: str, help: str) -> argparse.ArgumentParser:
        parser = actions.add_parser(name, help=help, description=help)
        _memory_call_options(parser)
        return parser
    add = action('add', 'add one sample (tau, theta)')
    add.add_argument('--skill', required=True)
    options.add_tau(add, required=True)
    add.add_argument('--theta', type=float, nargs='+', help='theta (or --theta-file)')
    options.add_theta_file(add, default='')
    complete = action('complete', 'complete [tau, theta] with the known entries clamped')
    complete.add_argument('--skill', required=True)
    complete.add_argument('--pattern', type=float, nargs='+', required=True)
    complete.add_argument('--known', required=True, help="e.g. 11000: one 0/1 per entry")
    path_help = ("the memory file (.npz): a name or a path inside the memory node's memory "
                 'folder (its memory_dir)')
    action('save', 'save the whole memory').add_argument('path', help=path_help)
    load = action('load', "add a memory file's skills to the memory (the others are kept)")
    load.add_argument('path', help=path_help)
    load.add_argument('--replace', action='store_true',
                      help="the file's skills replace those of the same name (else a name the "
                           'memory holds already is refused); a skill a learning session has '
                           'claimed is refused either way')
    action('info', 'the skills and their sample counts')


# -- psl learn -------------------------------------------------------------------------------
def cmd_learn(args) -> int:
    """psl learn: one learning session, resumable from its output folder. Where it runs
    (--learner: this process, or the running graph's learner node) and how its rollouts run
    (--mode: batch, graph) are two choices (psl_optimizer.rollout_modes)."""
    from psl_cli.progress import LearnProgress
    from psl_task.task import load_task

    try:
        task = load_task(args.task)
        warn_about('psl learn', check_task(args.task), args.task)
        _check_skill_map(args)
        _check_here_only(args)
        map_part = '' if args.skill_map == 'elm' else f'-{args.skill_map}'
        out = options.output_folder(args.out or f'runs/{task.name}-{args.strategy}{map_part}'
                                    f'-seed{args.seed}')
        _check_session_folder(args, out)
    except ValueError as exc:          # TaskError too
        return fail('psl learn', exc, 2)
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    progress = LearnProgress(args.tasks, bar=False if args.verbose else None)
    try:
        learn = _learn_in_graph if _learner(args) == 'node' else _learn_in_process
        return learn(args, task, out, stop, progress)
    finally:
        progress.close()
        signal.signal(signal.SIGINT, previous)


def _check_session_folder(args, out: Path) -> None:
    """ValueError (one line naming the folder and --out) when `out` holds a finished session
    of at least --tasks tasks (a run would do nothing), is the folder of the
    --continue-from memory (the session would write over the skill it continues), or holds a
    metrics.json that is no file. A folder of another session's checkpoint, or of a damaged
    one, is refused by the learner (`SessionFolderError`)."""
    from psl_optimizer.metrics import read_metrics

    if args.continue_from and Path(args.continue_from).expanduser().resolve().parent == out:
        raise ValueError(f'--continue-from {args.continue_from} lies in the session folder '
                         f'{out}: the session would write over the skill it continues; give '
                         'another --out')
    metrics_file = out / 'metrics.json'
    if os.path.lexists(metrics_file) and not metrics_file.is_file():
        raise ValueError(f'{metrics_file} is not a file: the session could not write its '
                         'metrics there; remove it or give another --out')
    if metrics_file.is_file():
        try:
            metrics = read_metrics(out)
        except (OSError, ValueError, KeyError):
            return                  # not a session's metrics: the learner says what it is
        if metrics.complete and len(metrics.tasks) >= args.tasks:
            raise ValueError(f'{out} holds a finished session ({len(metrics.tasks)} tasks, '
                             f'its metrics.json): give another --out (or psl plot {out})')


def _learner(args) -> str:
    """Where the session runs: --learner, by default the node for graph mode (the rollout
    workers' graph has a learner) and this process for batch mode."""
    return args.learner or ('node' if args.mode == 'graph' else 'here')


# psl learn options of a session in this process only (the LearnSkill goal has no fields for
# them): option -> its default
HERE_ONLY = {'model_error': '', 'continuation': None, 'measurement_noise': '',
             'confirm': (1, 1)}


def _check_here_only(args) -> None:
    """ValueError when a session of the learner node is given an option of HERE_ONLY."""
    given = [name for name, default in HERE_ONLY.items() if getattr(args, name) != default]
    if given and _learner(args) == 'node':
        raise ValueError(f'--{given[0].replace("_", "-")}: a session in this process only '
                         '(--learner here); the learner node continues the residual way, on the '
                         "graph's robot")
    if (args.model_error or args.measurement_noise) and args.mode != 'batch':
        raise ValueError('--model-error and --measurement-noise are batch mode\'s: in graph '
                         'mode the robot is what it is (psl up --robot standard '
                         '--robot-param ...)')


def _check_skill_map(args) -> None:
    """--skill-map: elm, or a known baseline in a session in this process (ValueError
    otherwise), checked before the output folder is made."""
    if args.skill_map == 'elm':
        return
    if _learner(args) == 'node':
        raise ValueError(f'--skill-map {args.skill_map}: the learner node learns with the '
                         'skill memory (elm) only; the baselines run in this process '
                         '(--learner here)')
    from psl_optimizer.learning import SKILL_MAPS
    if args.skill_map not in SKILL_MAPS:
        raise ValueError(f'unknown skill map {args.skill_map!r}; known: {", ".join(SKILL_MAPS)}')


def _print_summary(args, metrics, out: Path) -> None:
    if metrics.preempted:
        print(f"psl learn: {metrics.preempted} episodes were preempted by goals that are not "
              "psl's (someone else commands the robot's controller); each rollout ran again",
              file=sys.stderr)
    s = metrics.summary
    if s is not None:
        print(f"{s.total_rollouts} rollouts over {args.tasks} tasks; held-out zero-shot "
              f"success {100 * s.zero_shot_success_rate:.0f} % (mean reward "
              f"{s.zero_shot_mean_reward:.3f}); metrics in {out / 'metrics.json'}")
        if s.tracking_rmse_mean is not None:       # a task with feed-forward
            m = s.tracking_rmse_mean
            print(f"held-out tracking RMSE: PD only {m['pd_only']:.4f}, learned "
                  f"{m['learned']:.4f}, oracle {m['oracle']:.4f} rad")


def _learn_in_process(args, task, out: Path, stop: threading.Event, progress) -> int:
    """The session in this process; graph mode's rollouts through the running graph's
    rollout workers (--workers N: worker0..N-1, else its own loop)."""
    if args.mode == 'batch' and args.task_selection != 'given':
        return _learn_here(args, task, out, stop, progress, workers=None)
    from psl_ros.client import RolloutClient, RosClient
    from psl_ros.instance_source import TopicInstances

    with RosClient(args.namespace) as client:
        names = [f'worker{k}' for k in range(args.workers)] or ['']
        workers = None if args.mode == 'batch' else [RolloutClient(client.node, name)
                                                     for name in names]
        try:
            instances = None if args.task_selection != 'given' else TopicInstances(
                client.node, args.tau_topic, task.validate_tau, args.tau_timeout, stop.is_set)
        except ValueError as exc:
            progress.close()
            return fail('psl learn', exc, 2)
        return _learn_here(args, task, out, stop, progress, workers=workers,
                           instances=instances, node=client.node)


def _learn_here(args, task, out: Path, stop: threading.Event, progress, workers,
                instances=None, node=None) -> int:
    """The session in this process; with the graph's `node` (graph mode, instances from a
    topic) it publishes its learning curve on the graph as the learner node does."""
    from psl_optimizer.learning import Learner, LearnSettings, SessionFolderError
    from psl_optimizer.policy_search import SearchSettings
    from psl_optimizer.rollout_modes import make_rollouts
    from psl_optimizer.rollouts import Stopped
    from psl_ros.instance_source import InstanceStopped

    try:
        # --budget 0 is the default budget, as max_rollouts_per_task = 0 in a learn_skill goal
        settings = LearnSettings(strategy=args.strategy, num_tasks=args.tasks, seed=args.seed,
                                 num_test=args.test_tasks, task_selection=args.task_selection,
                                 search=SearchSettings(max_rollouts=args.budget
                                                       or SearchSettings.max_rollouts),
                                 continue_from=args.continue_from or '',
                                 skill_map=args.skill_map, model_error=args.model_error,
                                 continuation=args.continuation or '',
                                 measurement_noise=args.measurement_noise,
                                 confirm=args.confirm)
        rollouts = make_rollouts(args.mode, task, workers=workers, should_stop=stop.is_set,
                                 model_error=args.model_error,
                                 measurement_noise=args.measurement_noise)
        if node is None:
            learner = Learner(task, settings, out, rollouts, instances=instances)
        else:           # with the graph: the session the learner node runs, here
            from psl_optimizer.progress_topic import graph_session
            learner = graph_session(task, settings, out, rollouts, node, instances=instances)

        def finished(record) -> None:
            progress.finished(record.index, record.best_reward, record.fulfilled,
                              in_all=sum(done.rollouts for done in learner.done),
                              rollouts=record.rollouts)
            if record.failed:
                print(f'psl learn: warning: task {record.index + 1}: {record.failed} rollouts '
                      f'not scored ({record.failure}); each got the penalty', file=sys.stderr)
        metrics = learner.run(progress=finished, should_stop=stop.is_set)
    except SessionFolderError as exc:
        progress.close()
        return fail('psl learn', f'{exc} (--out)', 2)
    except (ValueError, OSError) as exc:       # OSError: a session file it cannot write
        progress.close()
        return fail('psl learn', exc, 2)
    except (Stopped, InstanceStopped):   # Ctrl-C between two rollouts, or while waiting
        progress.close()
        return fail('psl learn', f'stopped after {len(learner.done)} of {args.tasks} tasks; '
                    f'the same command resumes from {out}', 130)
    except (TimeoutError, RuntimeError) as exc:     # graph mode: no graph, a worker gone
        progress.close()
        return fail('psl learn', exc, 1)
    progress.close(complete=metrics.complete)
    if not metrics.complete:
        return fail('psl learn', f'stopped after {len(metrics.tasks)} of {args.tasks} tasks; '
                    f'the same command resumes from {out}', 130)
    _print_summary(args, metrics, out)
    return _outcome(metrics, out)


def _outcome(metrics, out: Path) -> int:
    """A finished session's exit status: 0, or 1 with the reason when the reward could score
    none of its rollouts (`psl_optimizer.learning.nothing_scored`)."""
    from psl_optimizer.learning import nothing_scored

    reason = nothing_scored(metrics.tasks)
    if reason:
        return fail('psl learn', f"{reason} (metrics in {out / 'metrics.json'})", 1)
    return 0


CANCEL_WAIT = 30.0     # s psl learn waits, after Ctrl-C, for the learner to say what it kept


def _learn_in_graph(args, task, out: Path, stop: threading.Event, progress) -> int:
    from psl_optimizer.metrics import read_metrics
    from psl_ros.client import RosClient, Stopped
    from psl_task.task import task_id

    def feedback(message) -> None:
        fb = message.feedback
        progress.batch(fb.task_index, fb.rollouts, fb.best_reward, fb.fulfilled)

    with RosClient(args.namespace) as client:
        try:
            handle = client.send_learn_goal(
                timeout=args.timeout, feedback=feedback, task=task_id(task),
                strategy=args.strategy, num_tasks=args.tasks,
                max_rollouts_per_task=args.budget, seed=args.seed, mode=args.mode,
                output_dir=str(out), task_selection=args.task_selection,
                num_test=args.test_tasks, continue_from=args.continue_from or '')
            try:
                result = client.learner.result(handle, stop=stop)
            except Stopped:
                progress.close()
                print('psl learn: cancelling (finished tasks stay in the checkpoint; Ctrl-C '
                      'again ends at once)', file=sys.stderr, flush=True)
                stop.clear()
                handle.cancel_goal_async()
                try:       # the learner stops between two rollouts and says what it kept
                    result = client.learner.result(handle, timeout=CANCEL_WAIT, stop=stop)
                except Stopped:
                    return fail('psl learn', "ended without the learner's answer", 130)
        except (TimeoutError, RuntimeError) as exc:
            progress.close()
            return fail('psl learn', exc, 1)
    progress.close(complete=result.success)
    if not result.success:
        return fail('psl learn', result.message, 1)
    metrics = read_metrics(Path(result.metrics_path).parent)
    _print_summary(args, metrics, out)
    return _outcome(metrics, out)


def _learn_options(p: argparse.ArgumentParser) -> None:
    from psl_optimizer.policy_search import STRATEGIES, SearchSettings
    from psl_optimizer.rollouts import MODES
    from psl_optimizer.task_selection import TASK_SELECTIONS

    options.add_task(p)
    p.add_argument('--strategy', choices=STRATEGIES, default='bootstrap')
    p.add_argument('--tasks', type=options.positive_int, default=30,
                   help='training task instances (default 30)')
    p.add_argument('--budget', type=options.non_negative_int, default=0,
                   help='rollouts per task at most; 0 (the default) is the learner\'s '
                   f'default budget, {SearchSettings.max_rollouts}')
    p.add_argument('--seed', type=options.seed, default=0)
    p.add_argument('--test-tasks', type=options.positive_int, default=20,
                   help='held-out instances tested zero-shot at the end (default 20)')
    options.add_out(p, 'output folder (default runs/TASK-STRATEGY[-MAP]-seedK); the same '
                    'folder resumes the session')
    p.add_argument('--mode', choices=MODES, default=MODES[0],
                   help='how the rollouts run: batch, with mujoco.rollout in the process of '
                   "the session (fast); graph, through the running graph's rollout workers "
                   '(execute_rollout)')
    p.add_argument('--learner', choices=('here', 'node'), default=None,
                   help='where the session runs: here (this process) or node (the running '
                   "graph's learner node); default: node with --mode graph, here with batch")
    p.add_argument('--workers', type=options.non_negative_int, default=0,
                   help='--learner here --mode graph: the graph runs N rollout workers '
                   '(psl up --workers N); 0 (default): its own loop')
    p.add_argument('--task-selection', choices=TASK_SELECTIONS, default=TASK_SELECTIONS[0],
                   help='next instance: random, the most uncertain of 20 candidates '
                   "(the skill's predictive variance), or given: each from --tau-topic (the "
                   'environment decides: perception, an operator)')
    p.add_argument('--tau-topic', default='task_instance_request', metavar='TOPIC',
                   help='--task-selection given: the instances, std_msgs/Float64MultiArray '
                   '(data = tau), one per message, in order; a bad one is skipped (the learner '
                   "node: its tau_topic parameter)")
    p.add_argument('--tau-timeout', type=options.positive_float, default=600.0, metavar='S',
                   help='--task-selection given: seconds to wait for the next instance')
    p.add_argument('--skill-map', default='elm', metavar='MAP',
                   help='the skill slot (batch mode): elm, the skill memory (default), or a '
                   'baseline in its place: library (k nearest solved instances, '
                   'inverse-distance weighted) or gp (Gaussian-process regression)')
    p.add_argument('--continue-from', metavar='FILE',
                   help='start from the skill this memory file holds instead of an empty one '
                   "(graph mode: a file of the memory node's memory folder); a resumed session "
                   'starts from its checkpoint')
    p.add_argument('--continuation', choices=('residual', 'samples'),
                   help="how --continue-from's skill is continued: residual (the default, and the "
                   "learner node's only way: the robot's correction learned on top of it) or "
                   "samples (the new solutions added to its samples)")
    p.add_argument('--model-error', default='', metavar='KEY=VALUE,...',
                   help="batch mode: the robot differs from the task's model (sim to real): "
                   'mass_scale=S,frictionloss=N_M,damping=N_M_S_PER_RAD (any subset)')
    p.add_argument('--measurement-noise', default='', metavar='KEY=VALUE,...',
                   help='batch mode: a noisy robot: position=RAD,velocity=RAD_S[,seed=N] '
                   '(Gaussian std on the measured joint angles and velocities)')
    p.add_argument('--confirm', type=options.k_of_n, default=(1, 1), metavar='K/N',
                   help='a success enters the skill only if K of N rollouts of its theta '
                   'fulfil the instance (the extra rollouts count; 1/1: off)')
    options.add_graph(p, timeout=30.0,
                      waits_for='the learner node to take the goal (graph mode)')
    p.add_argument('--verbose', action='store_true',
                   help='one line per finished task also on a terminal (instead of the bar; '
                   'always so when stderr is not a terminal)')


# -- psl plot, record, demo, render, bench ---------------------------------------------------
def cmd_plot(args) -> int:
    """psl plot DIR...: rollouts per task, reward over tau, predictive variance over tau; for a
    task with feed-forward also commanded vs executed joints and the torques (PD only,
    learned, oracle) on a held-out instance."""
    from psl_bench.plot_dynamics import plot_dynamics
    from psl_bench.plot_learning import plot_runs
    from psl_optimizer.metrics import read_metrics

    try:
        out = (options.output_file(args.out) if args.out
               else Path(args.dirs[0]) / 'learning.png')
        print(plot_runs(args.dirs, out))
        summary = read_metrics(args.dirs[0]).summary
        if summary is not None and summary.tracking_rmse is not None:   # with feed-forward
            print(plot_dynamics(args.dirs[0], out.with_name(out.stem + '_dynamics.png')))
    except (ValueError, OSError) as exc:
        return fail('psl plot', exc, 2)
    return 0


def _plot_options(p: argparse.ArgumentParser) -> None:
    p.add_argument('dirs', nargs='+', metavar='DIR', help='run folders; several seeds of a '
                   'strategy are drawn as mean and min-max band')
    options.add_out(p, 'PNG file (default: DIR/learning.png of the first DIR)')


def cmd_record(args) -> int:
    from psl_ros.bag_recorder import record

    # Ctrl-C and SIGTERM end the recording normally (the bag is complete); set explicitly:
    # a recorder started in the background by a script inherits SIGINT ignored
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        recording = record(args.output, args.topics, duration=args.duration, stop=stop)
    except (ValueError, OSError) as exc:      # FileExistsError too
        return fail('psl record', exc, 2)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    for topic, count in recording.counts.items():
        lost = recording.lost[topic]
        print(f'{topic:30s} {count}' + (f'  ({lost} lost)' if lost else ''))
    return 0


def _record_options(p: argparse.ArgumentParser) -> None:
    p.add_argument('-o', '--output', required=True, help='the bag folder to create')
    p.add_argument('--duration', type=options.positive_float, default=None,
                   help='seconds (default: until Ctrl-C)')
    p.add_argument('topics', nargs='*', help='topics (default: all)')


def cmd_demo(args) -> int:
    from psl_cli.demo import run_demo

    try:
        out = options.output_folder(args.out)
    except ValueError as exc:
        return fail('psl demo', exc, 2)
    return run_demo(task=args.task, out=out, positions=args.positions)


def _demo_options(p: argparse.ArgumentParser) -> None:
    options.add_task(p)
    options.add_out(p, 'folder for the bag and the learned skill (default demo)',
                    default='demo')
    p.add_argument('--positions', type=options.positive_int, default=5,
                   help='task instances rolled out before and after learning')


def cmd_check(args) -> int:
    from psl_optimizer.robot_check import check_robot, format_report
    from psl_task.task import load_task

    try:
        task = load_task(args.task)
        report = check_robot(task)
        components = reward_component_lines(task)
    except ValueError as exc:                 # TaskError: the cause and the fix
        return fail('psl check', exc, 2)
    print(format_report(report))
    print('\n'.join(components))
    if args.controller:
        why = controller_misfit(args.task, args.controller, args.command_interface,
                                args.namespace)
        if why:
            return fail('psl check', why, 1)
        print(f'controller {args.controller}: runs task {args.task!r}')
    return 1 if report.warnings and args.strict else 0


def reward_component_lines(task) -> list[str]:
    """psl check's list of the registered reward components (name, function, package), the
    task's weight beside those it uses; each of those imported (ValueError if it cannot be)."""
    from psl_task import reward_components

    weights = task.reward.weights
    for name in weights:
        reward_components.load(name)
    lines = [f'reward components (entry points {reward_components.GROUP}; weighted by this '
             'task: *):']
    for name, where in reward_components.registered().items():
        mark = f'* {weights[name]:<8g}' if name in weights else '  ' + ' ' * 8
        lines.append(f'  {mark} {name:18s} {where.target} ({where.package})')
    return lines


def _check_options(p: argparse.ArgumentParser) -> None:
    from psl_controller.parameters import COMMAND_INTERFACES

    options.add_task(p)
    p.add_argument('--strict', action='store_true', help='exit 1 when there are warnings')
    p.add_argument('--controller', metavar='NODE', default='',
                   help="also ask a running robot's JointTrajectoryController (its parameters "
                   'joints and command_interfaces) whether it can run the task')
    p.add_argument('--command-interface', choices=COMMAND_INTERFACES, default='',
                   help="the controller's command interface, if its parameters do not say")
    p.add_argument('--namespace', default='', help='the namespace to ask from')


def cmd_params(args) -> int:
    from psl_cli.node_parameters import node_parameters, parameter_file

    nodes = node_parameters()
    if args.node not in nodes:
        return fail('psl params', ValueError(f'no node {args.node!r}; nodes: '
                                             f'{", ".join(nodes)}'), 2)
    sys.stdout.write(parameter_file(args.node))
    return 0


def _params_options(p: argparse.ArgumentParser) -> None:
    p.add_argument('node', help='sim | pd_controller | dmp_executor | skill_memory | learner')


def cmd_render(args) -> int:
    from psl_cli import render

    return render.run(args)


def _render_options(p: argparse.ArgumentParser) -> None:
    from psl_cli import render

    render.add_arguments(p)


def cmd_teach(args) -> int:
    from psl_cli import teach

    return teach.run(args)


def _teach_options(p: argparse.ArgumentParser) -> None:
    from psl_cli import teach

    teach.add_arguments(p)


def cmd_init(args) -> int:
    from psl_cli import init

    return init.run(args)


def _init_options(p: argparse.ArgumentParser) -> None:
    from psl_cli import init

    init.add_arguments(p)


def cmd_view(args) -> int:
    from psl_cli import view

    return view.run(args)


def _view_options(p: argparse.ArgumentParser) -> None:
    from psl_cli import view

    view.add_arguments(p)


def cmd_bench(args) -> int:
    from psl_cli import bench_commands

    return bench_commands.run(args)


def _bench_options(p: argparse.ArgumentParser) -> None:
    from psl_cli import bench_commands

    bench_commands.add_arguments(p)


# -- psl run ---------------------------------------------------------------------------------
def _run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument('package', help='a package of the workspace, e.g. psl_sim')
    p.add_argument('executable', help='one of its executables, e.g. sim')
    p.add_argument('arguments', nargs=argparse.REMAINDER,
                   help='its arguments, e.g. --ros-args -r __ns:=/worker1 -p task:=T')


def cmd_run(args) -> int:
    """psl run PACKAGE EXECUTABLE [ARGS]: what ``ros2 run`` does (the ros2 command line is not
    installed with the wheels): the executable under ``<prefix>/lib/<package>/``, found in
    the ament index of this environment, run in this process's place."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        folder = Path(get_package_prefix(args.package)) / 'lib' / args.package
    except (PackageNotFoundError, ValueError):
        return fail('psl run', f'no package {args.package!r} in this environment (psl\'s: '
                    f'{", ".join(_workspace_packages())})', 2)
    executables = sorted(p.name for p in folder.glob('*') if p.is_file()
                         and os.access(p, os.X_OK)) if folder.is_dir() else []
    if args.executable not in executables:
        return fail('psl run', f'package {args.package!r} has no executable '
                    f'{args.executable!r} (it has: {", ".join(executables) or "none"})', 2)
    path = folder / args.executable
    sys.stdout.flush()
    os.execv(str(path), [str(path), *args.arguments])


def _workspace_packages() -> list[str]:
    """The packages of psl's workspace that have executables."""
    from ament_index_python.packages import get_packages_with_prefixes

    return sorted(name for name, prefix in get_packages_with_prefixes().items()
                  if name.startswith('psl_') and (Path(prefix) / 'lib' / name).is_dir())


# -- the parser ------------------------------------------------------------------------------
class Command(NamedTuple):
    help: str
    add_options: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


COMMANDS = {
    'up': Command('start the node graph; Ctrl-C ends it', _up_options, cmd_up),
    'rollout': Command('one rollout through the running graph', _rollout_options,
                       cmd_rollout),
    'query': Command('theta = PS(tau) and its variance', _query_options, cmd_memory),
    'memory': Command('the skill memory: add, complete, save, load, info', _memory_options,
                      cmd_memory),
    'learn': Command('learn a skill over random task instances (resumes from the checkpoint '
                     'in --out)', _learn_options, cmd_learn),
    'teach': Command('skill samples from kinesthetic demonstrations in a bag: cut, fitted, '
                     'checked, added to a skill memory file', _teach_options, cmd_teach),
    'plot': Command('plot learning runs (output folders of psl learn) into one PNG',
                    _plot_options, cmd_plot),
    'record': Command('record topics into a rosbag2 (MCAP) bag', _record_options, cmd_record),
    'demo': Command('start the graph, roll the demonstration out over a few obstacle '
                    'positions, learn the skill, roll it out zero-shot on the same positions, '
                    'record a bag, end everything', _demo_options, cmd_demo),
    'init': Command('a task file from a robot description (URDF or MJCF as published): the '
                    'chain to a link, gains, postures and a target box from the model',
                    _init_options, cmd_init),
    'check': Command('what psl makes of a task\'s robot (joints, limits, masses, end '
                     'effector, scene) and what will hurt learning (gravity sag, torque '
                     'saturation), with the fix', _check_options, cmd_check),
    'params': Command("a node's parameters at their defaults, as a ROS parameter file",
                      _params_options, cmd_params),
    'render': Command('draw one rollout offscreen into an animated GIF', _render_options,
                      cmd_render),
    'view': Command('the running graph live in the Foxglove app (a WebSocket server on '
                    'ws://127.0.0.1:8765), or its layout file', _view_options, cmd_view),
    'bench': Command('benchmarks (see docs/benchmarks.md)', _bench_options, cmd_bench),
    'run': Command("one node of the graph by its package and executable, as ros2 run "
                   "(e.g. a worker's nodes on a second machine)", _run_options, cmd_run),
}


class Parser(argparse.ArgumentParser):
    """argparse's parser, with an error as one line on stderr (exit code 2) that points to
    ``--help`` instead of printing the usage."""

    def error(self, message: str):
        self.exit(2, f'{self.prog}: {message} (see {self.prog} --help)\n')


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of ``psl``: every command with its help; the options of `command` only
    (of every command when None), so that a command imports no other command's modules."""
    parser = Parser(prog='psl', description=__doc__,
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')
    for name, spec in COMMANDS.items():
        p = sub.add_parser(name, help=spec.help, description=spec.help)
        if command is None or command == name:
            spec.add_options(p)
        p.set_defaults(func=spec.run)
    return parser


def _stdout_to_devnull() -> None:
    """After a BrokenPipeError: what is left to write (also at interpreter exit) goes to
    /dev/null, as the Python docs recommend (signal module, "Note on SIGPIPE")."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):       # a stdout without a file descriptor (a test's capture)
        pass


def is_refusal(exc: BaseException) -> bool:
    """Whether `exc` is one of psl's own refusals of bad input: a ValueError of a class a psl
    package defines for it (TaskError, MemoryFileError, MetricsError, BagError,
    SessionFolderError, ...), whose message names the file or value and says what is wrong."""
    return isinstance(exc, ValueError) and any(
        cls.__module__.startswith('psl_') for cls in type(exc).__mro__
        if issubclass(cls, ValueError))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = argv[0] if argv and argv[0] in COMMANDS else None
    try:
        args = build_parser(command).parse_args(argv)
        code = args.func(args)
        sys.stdout.flush()      # a closed pipe raises here, not at exit
        return code
    except ValueError as exc:           # a damaged file a command did not expect: one line
        if not is_refusal(exc):
            raise
        return fail(f'psl {command}', exc, 2)
    except BrokenPipeError:
        _stdout_to_devnull()
        return SIGPIPE_EXIT
    except KeyboardInterrupt:           # Ctrl-C in a command without its own handler
        return 128 + signal.SIGINT


if __name__ == '__main__':
    sys.exit(main())
