"""``psl bench memory``: update and query time of the skill memory against N, and its service.

For every readout of the parameterized skill (eq. 2.5-2.14), and for the whole
`ParameterizedSkill.add` of the default configuration, the time of one further per-sample
update and of one query when N samples are stored already. The timings are plain Python (psl_memory
only); the service needs a graph.

Method, per readout and N:
- data: tau uniform in [-1, 1]^E, theta a fixed smooth function of tau plus small noise (so the
  Bayesian evidence maximisation sees realistic data), seeded;
- fill: the first N - 1 samples as ONE chunk (``update`` with ``h`` (N - 1, N_H)), which every
  readout accepts; RLS processes a chunk sample by sample, so its fill costs O(N N_H^2);
- update: `repeats` further single-sample updates (samples N, N + 1, ...), each timed alone;
  the median is reported (with the slowest beside it);
- query: ELM transform of one tau + ``predict`` + ``predict_variance`` (what
  `ParameterizedSkill.query` calls), timed `query_repeats` times, median.
The batch ridge readout refits from all N samples at every update (O(N N_H^2)); sizes above
`ridge_max_samples` are skipped and recorded as such.

`run` adds the query service's round trip to a skill_memory process (`measure_query_service`)
beside a bare DDS round trip of the same run (`psl_bench.round_trip`).

The skill row fills the readout and the associative memory of a default-configured skill through
their chunk interfaces (the skill itself takes one sample at a time, which would take minutes
at N = 10,000), then times the public `ParameterizedSkill.add` and `query`.
"""
from __future__ import annotations

import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

from psl_memory.elm import ELMFeatures, RangeScaler
from psl_memory.parameterized_skill import ParameterizedSkill, scaler_around
from psl_memory.registry import READOUTS
from psl_memory.skill_config import SkillConfig

SIZES = (10, 100, 1000, 10000)
# (label, SkillConfig overrides): every readout with the node's defaults, and the Bayesian one
# also with evidence maximisation, to show what the re-estimation costs per sample.
READOUT_VARIANTS = (
    ('ridge', {'readout': 'ridge'}),
    ('rls', {'readout': 'rls'}),
    ('incremental_ridge', {'readout': 'incremental_ridge'}),
    ('bayes (fixed precisions, the default)', {'readout': 'bayes'}),
    ('bayes, precisions estimated', {'readout': 'bayes', 'estimate_precisions': True}),
)
SKILL_LABEL = 'ParameterizedSkill.add (default: {readout} + {associative})'
NOISE_STD = 0.01          # of theta, for the evidence maximisation
# The BLAS thread count changes small-matrix timings a lot on 2 cores (thread hand-off to a busy
# core): it is fixed by these variables before numpy is imported, so the run records them.
BLAS_THREAD_VARIABLES = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS')


