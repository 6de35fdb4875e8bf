"""``psl bench memory-load``: many clients at once on the skill memory; no answer may be lost.

A skill_memory process (under its own namespace, so no other memory of the domain answers)
holds one skill of `samples` samples; `clients` processes send `calls` queries each and
`adders` processes send `calls // 5` samples each, all at once and each new to the server,
while `busy` other processes keep a core busy each (`psl_bench.busy_cores`). Every call waits
at most `timeout` s; one that was sent and got no answer by then counts as lost (one that found
no server in that time counts apart, as unavailable). Reported: lost answers per kind, the
answer times (p50, p99) per kind, the worst client's p99, the slowest answers (a client's first
call also waits for discovery), whether every added sample arrived, the client processes' CPU
time, and what the server's log says about its answers (answers sent late to a client it had
not matched yet, answers given up: `psl_ros.service`).

Where answers went (docs/benchmarks.md has the runs): a client process starved for a few
seconds fell more than `psl_ros.qos.SERVICES.depth` answers (to the other clients) behind and
lost its own from its reader's history; a client the server matched late had its answer given
up after 2 s while every other client waited. Requests were never lost.

Fast DDS 2.14 can hang a process in the destruction of its participant (a livelock in
``set_listener``, a deadlock between the event thread and discovery) while others leave: a
client puts its results before it closes, and one still running `EXIT_PATIENCE` s after the
load is killed and counted (``clients_killed_at_exit``).
"""
from __future__ import annotations

import json
import multiprocessing
import queue
import re
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

SKILL = 'load'


NAMESPACE = 'memory_load'
EXIT_PATIENCE = 30.0    # s the client processes have to end after their last call
# what the server's log says about its answers (psl_ros.service), counted in the report
SERVER_LOG = {'answers_resent': 'answered a new client after',
              'answers_given_up': 'its answer is lost'}


def client_process(index: int, calls: int, kind: str, timeout: float, results,
                   namespace: str = NAMESPACE) -> None:
    """One client (its own process and participant): `calls` queries or adds; puts
    (kind, lost, times, index, lost_calls, unavailable, cpu_s) on `results` (lost_calls: the
    numbers of the calls that were sent and got no answer; unavailable: calls that found no
    server within `timeout`; cpu_s: the process's CPU time)."""
    import resource

    from psl_ros.client import RosClient

    lost, times, lost_calls, unavailable = 0, [], [], []
    with RosClient(namespace, name=f'load{index}') as client:
        for i in range(calls):
            start = time.perf_counter()
            try:
                if kind == 'add':
                    client.memory('add_sample', timeout=timeout, skill=SKILL,
                                  tau=[float(index), float(i)], theta=[1.0, 2.0, float(i)])
                else:
                    client.memory('query', timeout=timeout, skill=SKILL, tau=[0.5, 0.5])
                times.append(time.perf_counter() - start)
            except TimeoutError as exc:
                lost += 1
                (unavailable if 'not available' in str(exc) else lost_calls).append(i)
        # sent before the client is closed: Fast DDS 2.14 can spin for minutes, holding the
        # GIL, in the participant's destruction (set_listener) while other participants leave
        # (seen 4 times in about 1,000 client exits here); `measure` ends such a process
        usage = resource.getrusage(resource.RUSAGE_SELF)
        results.put((kind, lost, times, index, lost_calls, unavailable,
                     usage.ru_utime + usage.ru_stime))
        results.close()
        results.join_thread()


def _answered(times, failed) -> list[int]:
    """The numbers of the calls that were answered (`times` holds their times in order)."""
    lost = set(failed)
    return [i for i in range(len(times) + len(lost)) if i not in lost]


def _p99(times) -> float | None:
    return 1e3 * float(np.percentile(times, 99)) if times else None


def _server_log(path: Path) -> dict:
    """SERVER_LOG's counts in the node's log."""
    try:
        text = path.read_text(errors='replace')
    except OSError:
        return {}
    return {name: len(re.findall(re.escape(pattern), text))
            for name, pattern in SERVER_LOG.items()}


