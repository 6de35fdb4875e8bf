"""``psl bench graph``: the robot loop through the real node graph.

Lockstep control steps per second (the simulator's own end-of-episode figures on
/diagnostics, with the medians of its step phases) beside the bare publish/answer round trip
between two processes measured in the same run, in chunks between the rollouts
(`psl_bench.round_trip`), and the deadline misses of psl's standard robot on the wall clock
(its trajectory controller in its own loop: what a robot's real-time loop does). With ``view`` the lockstep rollouts run beside the
view node (`psl_ros.foxglove_view`): idle (no viewer) or watched (a viewer of the Foxglove
protocol subscribed to every channel, in this process), with the view's CPU share.
"""
from __future__ import annotations

import os
import statistics
import threading
import time

import numpy as np

from psl_bench.round_trip import RoundTrip
from psl_ros import names
from psl_task import DEFAULT_TASK


class EpisodeStats:
    """Collects the simulators' end-of-episode status from /diagnostics."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        self.done: list[dict] = []
        self.event = threading.Event()
        node.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self._on, 100)

    def _on(self, msg) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if 'steps_done' in values and values['steps_done'] == values['steps']:
                self.done.append(values)
                self.event.set()


VIEW_MODES = ('off', 'idle', 'watched')


class Viewer:
    """A Foxglove viewer subscribed to the channels of psl's layout (`psl_ros.foxglove_layout`:
    the scene, the joints measured and referenced, the task instance, the learning curve),
    receiving in a thread."""

    def __init__(self, url: str, topics: list[str]):
        from psl_bench.foxglove_client import FoxgloveClient

        self.client = FoxgloveClient(url)
        if not self.client.wait_channels(topics, 30.0):
            raise RuntimeError(f'the view offered {sorted(self.client.channels)}, not {topics}')
        self.client.subscribe(topics)
        self.stop, self.dropped = threading.Event(), ''
        self.thread = threading.Thread(target=self._receive)
        self.thread.start()

    def _receive(self) -> None:
        try:
            self.client.pump(until=self.stop.is_set, timeout=1e9)
        except ConnectionError as exc:      # the server dropped this viewer
            self.dropped = str(exc)

    def close(self) -> dict:
        """Stop; the messages received per topic (and why the server dropped the viewer)."""
        self.stop.set()
        self.thread.join()
        self.client.close()
        received = {topic: len(messages) for topic, messages in self.client.messages.items()}
        return {**received, **({'dropped': self.dropped} if self.dropped else {})}


def measure(task_name: str = DEFAULT_TASK, rollouts: int = 10,
            round_trips: int = 2000, realtime_seconds: float = 60.0, busy: int = 0,
            view: str = 'off') -> dict:
    """Round trip, lockstep and (realtime_seconds > 0) realtime figures of one run.

    Raises:
        RuntimeError: a graph did not come up or a rollout failed.
    """
    from psl_controller.policy import policy_for
    from psl_ros.client import RosClient
    from psl_ros.graph import Graph
    from psl_task.task import load_task, task_id

    if view not in VIEW_MODES:
        raise ValueError(f'view must be one of {", ".join(VIEW_MODES)}, got {view!r}')
    task = load_task(task_name)
    theta = policy_for(task).default_theta
    rng = np.random.default_rng(0)
    report: dict = {'task': task.name, 'machine_cores': os.cpu_count(), 'view': view}

    # the anchor in chunks between the rollouts, so that a drifting machine moves both alike
    chunk = max(1, round_trips // max(1, rollouts))
    rtt, chunk_medians = [], []
    viewer = None
    with Graph(task=task_id(task), mode='lockstep',
               view_port=None if view == 'off' else 0) as graph, RoundTrip() as round_trip:
        graph.wait_ready()
        if view == 'watched':
            viewer = Viewer(graph.view_url(), ['/' + t for t in (
                names.SCENE, names.JOINT_STATES, names.PSL_CONTROLLER_STATE, names.TASK_INSTANCE,
                names.LEARNING_PROGRESS)])
        viewed = next((p for p in graph.processes if p.name == 'view'), None)
        with RosClient() as client:
            stats = EpisodeStats(client.node)
            time.sleep(0.5)
            cpu_before = None if viewed is None else _cpu_seconds(viewed.pid)
            wall_before = time.perf_counter()
            rollout_wall = []
            for _ in range(rollouts):
                times = round_trip.measure(chunk)
                rtt += times
                chunk_medians.append(statistics.median(times))
                start = time.perf_counter()
                result = client.rollout(task_id(task), task.sample_tau(rng), theta)
                rollout_wall.append(time.perf_counter() - start)
                if not result.success:
                    raise RuntimeError(result.message)
            if viewed is not None:
                report['view_cpu_share'] = ((_cpu_seconds(viewed.pid) - cpu_before)
                                            / (time.perf_counter() - wall_before))
            time.sleep(0.5)
        if viewer is not None:
            report['viewer_messages'] = viewer.close()
    report['round_trip_ms'] = {'p50': 1e3 * statistics.median(rtt),
                               'p99': 1e3 * float(np.percentile(rtt, 99)), 'n': len(rtt)}
    rates = [float(s['steps_per_second']) for s in stats.done]
    steps = task.num_steps
    report['lockstep'] = {
        'episodes': len(rates), 'steps_per_episode': steps,
        'steps_per_second_median': statistics.median(rates),
        'steps_per_second_min': min(rates),
        'rollout_wall_s_median': statistics.median(rollout_wall),
        'rollout_overhead_s_median': (statistics.median(rollout_wall)
                                      - steps / statistics.median(rates)),
    }
    # where a step goes, the simulator's medians (`psl_ros.step_timing`), median over episodes
    phases = sorted({k for s in stats.done for k in s if k.startswith('step_')})
    report['lockstep']['phases_us'] = {
        k[len('step_'):-len('_us')]: statistics.median(float(s[k]) for s in stats.done if k in s)
        for k in phases}
    step_ms = 1e3 / report['lockstep']['steps_per_second_median']
    report['lockstep']['step_ms'] = step_ms
    report['lockstep']['step_over_round_trip'] = step_ms / report['round_trip_ms']['p50']
    report['lockstep']['ceiling_ratio'] = report['round_trip_ms']['p50'] / step_ms
    # each episode against the round trips measured just before it (when every episode's
    # report arrived; otherwise the ratio of the medians)
    report['lockstep']['ceiling_ratio_paired_median'] = (
        statistics.median(rt * rate for rt, rate in zip(chunk_medians, rates))
        if len(rates) == len(chunk_medians) else report['lockstep']['ceiling_ratio'])
    if realtime_seconds > 0:
        report['realtime'] = _realtime(task, realtime_seconds, busy)
    return report


class LoopReports:
    """The standard robot's reports of its loop's timing from /diagnostics."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        self.reports: list[dict] = []
        self.event = threading.Event()
        node.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self._on, 100)

    def _on(self, msg) -> None:
        for status in msg.status:
            if status.name.endswith('standard_robot: loop'):
                self.reports.append({kv.key: kv.value for kv in status.values})
                self.event.set()

    def wait(self, count: int, timeout: float) -> dict:
        """The `count`-th report from now (RuntimeError if none comes within `timeout` s)."""
        want = len(self.reports) + count
        deadline = time.monotonic() + timeout
        while len(self.reports) < want:
            self.event.clear()
            if not self.event.wait(max(0.0, deadline - time.monotonic())):
                raise RuntimeError('the standard robot reported no loop timing')
        return self.reports[want - 1]


