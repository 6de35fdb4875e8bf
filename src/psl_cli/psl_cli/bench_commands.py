"""``psl bench ...``: the command line of the benchmarks in `psl_bench` (docs/benchmarks.md).

Each subcommand parses its options, calls its benchmark (which returns a report: plain data)
and prints the report's table, or the report as JSON with ``--json``. A bad setting ends with
exit code 2 and the reason. Numbers are printed, never stored (``-o/--out`` keeps run folders).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

from psl_bench.dynamics import OPTIMISERS
from psl_bench.false_successes import NOISE_LEVELS
from psl_bench.memories import MEMORIES, STARTS
from psl_bench.sim_to_real import (REAL_ROBOT, SEEDS as SIM_TO_REAL_SEEDS,
                                   TASKS as SIM_TO_REAL_TASKS)
from psl_bench.teach import COUNTS as TEACH_COUNTS, NOISE as TEACH_NOISE, TASKS as TEACH_TASKS
from psl_cli import options
from psl_cli.options import fail, non_negative_int, positive_int
from psl_memory.registry import READOUTS
from psl_optimizer.policy_search import STRATEGIES

RUN_FOLDERS = 'keep every run folder (metrics.json) here, for psl plot'


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest='bench', required=True)

    def bench(name: str, help: str, task: str | None = options.DEFAULT_TASK):
        p = sub.add_parser(name, help=help, description=help)
        if task is not None:
            options.add_task(p, default=task)
        p.add_argument('--json', action='store_true', help='the whole report as JSON')
        return p

    def sessions(p, seeds: int, tasks: int, test_tasks: int, after: bool = True) -> None:
        """The options of benchmarks made of learning sessions."""
        p.add_argument('--seeds', type=options.seed, nargs='+', default=list(range(seeds)))
        p.add_argument('--tasks', type=positive_int, default=tasks,
                       help='training tasks per session')
        p.add_argument('--budget', type=positive_int, default=300,
                       help='rollouts per task at most')
        p.add_argument('--test-tasks', type=positive_int, default=test_tasks,
                       help='held-out tasks per seed')
        if after:
            p.add_argument('--after', type=non_negative_int, default=20,
                           help='rollouts per task are averaged over the tasks after this many')

    def spread(p) -> None:
        """The options of a sweep whose sessions run as Ray tasks (psl_bench.sessions)."""
        p.add_argument('--serial', action='store_true',
                       help='one session after the other in this process (default: each a '
                       "Ray task, on this machine's cores or the cluster of --address)")
        p.add_argument('--address', metavar='HOST:PORT',
                       help='a Ray cluster to run the sessions on (ray start --head; '
                       'default: $RAY_ADDRESS, else a local cluster for the sweep)')

    p = bench('graph', 'lockstep steps/s, DDS round trip, realtime misses')
    p.add_argument('--rollouts', type=positive_int, default=10)
    p.add_argument('--round-trips', type=positive_int, default=2000)
    p.add_argument('--realtime-seconds', type=float, default=60.0,
                   help="seconds of psl's standard robot on the wall clock (0 skips it)")
    p.add_argument('--busy', type=non_negative_int, default=0,
                   help='cores kept busy by spinning processes while the standard robot runs')
    p.add_argument('--view', choices=('off', 'idle', 'watched'), default='off',
                   help='the lockstep rollouts with the view node (psl up --view): off (none), '
                   'idle (running, no viewer) or watched (a Foxglove viewer subscribed to '
                   'every channel)')
    p = bench('rollout', 'batch-mode steps/s beside raw mujoco.rollout')
    p.add_argument('--population', type=positive_int, default=32)
    p.add_argument('--repeats', type=positive_int, default=7)
    p = bench('memory', 'readout update/query time against N; service round trip of query '
              'beside a bare DDS round trip', task=None)
    p.add_argument('--sizes', type=positive_int, nargs='+', default=[10, 100, 1000, 10000])
    p.add_argument('--n-hidden', type=positive_int, default=100)
    p.add_argument('--service-samples', type=positive_int, default=1000)
    p.add_argument('--round-trips', type=positive_int, default=1000)
    p = bench('memory-load', 'many clients at once on the skill memory: lost answers and '
              'answer times', task=None)
    p.add_argument('--clients', type=positive_int, default=8, help='querying client processes')
    p.add_argument('--adders', type=non_negative_int, default=2,
                   help='adding client processes')
    p.add_argument('--calls', type=positive_int, default=500,
                   help='queries per client (adds: a fifth)')
    p.add_argument('--samples', type=positive_int, default=200,
                   help='samples in the skill before the load starts')
    p.add_argument('--timeout', type=options.positive_float, default=5.0,
                   help='seconds a call may wait for its answer before it counts as lost')
    p.add_argument('--busy', type=non_negative_int, default=0,
                   help='cores kept busy by spinning processes meanwhile')
    p.add_argument('--log-dir', help="keep the skill memory's log here")
    p = bench('cli', 'a psl command that talks to the graph (psl memory info), end to end as '
              'a process: total, to the answer, after it; beside the call in this process',
              task=None)
    p.add_argument('--runs', type=positive_int, default=10, help='runs of each')
    p.add_argument('--timeout', type=options.positive_float, default=10.0,
                   help="seconds to wait for the skill memory's answer")
    p = bench('recording', 'lockstep steps/s with and without a bag recorder, messages kept and '
              'lost per topic')
    p.add_argument('--rollouts', type=positive_int, default=5,
                   help='rollouts per round and phase')
    p.add_argument('--rounds', type=positive_int, default=3)
    p.add_argument('--busy', type=non_negative_int, default=0,
                   help='cores kept busy meanwhile')
    p.add_argument('--topics', nargs='+', help='topics to record (default: what psl demo '
                   'records)')
    p = bench('workers', 'one graph-mode learning session with 1 and 2 rollout workers')
    p.add_argument('--workers', type=positive_int, nargs='+', default=[1, 2])
    p.add_argument('--strategy', choices=STRATEGIES, default='scratch')
    p.add_argument('--tasks', type=positive_int, default=3)
    p.add_argument('--budget', type=positive_int, default=22)
    p.add_argument('--seed', type=options.seed, default=5)
    p = bench('learn', 'policy-search strategies over task instances: rollouts per task, '
              'zero-shot success on held-out tasks')
    p.add_argument('--strategies', nargs='+', choices=STRATEGIES, default=list(STRATEGIES))
    sessions(p, seeds=5, tasks=30, test_tasks=20)
    p.add_argument('--readout', choices=READOUTS,
                   help="the skill's readout (default: the learner's)")
    p.add_argument('--skill-maps', nargs='+', default=['elm'], metavar='MAP',
                   help='what fills the skill slot, each a session per strategy and seed '
                   '(space- or comma-separated): elm (the skill memory, the default) and the '
                   'baselines library (k nearest solved instances) and gp (Gaussian-process '
                   'regression)')
    options.add_out(p, RUN_FOLDERS)
    spread(p)
    p = bench('dynamics', 'learned feed-forward on held-out payloads: tracking error of PD '
              'only, learned and the inverse-dynamics oracle', task='payload_transport')
    p.add_argument('--optimisers', nargs='+', choices=OPTIMISERS, default=list(OPTIMISERS),
                   help='ilc (ILC of theta_D, then CMA-ES) and/or cma (CMA-ES only)')
    sessions(p, seeds=3, tasks=8, test_tasks=10, after=False)
    options.add_out(p, RUN_FOLDERS)
    p = bench('memories', 'associative memories: completion error both ways on learned '
              'sessions')
    p.add_argument('--seeds', type=options.seed, nargs='+', default=[0, 1, 2, 3, 4])
    options.add_out(p, 'session folders (as psl bench learn --out leaves them); missing '
                    'bootstrap sessions are learned here first', default='runs/bench-learn')
    p.add_argument('--tasks', type=positive_int, default=30,
                   help='training tasks of a session learned here')
    p.add_argument('--stride', type=positive_int, default=3,
                   help='hold out every stride-th sample in turn (1: leave-one-out)')
    p.add_argument('--memories', nargs='+', choices=MEMORIES, default=list(MEMORIES))
    p.add_argument('--start', choices=STARTS, default=STARTS[0],
                   help='free entries start at the centre of the ranges or at the mean of the '
                   'training samples')
    p = bench('encodings', 'DMP vs GMR encoding, random vs variance-driven task selection')
    sessions(p, seeds=5, tasks=30, test_tasks=20)
    p.add_argument('--n-components', type=positive_int, default=6, help='GMR components')
    options.add_out(p, 'also write the report (with the learning curves) as JSON')
    p.add_argument('--figure', help='also draw the task-selection curves into this PNG')
    p = bench('sim-to-real', 'a skill learned on the model, continued on a robot whose model is '
              'wrong (batch mode, a model error): rollouts and zero-shot success on the robot, '
              'scratch vs continued; tracking error of the simulated feed-forward and ILC',
              task=None)
    p.add_argument('--tasks', nargs='+', default=list(SIM_TO_REAL_TASKS),
                   help='tasks (names or YAML files)')
    p.add_argument('--model-error', default=REAL_ROBOT,
                   help='how the robot differs from the model: mass_scale=S,frictionloss=F,'
                   'damping=D (any subset)')
    p.add_argument('--nominal-seed', type=options.seed, default=3,
                   help='seed of the session on the model')
    p.add_argument('--nominal-tasks', type=positive_int, default=30,
                   help='training tasks on the model')
    p.add_argument('--seeds', type=options.seed, nargs='+', default=list(SIM_TO_REAL_SEEDS),
                   help='robot seeds: each the training and held-out instances of one set of '
                   'sessions on the robot')
    p.add_argument('--robot-tasks', type=positive_int, default=10,
                   help='training tasks on the robot, per seed')
    p.add_argument('--measurement-noise', default='',
                   help="the robot's measurement noise: position=RAD,velocity=RAD_S[,seed=N] "
                   '(default: none)')
    p.add_argument('--robot-gains', type=float, default=1.0,
                   help="the robot controller's PD gains as a share of the task's (its own "
                   'controller; default 1: the same)')
    p.add_argument('--test-tasks', type=positive_int, default=20,
                   help='held-out instances on the robot')
    p.add_argument('--budget', type=positive_int, default=200, help='rollouts per task at most')
    p.add_argument('--ilc-iterations', type=non_negative_int, default=10,
                   help='ILC steps on the robot from the simulated skill (tracking table)')
    p.add_argument('--continuations', nargs='+', default=['residual', 'samples'],
                   help='ways of continuing the simulated skill, each a session: residual '
                   '(the default of continue_from) and/or samples')
    options.add_out(p, RUN_FOLDERS)
    spread(p)
    p = bench('teach', 'a skill taught with 3, 5, 10 demonstrations (psl teach) against the '
              'YAML demonstration alone: rollouts for the training tasks, zero-shot after',
              task=None)
    p.add_argument('--tasks', nargs='+', default=list(TEACH_TASKS),
                   help='tasks (names or YAML files)')
    p.add_argument('--counts', nargs='+', type=non_negative_int, default=list(TEACH_COUNTS),
                   help='demonstrations taught, each a session (0: none, the YAML demonstration)')
    p.add_argument('--seeds', nargs='+', type=options.seed, default=[0, 1, 2])
    p.add_argument('--tasks-per-session', type=positive_int, default=30,
                   help='training tasks per session')
    p.add_argument('--test-tasks', type=positive_int, default=20)
    p.add_argument('--budget', type=positive_int, default=300, help='rollouts per task at most')
    p.add_argument('--noise', default=TEACH_NOISE,
                   help='measurement noise of the demonstrations (position=RAD,velocity=RAD_S)')
    p.add_argument('--through', choices=('batch', 'graph'), default='batch',
                   help='how the demonstrations are shown and recorded: batch rollouts with '
                   "noise (default), or through the node graph on psl's standard robot "
                   '(noise, the wall clock, driven back between two) into a bag that psl '
                   "teach's steps read")
    p.add_argument('--robot', choices=('standard', 'sim'), default='standard',
                   help="with --through graph: psl's standard robot on the wall clock "
                   "(default) or psl's lockstep simulator (exact measurements, no noise)")
    options.add_out(p, RUN_FOLDERS)
    spread(p)        # --through graph: one after the other here, whatever is asked
    p = bench('false-successes', 'a noisy robot (measurement noise): samples added on a lucky '
              'rollout, with and without confirming a success (k of n)', task=None)
    p.add_argument('--tasks', nargs='+', default=list(NOISE_LEVELS),
                   help='tasks (names or YAML files)')
    p.add_argument('--noise', nargs='+', metavar='LEVEL',
                   help='noise levels for every task, each position=RAD,velocity=RAD_S[,seed=N] '
                   "(default: each task's realistic level and one at the edge)")
    p.add_argument('--confirms', nargs='+', default=['1/1', '2/3', '3/3'], metavar='K/N',
                   help='confirmations, each a session: k of n rollouts must fulfil (1/1: off)')
    p.add_argument('--seed', type=options.seed, default=21)
    p.add_argument('--tasks-per-session', type=positive_int, default=20,
                   help='training tasks per session')
    p.add_argument('--test-tasks', type=positive_int, default=20)
    p.add_argument('--budget', type=positive_int, default=200, help='rollouts per task at most')
    p.add_argument('--reruns', type=positive_int, default=10,
                   help='noisy re-runs of every added sample')
    options.add_out(p, RUN_FOLDERS)
    spread(p)


def _progress(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _folder(path: str | None) -> str | None:
    """An -o/--out folder, created before the benchmark runs (ValueError if it cannot be)."""
    return None if path is None else str(options.output_folder(path))


def _file(path: str | None) -> Path | None:
    """An output file, checked before the benchmark runs (ValueError if it cannot be written)."""
    return None if path is None else options.output_file(path)


def _graph(args) -> tuple[dict, str]:
    from psl_bench import graph
    report = graph.measure(args.task, args.rollouts, args.round_trips, args.realtime_seconds,
                           busy=args.busy, view=args.view)
    return report, graph.format_report(report)


def _rollout(args) -> tuple[dict, str]:
    from psl_bench import rollout
    report = rollout.measure(args.task, args.population, args.repeats)
    return report, rollout.format_report(report)


def _memory(args) -> tuple[dict, str]:
    from psl_bench import memory
    report = memory.run(args.sizes, args.n_hidden, args.service_samples, args.round_trips)
    return report, memory.format_report(report)


def _memory_load(args) -> tuple[dict, str]:
    from psl_bench import memory_load
    report = memory_load.measure(args.clients, args.adders, args.calls, timeout=args.timeout,
                                 busy=args.busy, samples=args.samples, log_dir=args.log_dir)
    return report, memory_load.format_report(report)


def _cli(args) -> tuple[dict, str]:
    from psl_bench import cli_latency
    report = cli_latency.measure(args.runs, args.timeout)
    return report, cli_latency.format_report(report)


def _recording(args) -> tuple[dict, str]:
    from psl_bench import recording
    from psl_ros import names
    report = recording.measure(args.task, args.rollouts, args.busy,
                               args.topics or names.RECORDED_TOPICS, args.rounds)
    return report, recording.format_report(report)


def _workers(args) -> tuple[dict, str]:
    from psl_bench import workers
    report = workers.measure(args.task, args.workers, args.strategy, args.tasks, args.budget,
                             args.seed, progress=_progress)
    return report, workers.format_report(report)


def _learn(args) -> tuple[dict, str]:
    from psl_bench import learn
    report = learn.run(task_name=args.task, strategies=args.strategies, seeds=args.seeds,
                       num_tasks=args.tasks, budget=args.budget, num_test=args.test_tasks,
                       after=args.after, out=_folder(args.out), readout=args.readout,
                       skill_maps=[name for arg in args.skill_maps
                                   for name in arg.split(',') if name],
                       progress=_progress, runner='serial' if args.serial else 'ray',
                       address=args.address)
    return report, learn.format_table(report)


def _dynamics(args) -> tuple[dict, str]:
    from psl_bench import dynamics
    report = dynamics.run(task_name=args.task, optimisers=args.optimisers, seeds=args.seeds,
                          num_tasks=args.tasks, budget=args.budget, num_test=args.test_tasks,
                          out=_folder(args.out), progress=_progress)
    return report, dynamics.format_table(report)


def _memories(args) -> tuple[dict, str]:
    from psl_bench import memories
    report = memories.run(task_name=args.task, seeds=args.seeds, out=_folder(args.out),
                          num_tasks=args.tasks, stride=args.stride, memories=args.memories,
                          start=args.start, progress=_progress)
    return report, memories.format_table(report)


def _encodings(args) -> tuple[dict, str]:
    from psl_bench import encodings
    out, figure = _file(args.out), _file(args.figure)
    report = encodings.run(args.task, args.seeds, args.tasks, args.budget, args.test_tasks,
                           args.after, args.n_components, progress=_progress)
    if out:
        out.write_text(json.dumps(report, indent=1))
    if figure:
        _progress(f'figure: {encodings.plot_selection(report, figure)}')
    return report, encodings.format_tables(report)


def _sim_to_real(args) -> tuple[dict, str]:
    from psl_bench import sim_to_real
    report = sim_to_real.run(tasks=args.tasks, model_error=args.model_error,
                             nominal_seed=args.nominal_seed, nominal_tasks=args.nominal_tasks,
                             seeds=args.seeds, num_tasks=args.robot_tasks,
                             num_test=args.test_tasks, budget=args.budget,
                             ilc_iterations=args.ilc_iterations,
                             continuations=args.continuations,
                             measurement_noise=args.measurement_noise,
                             robot_gains=args.robot_gains, out=_folder(args.out),
                             progress=_progress, runner='serial' if args.serial else 'ray',
                             address=args.address)
    return report, sim_to_real.format_table(report)


def _false_successes(args) -> tuple[dict, str]:
    from psl_bench import false_successes
    report = false_successes.run(
        tasks=args.tasks, noise=args.noise,
        confirms=[false_successes.parse_confirm(c) for c in args.confirms], seed=args.seed,
        num_tasks=args.tasks_per_session, num_test=args.test_tasks, budget=args.budget,
        reruns=args.reruns, out=_folder(args.out), progress=_progress,
        runner='serial' if args.serial else 'ray', address=args.address)
    return report, false_successes.format_table(report)


def _teach(args) -> tuple[dict, str]:
    from psl_bench import teach
    report = teach.run(tasks=args.tasks, counts=args.counts, seeds=args.seeds,
                       num_tasks=args.tasks_per_session, num_test=args.test_tasks,
                       budget=args.budget, noise=args.noise, out=_folder(args.out),
                       progress=_progress, through=args.through,
                       robot=args.robot, runner='serial' if args.serial else 'ray',
                       address=args.address)
    return report, teach.format_table(report)


BENCHES = {'graph': _graph, 'rollout': _rollout, 'memory': _memory,
           'memory-load': _memory_load, 'cli': _cli, 'recording': _recording, 'workers': _workers,
           'learn': _learn, 'dynamics': _dynamics, 'memories': _memories,
           'encodings': _encodings, 'sim-to-real': _sim_to_real,
           'false-successes': _false_successes, 'teach': _teach}


def run(args) -> int:
    """Run the benchmark `args.bench`; print its table (or JSON). Exit code 2 for a bad
    setting or a folder or file it cannot write, 1 when the graph could not run it."""
    command = f'psl bench {args.bench}'
    try:
        # stdout holds the table or the JSON alone: whatever else prints while the benchmark
        # runs goes to stderr (Ray's driver prints a dead worker's notice on stdout, from a
        # thread of its own, even with log_to_driver off)
        with contextlib.redirect_stdout(sys.stderr):
            report, table = BENCHES[args.bench](args)
    except (ValueError, OSError) as exc:
        return fail(command, exc, 2)
    except (RuntimeError, TimeoutError) as exc:
        return fail(command, exc, 1)
    print(json.dumps(report, indent=2) if args.json else table, end='\n' if args.json else '')
    return 0
