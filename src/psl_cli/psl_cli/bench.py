"""``psl bench``: measurements behind docs/benchmarks.md (numbers are printed, never stored).

``psl bench graph``: lockstep control steps per second through the real node graph, beside
the bare publish/answer round trip between two processes measured in the same run, and the
deadline misses of the realtime mode at 500 Hz over a long episode.
``psl bench memory``: per-sample update and query time of each readout against the number of
stored samples, and the query service round trip beside a bare DDS round trip.
``psl bench learn``: policy-search strategies over task instances (`psl_cli.bench_learn`).
``psl bench dynamics``: learned feed-forward on held-out payloads (`psl_cli.bench_dynamics`).
``psl bench memories``: associative memories completing learned samples both ways
(`psl_cli.bench_memories`).
``psl bench encodings``: DMP vs GMR encoding, random vs variance-driven task selection
(`psl_cli.bench_encodings`).
"""
from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import threading
import time

import numpy as np

ECHO_TOPICS = ('bench/ping', 'bench/pong')


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest='bench', required=True)
    graph = sub.add_parser('graph', help='lockstep steps/s, DDS round trip, realtime misses')
    graph.add_argument('--task', default='reach_over_obstacle')
    graph.add_argument('--rollouts', type=int, default=10)
    graph.add_argument('--round-trips', type=int, default=2000)
    graph.add_argument('--realtime-seconds', type=float, default=60.0,
                       help='length of the realtime episode (0 skips it)')
    graph.add_argument('--json', action='store_true')
    add_rollout_arguments(sub)
    memory = sub.add_parser('memory', help='readout update/query time against N; service '
                            'round trip of query beside a bare DDS round trip')
    memory.add_argument('--sizes', type=int, nargs='+', default=[10, 100, 1000, 10000])
    memory.add_argument('--n-hidden', type=int, default=100)
    memory.add_argument('--service-samples', type=int, default=1000)
    memory.add_argument('--round-trips', type=int, default=1000)
    memory.add_argument('--json', action='store_true')
    from psl_cli import bench_dynamics, bench_encodings, bench_learn, bench_memories
    bench_learn.add_arguments(sub)
    bench_dynamics.add_arguments(sub)
    bench_memories.add_arguments(sub)
    bench_encodings.add_arguments(sub)


def add_rollout_arguments(sub) -> None:
    rollout = sub.add_parser('rollout', help='batch-mode steps/s beside raw mujoco.rollout')
    rollout.add_argument('--task', default='reach_over_obstacle')
    rollout.add_argument('--population', type=int, default=32)
    rollout.add_argument('--repeats', type=int, default=7)
    rollout.add_argument('--json', action='store_true')


def bench_rollout(args) -> int:
    """Batch mode (references, controls, mujoco.rollout, rewards) against mujoco.rollout
    alone on the same model with the same controls, in the same run."""
    from mujoco import rollout as mj_rollout

    from psl_optimizer.batch_rollout import CONTROL, BatchRollouts
    from psl_sim.task import load_task

    task = load_task(args.task)
    batch = BatchRollouts(task)
    rng = np.random.default_rng(0)
    default = batch.policy.default_theta
    thetas = default + rng.normal(0.0, 0.1 * np.abs(default).max(), (args.population,
                                                                      default.size))
    taus = np.array([task.sample_tau(rng) for _ in range(args.population)])
    control = batch.controls([batch.policy.reference(t) for t in thetas], taus)
    steps = args.population * control.shape[1]
    raw, full, refs, ctrls = [], [], [], []
    for _ in range(args.repeats):
        start = time.perf_counter()
        mj_rollout.rollout(batch.model, batch.datas, batch.initial_state[None], control,
                           control_spec=CONTROL)
        raw.append(time.perf_counter() - start)
        start = time.perf_counter()
        batch.run(thetas, taus)
        full.append(time.perf_counter() - start)
        start = time.perf_counter()                  # where batch mode's extra time goes
        references = [batch.policy.reference(t) for t in thetas]
        refs.append(time.perf_counter() - start)
        start = time.perf_counter()
        batch.controls(references, taus)
        ctrls.append(time.perf_counter() - start)
    med = statistics.median
    report = {'task': task.name, 'population': args.population, 'steps_per_rollout':
              control.shape[1], 'threads': len(batch.datas),
              'raw_steps_per_second': steps / med(raw),
              'batch_steps_per_second': steps / med(full),
              # each repeat's raw and batch run back to back: robust to a drifting load
              'ratio_paired_median': med([r / f for r, f in zip(raw, full)]),
              'ms_per_population': {'total': 1e3 * med(full), 'mujoco_rollout': 1e3 * med(raw),
                                    'references': 1e3 * med(refs), 'controls': 1e3 * med(ctrls),
                                    'rewards_and_rest': 1e3 * (med(full) - med(raw) - med(refs)
                                                               - med(ctrls))}}
    report['ratio'] = report['batch_steps_per_second'] / report['raw_steps_per_second']
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        ms = report['ms_per_population']
        print(f"raw mujoco.rollout: {report['raw_steps_per_second']:.0f} steps/s; batch mode "
              f"(DMP references, controls, rollout, rewards): "
              f"{report['batch_steps_per_second']:.0f} steps/s; ratio {report['ratio']:.2f} "
              f"(paired median {report['ratio_paired_median']:.2f}; population "
              f"{args.population}, {report['threads']} threads)")
        print('ms per population: ' + ', '.join(f'{k} {v:.1f}' for k, v in ms.items()))
    return 0


