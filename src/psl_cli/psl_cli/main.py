"""``psl``: start the node graph, run rollouts, learn skills, query the memory, plot, record
bags, run the demo and benchmarks."""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

from psl_optimizer.policy_search import STRATEGIES
from psl_optimizer.rollouts import MODES
from psl_optimizer.task_selection import TASK_SELECTIONS
from psl_cli.vectors import load_vector
from psl_ros.graph import SIM_MODES




def cmd_up(args) -> int:
    from psl_ros.graph import Graph

    graph = Graph(task=args.task, mode=args.mode, namespace=args.namespace,
                  workers=args.workers)
    names = {name for name, *_ in graph.nodes_spec}
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        graph.start()
        for p in graph.processes:
            print(f'started {p.name:18s} pid {p.pid}')
        print(f'logs in {graph.log_dir}; Ctrl-C ends the graph', flush=True)
        try:
            graph.wait_ready(timeout=60, stop=stop)
            if 'skill_memory' in names and not stop.is_set():
                print(create_task_skill(args.task, graph.namespace), flush=True)
        except (RuntimeError, TimeoutError) as exc:
            print(exc, file=sys.stderr)
            return 1
        if not stop.is_set():
            print('graph ready', flush=True)
        while not stop.wait(0.2):
            dead = graph.dead()
            if dead:
                print(graph.describe_death(dead[0]), file=sys.stderr)
                return 1
        return 0
    finally:
        graph.stop()
        print('graph ended', flush=True)


def create_task_skill(task_name: str, namespace: str = '', timeout: float = 30.0) -> str:
    """Create the task's skill in the graph's skill memory (tau ranges and default policy from
    the task; kept as it is if it exists): the memory knows no tasks. Returns its answer;
    RuntimeError if it refuses, TimeoutError if it does not answer."""
    from psl_controller.policy import policy_for
    from psl_ros.client import RosClient
    from psl_sim.task import load_task

    task = load_task(task_name)
    with RosClient(namespace) as client:
        response = client.memory('create_skill', timeout=timeout, skill=task.name,
                                 tau_low=task.tau_low.tolist(), tau_high=task.tau_high.tolist(),
                                 theta_reference=policy_for(task).default_theta.tolist())
    if not response.success:
        raise RuntimeError(f'the skill memory did not create the skill of task {task.name!r}: '
                           f'{response.message}')
    return response.message


def format_evaluation(ev: dict) -> str:
    lines = [f"reward {ev['reward']:.4f}  fulfilled {ev['fulfilled']}  "
             f"steps {ev['num_steps']}  tracking error {ev['tracking_error']:.4f} rad"]
    lines += [f'  {name:15s} {value:.6g}' for name, value in ev['components'].items()]
    return '\n'.join(lines)


def cmd_rollout(args) -> int:
    from psl_controller.policy import policy_for
    from psl_ros.client import RosClient, evaluation_dict
    from psl_sim.task import TaskError, load_task, task_id

    try:
        task = load_task(args.task)
        tau = task.tau_default if args.tau is None else task.validate_tau(args.tau)
        theta = (policy_for(task).default_theta if args.theta_file is None
                 else load_vector(args.theta_file))
    except (TaskError, OSError, ValueError) as exc:
        print(f'psl rollout: {exc}', file=sys.stderr)
        return 2
    with RosClient(args.namespace) as client:
        try:
            # by name, or by absolute path: the graph's processes have their own working dir
            result = client.rollout(task_id(task), tau, theta, timeout=args.timeout)
        except (TimeoutError, RuntimeError) as exc:
            print(f'psl rollout: {exc}', file=sys.stderr)
            return 1
    if not result.success:
        print(f'psl rollout: {result.message}', file=sys.stderr)
        return 1
    ev = evaluation_dict(result.evaluation)
    print(json.dumps(ev) if args.json else format_evaluation(ev))
    return 0


def _floats(values) -> list[float]:
    return [float(v) for v in values]