def measure(clients: int = 8, adders: int = 2, calls: int = 1000,
            timeout: float = 10.0, busy: int = 0, samples: int = 1,
            log_dir: str | Path | None = None) -> dict:
    """Run the load against a fresh skill_memory process (see the module docstring); the
    node's log goes to `log_dir` (default: a temporary folder, removed).

    Raises:
        ValueError: fewer than one client, call or sample; RuntimeError: the memory did not
        answer.
    """
    from psl_bench.busy_cores import busy_cores
    from psl_ros.client import RosClient
    from psl_ros.graph import Graph

    if clients < 1 or calls < 1 or adders < 0 or samples < 1 or busy < 0 or timeout <= 0:
        raise ValueError('need clients >= 1, calls >= 1, adders >= 0, samples >= 1, '
                         'busy >= 0 and timeout > 0')
    adds = max(1, calls // 5)
    with tempfile.TemporaryDirectory(prefix='psl-bench-load-') as scratch:
        logs = Path(log_dir) if log_dir else Path(scratch)
        graph = Graph(nodes=(('skill_memory', 'psl_memory', 'skill_memory'),), log_dir=logs,
                      namespace=NAMESPACE)
        with busy_cores(busy), graph, RosClient(NAMESPACE) as probe:
            rng = np.random.default_rng(0)
            for k in range(samples):     # the skill, filled before the load starts
                first = probe.memory('add_sample', timeout=60, skill=SKILL,
                                     tau=[float(x) for x in rng.uniform(-1, 1, 2)],
                                     theta=[1.0, 2.0, float(k)])
                if not first.success:
                    raise RuntimeError(first.message)
            spawn = multiprocessing.get_context('spawn')     # rclpy does not survive a fork
            results = spawn.Queue()
            jobs = [spawn.Process(target=client_process, args=(k, calls, 'query', timeout,
                                                               results))
                    for k in range(clients)]
            jobs += [spawn.Process(target=client_process, args=(1000 + k, adds, 'add',
                                                                timeout, results))
                     for k in range(adders)]
            start = time.monotonic()
            for job in jobs:
                job.start()
            hung = 0
            try:
                done = [results.get(timeout=timeout * (calls + 10) + 60) for _ in jobs]
                load_s = time.monotonic() - start
            except queue.Empty:
                raise RuntimeError('a client process did not report (it died or hung)') from None
            finally:
                deadline = time.monotonic() + EXIT_PATIENCE
                for job in jobs:
                    job.join(timeout=max(0.0, deadline - time.monotonic()))
                    if job.is_alive():
                        hung += 1
                        job.kill()
                        job.join()
            held = json.loads(probe.memory('info', timeout=30).message)[SKILL]['num_samples']
        server = _server_log(graph.processes[0].log_path)
    report = {'clients': clients, 'adders': adders, 'calls': calls, 'adds_per_adder': adds,
              'timeout_s': timeout, 'busy_cores': busy, 'samples_before': samples,
              'samples_expected': samples + adders * adds, 'samples_held': held,
              'server_log': server, 'clients_killed_at_exit': hung,
              # from the start of the client processes to the last report (their start-up
              # included): a lower bound of the answers per second
              'load_s': load_s, 'calls_per_s': sum(len(r[2]) for r in done) / load_s}
    worst = None
    for kind in ('query', 'add'):
        rows = [r for r in done if r[0] == kind]
        times = [t for r in rows for t in r[2]]
        per_client = [(_p99(r[2]), r[3]) for r in rows if r[2]]
        report[kind] = {'calls': sum(len(r[2]) + r[1] for r in rows),
                        'lost': sum(len(r[4]) for r in rows),
                        'lost_calls': {str(r[3]): r[4] for r in rows if r[4]},
                        'unavailable': sum(len(r[5]) for r in rows),
                        'client_cpu_s': statistics.mean(r[6] for r in rows) if rows else None,
                        'p50_ms': 1e3 * statistics.median(times) if times else None,
                        'p99_ms': _p99(times),
                        'worst_client_p99_ms': max(per_client)[0] if per_client else None}
        if per_client and (worst is None or max(per_client)[0] > worst):
            worst = max(per_client)[0]
    report['worst_client_p99_ms'] = worst
    # the slowest answers: [ms, kind, client, call number] (the first call of a client also
    # waits for the server to be discovered)
    report['slowest'] = sorted(([round(1e3 * t, 1), r[0], r[3], i] for r in done
                                for i, t in zip(_answered(r[2], r[4] + r[5]), r[2])),
                               reverse=True)[:8]
    report['lost'] = report['query']['lost'] + report['add']['lost']
    report['unavailable'] = report['query']['unavailable'] + report['add']['unavailable']
    return report


def format_report(report: dict) -> str:
    q, a = report['query'], report['add']

    def ms(value):
        return '-' if value is None else f'{value:.2f}'
    log, busy = report.get('server_log', {}), report.get('busy_cores', 0)
    return (f"{report['clients']} querying and {report['adders']} adding clients at once "
            f"({busy} core{'' if busy == 1 else 's'} kept busy, {report.get('samples_before', 1)}"
            f" samples, timeout {report['timeout_s']:g} s): lost {report['lost']} of "
            f"{q['calls'] + a['calls']}"
            + (f", {report['unavailable']} found no server in time" if report.get('unavailable')
               else '') + "\n"
            f"  queries {q['calls']}, lost {q['lost']}, p50 {ms(q['p50_ms'])} ms, p99 "
            f"{ms(q['p99_ms'])} ms, worst client p99 {ms(q['worst_client_p99_ms'])} ms\n"
            f"  adds {a['calls']}, lost {a['lost']}, p50 {ms(a['p50_ms'])} ms, p99 "
            f"{ms(a['p99_ms'])} ms, worst client p99 {ms(a['worst_client_p99_ms'])} ms\n"
            f"  samples held {report['samples_held']} of {report['samples_expected']}; server: "
            f"{log.get('answers_resent', 0)} answers sent again to a client not matched yet, "
            f"{log.get('answers_given_up', 0)} given up; {report.get('calls_per_s', 0):.0f} "
            "calls/s (client start-up included)\n")