def measure_readouts(sizes=SIZES, n_hidden: int = 100, tau_dim: int = 2, theta_dim: int = 30,
                     repeats: int = 50, query_repeats: int = 500,
                     ridge_max_samples: int = 10000, seed: int = 0) -> dict:
    """Per-sample update and query time [ms] of each readout, and of the skill, against N.

    Args:
        sizes: numbers of stored samples N (each >= 1).
        n_hidden: hidden neurons N_H of the ELM.
        tau_dim: E, entries of tau.
        theta_dim: F, entries of theta.
        repeats: timed single updates per N (median reported).
        query_repeats: timed queries per N (median reported).
        ridge_max_samples: largest N measured for the batch ridge readout.
        seed: seed of the data and of the ELM.

    Returns:
        JSON-able dict: ``settings``, ``rows`` (one per readout variant and one for the skill),
        each row ``{'label', 'kind', 'points': [{'n', 'update_ms', 'update_max_ms',
        'query_ms'} or {'n', 'skipped': reason}]}``.

    Raises:
        ValueError: a size < 1, or repeats / query_repeats < 1.
    """
    sizes = tuple(int(n) for n in sizes)
    if not sizes or min(sizes) < 1:
        raise ValueError(f'sizes must be integers >= 1, got {sizes}')
    if repeats < 1 or query_repeats < 1:
        raise ValueError('repeats and query_repeats must be >= 1')
    data = _Data(max(sizes) + repeats, tau_dim, theta_dim, seed)
    features = ELMFeatures(RangeScaler(-np.ones(tau_dim), np.ones(tau_dim)), n_hidden, seed)
    hidden = features.transform(data.taus)                        # (n_max, N_H)
    rows = []
    for label, overrides in READOUT_VARIANTS:
        config = SkillConfig(n_hidden=n_hidden, seed=seed, **overrides)
        points = []
        for n in sizes:
            if config.readout == 'ridge' and n > ridge_max_samples:
                points.append({'n': n, 'skipped': f'N > ridge_max_samples = {ridge_max_samples}'})
                continue
            readout = READOUTS[config.readout].from_config(n_hidden, theta_dim, config)
            if n > 1:
                readout.update(hidden[:n - 1], data.targets[:n - 1])       # one chunk
            update = _timed(lambda i: readout.update(hidden[i], data.targets[i]),
                            range(n - 1, n - 1 + repeats))

            def query(i: int) -> None:
                h = features.transform(data.taus[i % len(data.taus)])
                readout.predict(h)
                readout.predict_variance(h)

            points.append(_point(n, update, _timed(query, range(query_repeats))))
        rows.append({'label': label, 'kind': 'readout', 'points': points})
    rows.append(_measure_skill(sizes, data, n_hidden, seed, repeats, query_repeats))
    settings = {'sizes': list(sizes), 'n_hidden': n_hidden, 'tau_dim': tau_dim,
                'theta_dim': theta_dim, 'repeats': repeats, 'query_repeats': query_repeats,
                'ridge_max_samples': ridge_max_samples, 'seed': seed,
                'numpy': np.__version__, 'python': platform.python_version(),
                'cpus': os.cpu_count(),
                'blas_threads_env': {k: os.environ[k] for k in BLAS_THREAD_VARIABLES
                                     if k in os.environ}}
    return {'settings': settings, 'rows': rows}


def format_table(result: dict) -> str:
    """Two plain-text tables (update, query) with one column per N."""
    s = result['settings']
    sizes = s['sizes']
    width = max(len(row['label']) for row in result['rows'])
    head = f'{"":{width}}' + ''.join(f'{f"N={n:,}":>12}' for n in sizes)
    threads = ', '.join(f'{k}={v}' for k, v in s['blas_threads_env'].items()) or 'default'
    lines = [f"skill memory, N_H = {s['n_hidden']}, tau {s['tau_dim']}-D, theta "
             f"{s['theta_dim']}-D; median of {s['repeats']} updates / {s['query_repeats']} "
             f'queries at each N [ms]; BLAS threads: {threads}']
    for title, key in (('per-sample update', 'update_ms'), ('query', 'query_ms')):
        lines += ['', title, head]
        for row in result['rows']:
            cells = []
            for point in row['points']:
                cells.append(f'{"skipped":>12}' if 'skipped' in point
                             else f'{point[key]:>12.3f}')
            lines.append(f'{row["label"]:{width}}' + ''.join(cells))
    skipped = {p['skipped'] for row in result['rows'] for p in row['points'] if 'skipped' in p}
    lines += [''] + [f'skipped: {reason}' for reason in sorted(skipped)]
    return '\n'.join(lines).rstrip() + '\n'


# -- helpers ------------------------------------------------------------------------------------
class _Data:
    """Seeded samples: taus (n, E) in [-1, 1], targets (n, F) in normalised units, thetas."""

    def __init__(self, n: int, tau_dim: int, theta_dim: int, seed: int):
        rng = np.random.default_rng(seed)
        self.taus = rng.uniform(-1.0, 1.0, size=(n, tau_dim))                     # (n, E)
        basis = np.column_stack([np.ones(n), np.sin(2.0 * self.taus), self.taus**2,
                                 np.tanh(3.0 * self.taus)])                         # (n, 1+3E)
        mix = rng.normal(size=(basis.shape[1], theta_dim)) / np.sqrt(basis.shape[1])
        self.thetas = basis @ mix + rng.normal(0.0, NOISE_STD, size=(n, theta_dim))   # (n, F)
        self.theta_scaler = scaler_around(np.zeros(theta_dim))          # spread 1: theta = unit
        self.targets = self.theta_scaler.to_unit(self.thetas)                     # (n, F)