def cmd_memory(args) -> int:
    """psl query / psl memory add|complete|save|load|info: one call to the skill memory."""
    from psl_ros.client import RosClient

    action = 'query' if args.command == 'query' else args.action
    if action == 'query':
        service, fields = 'query', {'skill': args.skill, 'tau': _floats(args.tau)}
    elif action == 'add':
        if (args.theta is None) == (args.theta_file is None):
            print('psl memory add: give --theta or --theta-file', file=sys.stderr)
            return 2
        try:
            theta = args.theta if args.theta is not None else load_vector(args.theta_file)
        except (OSError, ValueError) as exc:
            print(f'psl memory add: {exc}', file=sys.stderr)
            return 2
        service, fields = 'add_sample', {'skill': args.skill, 'tau': _floats(args.tau),
                                         'theta': _floats(theta)}
    elif action == 'complete':
        pattern = _floats(args.pattern)
        known = [c == '1' for c in args.known]
        if set(args.known) - {'0', '1'}:
            print('psl memory complete: --known is a string of 0 and 1, one per entry',
                  file=sys.stderr)
            return 2
        service, fields = 'complete', {'skill': args.skill, 'pattern': pattern, 'known': known}
    elif action in ('save', 'load'):
        service, fields = action, {'path': str(Path(args.path).resolve())}
    else:
        service, fields = 'info', {}
    with RosClient(args.namespace) as client:
        try:
            response = client.memory(service, timeout=args.timeout, **fields)
        except TimeoutError as exc:
            print(f'psl: {exc}', file=sys.stderr)
            return 1
    if not response.success:
        print(f'psl: {response.message}', file=sys.stderr)
        return 1
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


def cmd_learn(args) -> int:
    """psl learn: one learning session, resumable from its output folder. Batch mode runs
    in this process; graph mode sends the session to the running graph's learner node."""
    from psl_sim.task import TaskError, load_task

    try:
        task = load_task(args.task)
    except TaskError as exc:
        print(f'psl learn: {exc}', file=sys.stderr)
        return 2
    out = Path(args.out or f'runs/{task.name}-{args.strategy}-seed{args.seed}').resolve()
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        learn = _learn_in_graph if args.mode == 'graph' else _learn_in_process
        return learn(args, task, out, stop)
    finally:
        signal.signal(signal.SIGINT, previous)


def _progress_line(args, index: int, rollouts: int, best: float, fulfilled: bool,
                   final: bool) -> None:
    """One line per task, redrawn while it is searched."""
    done = index + 1 if final else index
    bar = '#' * int(30 * done / args.tasks)
    state = 'fulfilled' if fulfilled else ('NOT fulfilled' if final else 'searching')
    print(f"\r[{bar:30s}] task {index + 1}/{args.tasks}: {rollouts:4d} rollouts, {state}, "
          f"best reward {best:.3f}   ", end='\n' if (args.verbose and final) else '',
          flush=True)


def _print_summary(args, metrics, out: Path) -> None:
    print()
    s = metrics.summary
    if s is not None:
        print(f"{s.total_rollouts} rollouts over {args.tasks} tasks; held-out zero-shot "
              f"success {100 * s.zero_shot_success_rate:.0f} % (mean reward "
              f"{s.zero_shot_mean_reward:.3f}); metrics in {out / 'metrics.json'}")
        if s.tracking_rmse_mean is not None:       # a task with feed-forward
            m = s.tracking_rmse_mean
            print(f"held-out tracking RMSE: PD only {m['pd_only']:.4f}, learned "
                  f"{m['learned']:.4f}, oracle {m['oracle']:.4f} rad")


def _learn_in_process(args, task, out: Path, stop: threading.Event) -> int:
    from psl_optimizer.learning import Learner, LearnSettings
    from psl_optimizer.policy_search import SearchSettings

    settings = LearnSettings(strategy=args.strategy, num_tasks=args.tasks, seed=args.seed,
                             num_test=args.test_tasks, task_selection=args.task_selection,
                             search=SearchSettings(max_rollouts=args.budget))

    def progress(record) -> None:
        _progress_line(args, record.index, record.rollouts, record.best_reward,
                       record.fulfilled, final=True)

    try:
        metrics = Learner(task, settings, out).run(progress=progress, should_stop=stop.is_set)
    except ValueError as exc:
        print(f'\npsl learn: {exc}', file=sys.stderr)
        return 2
    if not metrics.complete:
        print(f"\npsl learn: stopped after {len(metrics.tasks)} of {args.tasks} tasks; the "
              f'same command resumes from {out}', file=sys.stderr)
        return 130
    _print_summary(args, metrics, out)
    return 0


CANCEL_WAIT = 30.0     # s psl learn waits, after Ctrl-C, for the learner to say what it kept