def _realtime(task, seconds: float, busy: int = 0) -> dict:
    """psl's standard robot (the task's model as a ros2_control robot: its trajectory
    controller inside its loop, stepped with the physics) on the wall clock for `seconds`,
    holding its posture, with `busy` cores kept busy: its loop's deadline misses (a step that
    ends after its control period), the lateness of the steps (p99 and max of its reports)
    and the CPU it used per second."""
    from psl_bench.busy_cores import busy_cores
    from psl_ros.client import RosClient
    from psl_ros.graph import STANDARD_ROBOT, Graph
    from psl_task.task import task_id

    graph = Graph(task=task_id(task), robot='standard', nodes=(STANDARD_ROBOT,))
    with graph, RosClient() as client:
        reports = LoopReports(client.node)
        reports.wait(2, 30.0)           # running (and the first report's start-up behind)
        with busy_cores(busy):
            first = reports.wait(1, 10.0)
            cpu_before = {p.name: _cpu_seconds(p.pid) for p in graph.processes}
            wall_before = time.perf_counter()
            late = []
            for _ in range(max(1, round(seconds))):
                late.append(reports.wait(1, 10.0))
            wall = time.perf_counter() - wall_before
            cpu = {p.name: _cpu_seconds(p.pid) - cpu_before[p.name] for p in graph.processes}
    last = late[-1]
    periods = int(last['periods']) - int(first['periods'])
    misses = int(last['deadline_misses']) - int(first['deadline_misses'])
    return {'rate_hz': task.control_rate, 'seconds': wall, 'steps': periods,
            'deadline_misses': misses, 'miss_fraction': misses / max(1, periods),
            'skipped': int(last['skipped']) - int(first['skipped']),
            'late_p99_us_max': max(float(r['late_p99_us']) for r in late),
            'late_max_us': max(float(r['late_max_us']) for r in late),
            'busy_cores': busy, 'cpu_share': {name: value / wall for name, value in cpu.items()}}


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time [s] of a process so far (/proc/PID/stat)."""
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def format_report(report: dict) -> str:
    rt, ls = report['round_trip_ms'], report['lockstep']
    lines = [f"bare round trip (2 processes): p50 {rt['p50']:.3f} ms  p99 {rt['p99']:.3f} ms",
             f"lockstep: {ls['steps_per_second_median']:.0f} steps/s median "
             f"(min {ls['steps_per_second_min']:.0f}) = {ls['step_ms']:.3f} ms/step = "
             f"{ls['step_over_round_trip']:.2f} round trips (ratio to the one-round-trip ceiling "
             f"{ls['ceiling_ratio']:.2f}, paired median {ls['ceiling_ratio_paired_median']:.2f}); "
             "rollout wall "
             f"{ls['rollout_wall_s_median']:.2f} s for {ls['steps_per_episode']} steps"]
    if report.get('view', 'off') != 'off':
        lines.append(f"  with the view {report['view']}: view node CPU "
                     f"{100 * report.get('view_cpu_share', float('nan')):.0f} % of a core"
                     + ('' if 'viewer_messages' not in report else '; the viewer received '
                        + ', '.join(f'{t} {n}' for t, n in report['viewer_messages'].items())))
    if ls.get('phases_us'):
        lines.append('  per step (simulator, median us): ' + ', '.join(
            f'{phase} {us:.0f}' for phase, us in ls['phases_us'].items()))
    if 'realtime' in report:
        r = report['realtime']
        cpu = ', '.join(f'{name} {100 * share:.0f} %' for name, share in
                        r.get('cpu_share', {}).items())
        lines.append(f"standard robot on the wall clock, {r['rate_hz']:.0f} Hz over "
                     f"{r['seconds']:.0f} s, {r.get('busy_cores', 0)} cores kept busy: "
                     f"{r['deadline_misses']} deadline misses of {r['steps']} periods "
                     f"({100 * r['miss_fraction']:.3f} %), {r['skipped']} skipped, step "
                     "lateness p99 "
                     f"{r['late_p99_us_max']:.0f} us (worst second), max "
                     f"{r['late_max_us']:.0f} us; CPU of a core: {cpu}")
    return '\n'.join(lines) + '\n'