def _timed(call: Callable[[int], object], indices) -> list[float]:
    """Wall time [s] of call(i) for each i, one measurement per call."""
    times = []
    for i in indices:
        start = time.perf_counter()
        call(i)
        times.append(time.perf_counter() - start)
    return times


def _point(n: int, update: list[float], query: list[float]) -> dict:
    return {'n': n, 'update_ms': 1e3 * statistics.median(update),
            'update_max_ms': 1e3 * max(update), 'query_ms': 1e3 * statistics.median(query)}


def _measure_skill(sizes, data: _Data, n_hidden: int, seed: int, repeats: int,
                   query_repeats: int) -> dict:
    """The full ParameterizedSkill.add (readout + associative memory + sample store)."""
    config = SkillConfig(n_hidden=n_hidden, seed=seed)
    tau_dim = data.taus.shape[1]
    points = []
    for n in sizes:
        skill = ParameterizedSkill('bench', RangeScaler(-np.ones(tau_dim), np.ones(tau_dim)),
                                   data.theta_scaler, config)
        if n > 1:
            # fill through the components' chunk interfaces, as add would one by one
            taus, thetas = data.taus[:n - 1], data.thetas[:n - 1]
            skill.readout.update(skill.features.transform(taus),
                                 skill.theta_scaler.to_unit(thetas))
            skill.associative.add(np.hstack([taus, thetas]))
            skill._taus, skill._thetas = list(taus), list(thetas)
        update = _timed(lambda i: skill.add(data.taus[i], data.thetas[i]),
                        range(n - 1, n - 1 + repeats))
        query = _timed(lambda i: skill.query(data.taus[i % len(data.taus)]),
                       range(query_repeats))
        points.append(_point(n, update, query))
    label = SKILL_LABEL.format(readout=config.readout, associative=config.associative)
    return {'label': label, 'kind': 'skill', 'points': points}


def measure_query_service(n_samples: int, n_calls: int) -> list[float]:
    """Round-trip times [s] of QuerySkill calls to a skill_memory process holding a skill
    with n_samples samples (restored from a memory file at start)."""
    from psl_memory.skill_memory import SkillMemory
    from psl_ros.client import RosClient
    from psl_ros.graph import Graph

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
                      extra_params={'skill_memory': {'autosave_path': str(path),
                                                     'memory_dir': folder}})
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


def run(sizes=SIZES, n_hidden: int = 100, service_samples: int = 1000,
        round_trips: int = 1000) -> dict:
    """The readout timings and the query service beside a bare round trip."""
    from psl_bench.round_trip import measure_round_trip

    report = {'readouts': measure_readouts(sizes=tuple(sizes), n_hidden=n_hidden)}
    service = measure_query_service(service_samples, round_trips)
    bare = measure_round_trip(round_trips)
    report['service'] = {
        'samples': service_samples,
        'query_ms': {'p50': 1e3 * statistics.median(service),
                     'p99': 1e3 * float(np.percentile(service, 99))},
        'bare_round_trip_ms': {'p50': 1e3 * statistics.median(bare),
                               'p99': 1e3 * float(np.percentile(bare, 99))}}
    return report


def format_report(report: dict) -> str:
    q, b = report['service']['query_ms'], report['service']['bare_round_trip_ms']
    return (format_table(report['readouts'])
            + f"query service round trip with {report['service']['samples']} samples: p50 "
              f"{q['p50']:.3f} ms, p99 {q['p99']:.3f} ms (bare DDS round trip in the same run: "
              f"p50 {b['p50']:.3f} ms, p99 {b['p99']:.3f} ms)\n")