def _learn_in_graph(args, task, out: Path, stop: threading.Event) -> int:
    from psl_optimizer.metrics import read_metrics
    from psl_ros.client import RosClient, Stopped
    from psl_sim.task import task_id

    def feedback(message) -> None:
        fb = message.feedback
        _progress_line(args, fb.task_index, fb.rollouts, fb.best_reward, fb.fulfilled,
                       final=False)

    with RosClient(args.namespace) as client:
        try:
            handle = client.send_learn_goal(
                feedback=feedback, task=task_id(task), strategy=args.strategy,
                num_tasks=args.tasks, max_rollouts_per_task=args.budget, seed=args.seed,
                mode='graph', output_dir=str(out), task_selection=args.task_selection)
            try:
                result = client.learner.result(handle, stop=stop)
            except Stopped:
                print('\npsl learn: cancelling (finished tasks stay in the checkpoint; Ctrl-C '
                      'again ends at once)', file=sys.stderr)
                stop.clear()
                handle.cancel_goal_async()
                try:       # the learner stops between two rollouts and says what it kept
                    result = client.learner.result(handle, timeout=CANCEL_WAIT, stop=stop)
                except Stopped:
                    print('psl learn: ended without the learner\'s answer', file=sys.stderr)
                    return 130
        except (TimeoutError, RuntimeError) as exc:
            print(f'\npsl learn: {exc}', file=sys.stderr)
            return 1
    if not result.success:
        print(f'\npsl learn: {result.message}', file=sys.stderr)
        return 1
    _print_summary(args, read_metrics(Path(result.metrics_path).parent), out)
    return 0


def cmd_plot(args) -> int:
    """psl plot DIR...: rollouts per task, reward over tau, predictive variance over tau; for a
    task with feed-forward also commanded vs executed joints and the torques (PD only,
    learned, oracle) on a held-out instance."""
    from psl_bench.plot_dynamics import plot_dynamics
    from psl_bench.plot_learning import plot_runs
    from psl_optimizer.metrics import read_metrics

    out = Path(args.out) if args.out else Path(args.dirs[0]) / 'learning.png'
    try:
        print(plot_runs(args.dirs, out))
        summary = read_metrics(args.dirs[0]).summary
        if summary is not None and summary.tracking_rmse is not None:   # with feed-forward
            print(plot_dynamics(args.dirs[0], out.with_name(out.stem + '_dynamics.png')))
    except (ValueError, OSError) as exc:
        print(f'psl plot: {exc}', file=sys.stderr)
        return 2
    return 0


def cmd_record(args) -> int:
    from psl_ros.bag_recorder import record

    try:
        recording = record(args.output, args.topics, duration=args.duration)
    except (FileExistsError, ValueError) as exc:
        print(f'psl record: {exc}', file=sys.stderr)
        return 2
    for topic, count in recording.counts.items():
        lost = recording.lost[topic]
        print(f'{topic:30s} {count}' + (f'  ({lost} lost)' if lost else ''))
    return 0


def cmd_demo(args) -> int:
    from psl_cli.demo import run_demo

    return run_demo(task=args.task, out=Path(args.out), positions=args.positions)