def main(args) -> int:
    if args.bench == 'rollout':
        return bench_rollout(args)
    if args.bench == 'graph':
        return bench_graph(args)
    if args.bench == 'memory':
        return bench_memory(args)
    if args.bench == 'learn':
        from psl_cli import bench_learn
        return bench_learn.main(args)
    if args.bench == 'dynamics':
        from psl_cli import bench_dynamics
        return bench_dynamics.main(args)
    if args.bench == 'memories':
        from psl_cli import bench_memories
        return bench_memories.main(args)
    if args.bench == 'encodings':
        from psl_cli import bench_encodings
        return bench_encodings.main(args)
    raise ValueError(f'unknown benchmark {args.bench!r}')


def measure_query_service(n_samples: int, n_calls: int) -> list[float]:
    """Round-trip times [s] of QuerySkill calls to a skill_memory process holding a skill
    with n_samples samples (restored from a memory file at start)."""
    import tempfile
    from pathlib import Path

    from psl_cli.graph import Graph
    from psl_ros.client import RosClient
    from psl_memory.skill_memory import SkillMemory

    rng = np.random.default_rng(0)
    memory = SkillMemory()
    memory.create('bench', [0.0, 0.0], [1.0, 1.0], np.zeros(24))
    taus = rng.uniform(0.0, 1.0, (n_samples, 2))
    for tau in taus:
        memory.add('bench', tau, np.r_[np.sin(3 * tau), np.cos(2 * tau), np.zeros(20)])
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / 'bench_memory.npz'
        memory.save(path)
        graph = Graph(nodes=(('skill_memory', 'psl_memory', 'skill_memory'),),
                      extra_params={'skill_memory': {'autosave_path': str(path)}})
        with graph, RosClient() as client:
            info = json.loads(client.memory('info', timeout=60).message)
            if info['bench']['num_samples'] != n_samples:
                raise RuntimeError(f'the memory node holds {info}')
            times = []
            for i in range(n_calls + 50):
                start = time.perf_counter()
                response = client.memory('query', skill='bench', tau=taus[i % n_samples].tolist())
                elapsed = time.perf_counter() - start
                if not response.success:
                    raise RuntimeError(response.message)
                if i >= 50:
                    times.append(elapsed)
    return times


def bench_memory(args) -> int:
    from psl_cli.bench_memory import format_table, measure_readouts

    report = {'readouts': measure_readouts(sizes=tuple(args.sizes), n_hidden=args.n_hidden)}
    service = measure_query_service(args.service_samples, args.round_trips)
    bare = measure_round_trip(args.round_trips)
    report['service'] = {
        'samples': args.service_samples,
        'query_ms': {'p50': 1e3 * statistics.median(service),
                     'p99': 1e3 * float(np.percentile(service, 99))},
        'bare_round_trip_ms': {'p50': 1e3 * statistics.median(bare),
                               'p99': 1e3 * float(np.percentile(bare, 99))}}
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(format_table(report['readouts']))
        q, b = report['service']['query_ms'], report['service']['bare_round_trip_ms']
        print(f"query service round trip with {args.service_samples} samples: p50 "
              f"{q['p50']:.3f} ms, p99 {q['p99']:.3f} ms (bare DDS round trip in the same run: "
              f"p50 {b['p50']:.3f} ms, p99 {b['p99']:.3f} ms)")
    return 0


# -- bare round trip ------------------------------------------------------------------------
def echo_main() -> None:
    """A second process that answers every ping with a pong (the reference round trip)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64MultiArray

    rclpy.init()
    node = Node('bench_echo')
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(Float64MultiArray, ECHO_TOPICS[1], qos)
    node.create_subscription(Float64MultiArray, ECHO_TOPICS[0], pub.publish, qos)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def measure_round_trip(n: int) -> list[float]:
    """Round-trip times [s] of n publish/answer exchanges with an echo process."""
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64MultiArray

    echo = subprocess.Popen([sys.executable, '-c', 'from psl_cli.bench import echo_main; '
                             'echo_main()'], start_new_session=True)
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = Node('bench_ping', context=context)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        got = []
        node.create_subscription(Float64MultiArray, ECHO_TOPICS[1], got.append, qos)
        pub = node.create_publisher(Float64MultiArray, ECHO_TOPICS[0], qos)
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() == 0 or node.count_publishers(ECHO_TOPICS[1]) == 0:
            if time.monotonic() > deadline:
                raise RuntimeError('the echo process did not come up')
            executor.spin_once(timeout_sec=0.05)
        time.sleep(0.5)
        msg = Float64MultiArray(data=[0.0, 0.0, 0.0])
        times = []
        for i in range(n + 50):
            got.clear()
            start = time.perf_counter()
            pub.publish(msg)
            while not got:
                executor.spin_once(timeout_sec=1.0)
                if not got and time.perf_counter() - start > 5:
                    raise RuntimeError('no pong within 5 s')
            if i >= 50:    # warm-up excluded
                times.append(time.perf_counter() - start)
        return times
    finally:
        rclpy.try_shutdown(context=context)
        echo.send_signal(2)
        try:
            echo.wait(timeout=5)
        except subprocess.TimeoutExpired:
            echo.kill()
            echo.wait()


# -- graph ----------------------------------------------------------------------------------
class EpisodeStats:
    """Collects the simulator's end-of-episode status from /diagnostics."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        self.done: list[dict] = []
        self.event = threading.Event()
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on, 100)

    def _on(self, msg) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if 'steps_done' in values and values['steps_done'] == values['steps']:
                self.done.append(values)
                self.event.set()


