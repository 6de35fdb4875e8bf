"""``psl bench memory-load``: many clients at once on the skill memory; no answer may be lost.

A skill_memory process (under its own namespace, so no other memory of the domain answers)
holds one skill; `clients` processes send `calls` queries each and
`adders` processes send `calls // 5` samples each, all at once and each new to the server.
Every call waits at most `timeout` s; one without an answer by then counts as lost. Reported:
lost answers per kind, the answer times (p50, p99) and whether every added sample arrived.
"""
from __future__ import annotations

import multiprocessing
import statistics
import tempfile

import numpy as np

SKILL = 'load'


NAMESPACE = 'memory_load'


def client_process(index: int, calls: int, kind: str, timeout: float, results,
                   namespace: str = NAMESPACE) -> None:
    """One client (its own process and participant): `calls` queries or adds; puts
    (kind, lost, times) on `results`."""
    import time

    from psl_ros.client import RosClient

    lost, times = 0, []
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
            except TimeoutError:
                lost += 1
    results.put((kind, lost, times))


def measure(clients: int = 8, adders: int = 2, calls: int = 1000,
            timeout: float = 10.0) -> dict:
    """Run the load against a fresh skill_memory process (see the module docstring).

    Raises:
        ValueError: fewer than one client or call; RuntimeError: the memory did not answer.
    """
    from psl_ros.client import RosClient
    from psl_ros.graph import Graph

    if clients < 1 or calls < 1 or adders < 0:
        raise ValueError('need clients >= 1, calls >= 1 and adders >= 0')
    adds = max(1, calls // 5)
    with tempfile.TemporaryDirectory(prefix='psl-bench-load-') as logs:
        graph = Graph(nodes=(('skill_memory', 'psl_memory', 'skill_memory'),), log_dir=logs,
                      namespace=NAMESPACE)
        with graph, RosClient(NAMESPACE) as probe:
            first = probe.memory('add_sample', timeout=30, skill=SKILL, tau=[0.0, 0.0],
                                 theta=[1.0, 2.0, 3.0])
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
            for job in jobs:
                job.start()
            try:
                done = [results.get(timeout=timeout * (calls + 10) + 60) for _ in jobs]
            finally:
                for job in jobs:
                    job.join(timeout=30)
                    if job.is_alive():
                        job.kill()
            import json
            held = json.loads(probe.memory('info', timeout=30).message)[SKILL]['num_samples']
    report = {'clients': clients, 'adders': adders, 'calls': calls, 'adds_per_adder': adds,
              'timeout_s': timeout, 'samples_expected': 1 + adders * adds,
              'samples_held': held}
    for kind in ('query', 'add'):
        rows = [r for r in done if r[0] == kind]
        times = [t for r in rows for t in r[2]]
        report[kind] = {'calls': sum(len(r[2]) + r[1] for r in rows),
                        'lost': sum(r[1] for r in rows),
                        'p50_ms': 1e3 * statistics.median(times) if times else None,
                        'p99_ms': 1e3 * float(np.percentile(times, 99)) if times else None}
    return report


def format_report(report: dict) -> str:
    q, a = report['query'], report['add']

    def ms(value):
        return '-' if value is None else f'{value:.2f}'
    return (f"{report['clients']} querying and {report['adders']} adding clients at once: "
            f"queries {q['calls']}, lost {q['lost']}, p50 {ms(q['p50_ms'])} ms, p99 "
            f"{ms(q['p99_ms'])} ms; adds {a['calls']}, lost {a['lost']}, p50 {ms(a['p50_ms'])}"
            f" ms, p99 {ms(a['p99_ms'])} ms; samples held {report['samples_held']} of "
            f"{report['samples_expected']}\n")