def cmd_bench(args) -> int:
    from psl_cli import bench_commands

    return bench_commands.run(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='psl', description=__doc__)
    sub = parser.add_subparsers(dest='command', required=True)

    up = sub.add_parser('up', help='start the node graph; Ctrl-C ends it')
    up.add_argument('--task', default='reach_over_obstacle')
    up.add_argument('--mode', choices=SIM_MODES, default=SIM_MODES[0])
    up.add_argument('--namespace', default='')
    up.add_argument('--workers', type=int, default=0,
                    help='N rollout workers (sim, controller, executor, evaluator) under '
                    '<namespace>/worker0..N-1; the learner spreads a population over them')
    up.set_defaults(func=cmd_up)

    ro = sub.add_parser('rollout', help='one rollout through the running graph')
    ro.add_argument('--task', default='reach_over_obstacle')
    ro.add_argument('--tau', type=float, nargs='+', help='task parameters (default: the task '
                    'defaults)')
    ro.add_argument('--theta-file', help='.npy, .json or whitespace-separated text; default: '
                    "the demonstration's fit")
    ro.add_argument('--namespace', default='')
    ro.add_argument('--timeout', type=float, default=120.0)
    ro.add_argument('--json', action='store_true')
    ro.set_defaults(func=cmd_rollout)

    common = argparse.ArgumentParser(add_help=False)
    common.add_argument('--namespace', default='')
    common.add_argument('--timeout', type=float, default=10.0)
    common.add_argument('--json', action='store_true')

    query = sub.add_parser('query', parents=[common], help='theta = PS(tau) and its variance')
    query.add_argument('--skill', required=True)
    query.add_argument('--tau', type=float, nargs='+', required=True)
    query.set_defaults(func=cmd_memory)

    memory = sub.add_parser('memory', help='the skill memory: add, complete, save, load, info')
    actions = memory.add_subparsers(dest='action', required=True)
    add = actions.add_parser('add', parents=[common], help='add one sample (tau, theta)')
    add.add_argument('--skill', required=True)
    add.add_argument('--tau', type=float, nargs='+', required=True)
    add.add_argument('--theta', type=float, nargs='+')
    add.add_argument('--theta-file')
    complete = actions.add_parser('complete', parents=[common],
                                  help='complete [tau, theta] with the known entries clamped')
    complete.add_argument('--skill', required=True)
    complete.add_argument('--pattern', type=float, nargs='+', required=True)
    complete.add_argument('--known', required=True, help="e.g. 11000: one 0/1 per entry")
    for name in ('save', 'load'):
        p = actions.add_parser(name, parents=[common], help=f'{name} the whole memory')
        p.add_argument('path')
    actions.add_parser('info', parents=[common], help='the skills and their sample counts')
    memory.set_defaults(func=cmd_memory)

    learn = sub.add_parser('learn', help='learn a skill over random task instances (resumes '
                           'from the checkpoint in --out)')
    learn.add_argument('--task', default='reach_over_obstacle')
    learn.add_argument('--strategy', choices=STRATEGIES, default='bootstrap')
    learn.add_argument('--tasks', type=int, default=30)
    learn.add_argument('--budget', type=int, default=200, help='rollouts per task at most')
    learn.add_argument('--seed', type=int, default=0)
    learn.add_argument('--test-tasks', type=int, default=20)
    learn.add_argument('--out', help='output folder (default runs/TASK-STRATEGY-seedK)')
    learn.add_argument('--mode', choices=MODES, default=MODES[0],
                       help='batch: rollouts in this process with mujoco.rollout (fast); graph: '
                       "the running graph's learner node, rollouts through execute_rollout")
    learn.add_argument('--task-selection', choices=TASK_SELECTIONS, default=TASK_SELECTIONS[0],
                       help='next instance: random, or the most uncertain of 20 candidates '
                       "(the skill's predictive variance)")
    learn.add_argument('--namespace', default='', help='graph mode: namespace of the graph')
    learn.add_argument('--verbose', action='store_true', help='one line per task')
    learn.set_defaults(func=cmd_learn)

    plot = sub.add_parser('plot', help='plot learning runs (output folders of psl learn) '
                          'into one PNG')
    plot.add_argument('dirs', nargs='+', metavar='DIR', help='run folders; several seeds of a '
                      'strategy are drawn as mean and min-max band')
    plot.add_argument('--out', help='PNG file (default: DIR/learning.png of the first DIR)')
    plot.set_defaults(func=cmd_plot)

    rec = sub.add_parser('record', help='record topics into a rosbag2 (MCAP) bag')
    rec.add_argument('-o', '--output', required=True)
    rec.add_argument('--duration', type=float, default=None, help='seconds (default: Ctrl-C)')
    rec.add_argument('topics', nargs='*', help='topics (default: all)')
    rec.set_defaults(func=cmd_record)

    demo = sub.add_parser('demo', help='start the graph, roll the demonstration out over a '
                          'few obstacle positions, learn the skill, roll it out zero-shot on '
                          'the same positions, record a bag, end everything')
    demo.add_argument('--task', default='reach_over_obstacle')
    demo.add_argument('--out', default='demo')
    demo.add_argument('--positions', type=int, default=5)
    demo.set_defaults(func=cmd_demo)

    render_parser = sub.add_parser('render', help='draw one rollout offscreen into an animated '
                                   'GIF')
    from psl_cli import render
    render.add_arguments(render_parser)
    render_parser.set_defaults(func=render.run)

    bench_parser = sub.add_parser('bench', help='benchmarks (see docs/benchmarks.md)')
    from psl_cli import bench_commands
    bench_commands.add_arguments(bench_parser)
    bench_parser.set_defaults(func=cmd_bench)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == '__main__':
    sys.exit(main())