def bench_graph(args) -> int:
    from psl_cli.graph import Graph
    from psl_ros.client import RosClient
    from psl_controller.policy import policy_for
    from psl_sim.task import load_task, task_id

    task = load_task(args.task)
    theta = policy_for(task).default_theta
    rng = np.random.default_rng(0)
    report: dict = {'task': task.name, 'machine_cores': os.cpu_count()}

    rtt = measure_round_trip(args.round_trips)
    report['round_trip_ms'] = {'p50': 1e3 * statistics.median(rtt),
                               'p99': 1e3 * float(np.percentile(rtt, 99)), 'n': len(rtt)}

    with Graph(task=task_id(task), mode='lockstep') as graph:
        graph.wait_ready()
        with RosClient() as client:
            stats = EpisodeStats(client.node)
            time.sleep(0.5)
            rollout_wall = []
            for _ in range(args.rollouts):
                start = time.perf_counter()
                result = client.rollout(task_id(task), task.sample_tau(rng), theta)
                rollout_wall.append(time.perf_counter() - start)
                if not result.success:
                    raise RuntimeError(result.message)
            time.sleep(0.5)
    rates = [float(s['steps_per_second']) for s in stats.done]
    steps = task.num_steps
    report['lockstep'] = {
        'episodes': len(rates), 'steps_per_episode': steps,
        'steps_per_second_median': statistics.median(rates),
        'steps_per_second_min': min(rates),
        'rollout_wall_s_median': statistics.median(rollout_wall),
        'rollout_overhead_s_median': statistics.median(rollout_wall) - steps / statistics.median(rates),
    }
    step_ms = 1e3 / report['lockstep']['steps_per_second_median']
    report['lockstep']['step_ms'] = step_ms
    report['lockstep']['step_over_round_trip'] = step_ms / report['round_trip_ms']['p50']

    if args.realtime_seconds > 0:
        seconds = args.realtime_seconds
        graph = Graph(task=task_id(task), mode='realtime',
                      nodes=(('sim', 'psl_sim', 'sim'), ('pd_controller', 'psl_controller',
                                                         'pd_controller')),
                      extra_params={'sim': {'episode_duration': seconds}})
        with graph:
            with RosClient() as client:
                stats = EpisodeStats(client.node)
                if not client.reset_client.wait_for_service(timeout_sec=30):
                    raise RuntimeError('realtime simulator did not come up')
                deadline = time.monotonic() + 20
                while client.node.count_subscribers('joint_states') < 1:
                    if time.monotonic() > deadline:
                        raise RuntimeError('controller did not come up')
                    time.sleep(0.1)
                time.sleep(1.0)
                response = client.reset(task_id(task), task.tau_default)
                if not response.success:
                    raise RuntimeError(response.message)
                if not stats.event.wait(timeout=seconds * 1.5 + 30):
                    raise RuntimeError('the realtime episode did not end')
        done = stats.done[-1]
        misses, total = int(done['deadline_misses']), int(done['steps'])
        report['realtime'] = {'rate_hz': task.control_rate, 'seconds': seconds, 'steps': total,
                              'deadline_misses': misses, 'miss_fraction': misses / total,
                              'wall_time_s': float(done['wall_time_s'])}

    if args.json:
        print(json.dumps(report, indent=2))
    else:
        rt, ls = report['round_trip_ms'], report['lockstep']
        print(f"bare round trip (2 processes): p50 {rt['p50']:.3f} ms  p99 {rt['p99']:.3f} ms")
        print(f"lockstep: {ls['steps_per_second_median']:.0f} steps/s median "
              f"(min {ls['steps_per_second_min']:.0f}) = {ls['step_ms']:.3f} ms/step = "
              f"{ls['step_over_round_trip']:.2f} round trips; rollout wall "
              f"{ls['rollout_wall_s_median']:.2f} s for {ls['steps_per_episode']} steps")
        if 'realtime' in report:
            r = report['realtime']
            print(f"realtime {r['rate_hz']:.0f} Hz over {r['seconds']:.0f} s: "
                  f"{r['deadline_misses']} misses of {r['steps']} steps "
                  f"({100 * r['miss_fraction']:.2f} %)")
    return 0
