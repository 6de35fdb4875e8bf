"""``psl bench memories``: the associative memories AELM, ARBF, RBM and Hopfield on
the same learning data, completing ``v = [tau, theta]`` in both directions.

Data, per seed: the samples ``(tau_i, theta_i)`` that a bootstrap learning session of the task
added to its skill (`psl_optimizer.learning.Learner`, the memory file ``memory.npz`` of the
session folder ``OUT/<task>-bootstrap-seed<k>/``, as ``psl bench learn --out OUT`` leaves it).
A complete session found there is used as it is (its settings are recorded in the report);
a missing one is learned first with the default `LearnSettings` (minutes per seed).

Method, per seed and memory, leave-one-out: every ``stride``-th sample is held out in turn; a
fresh memory (seeded with the session's seed) is filled with the other samples one at a time,
in the session's order, each ``add`` timed; then the held-out pair is completed both ways (tau ->
theta with tau clamped, theta -> tau with theta clamped), each ``complete`` timed. The free
entries start at the centre of the ranges (``start='centre'``, as in the memories' tests) or at
the mean of the training samples (``start='mean'``); the ranges are widened by outliers, so the
two differ, and a memory with several attractors (the RBM) can end in another one. Every memory
gets the same ranges: fitted to the training samples of the fold (`RangeScaler.fit`, margin
0.1), since the skill's own theta range is much wider than the data (the samples of a session
spread over a few hundredths of it) and the Hopfield code would not resolve them. Modality
split ``(E, F)`` for all but the Hopfield network.

Error: normalised RMS, ``sqrt(mean((x_hat - x)^2 / sd^2))`` over the held-out pairs and the
entries of the completed modality, ``sd`` the entry's standard deviation over the session's
samples: 0 is perfect, about 1 is no better than answering the mean. Two references beside the
memories: the mean of the training samples (both directions) and the skill's own readout
``PS(tau)`` (tau -> theta only; the session's ranges and `SkillConfig`). Per memory the table
gives mean and sample standard deviation over seeds, the share of converged completions, the
median add and complete times (per seed, then averaged) and the slowest add. Plain Python, no
ROS.
"""
from __future__ import annotations

import os
import platform
import statistics
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from psl_bench.stats import over_seeds
from psl_memory.registry import ASSOCIATIVE_MEMORIES
from psl_memory.skill_config import SkillConfig
from psl_optimizer.metrics import METRICS_FILE, read_metrics
from psl_task import DEFAULT_TASK

MEMORIES = tuple(ASSOCIATIVE_MEMORIES)      # aelm, arbf, rbm, hopfield
REFERENCES = ('mean', 'readout')
MARGIN = 0.1                     # of RangeScaler.fit, the ranges every memory gets
STARTS = ('centre', 'mean')      # where the free entries of a completion start


def make_memory(kind: str, scaler, sizes: tuple[int, int], seed: int):
    """The memory `kind` as a skill of the default configuration with this seed builds it
    (`psl_memory.registry`), on the given ranges."""
    return ASSOCIATIVE_MEMORIES[kind].from_config(scaler, sizes,
                                                  SkillConfig(associative=kind, seed=seed))


def session_samples(task_name: str, seed: int, out: Path, num_tasks: int,
                    progress: Callable[[str], None] | None = None) -> dict:
    """The samples of the bootstrap session of `seed` in `out`, learned first if missing.

    Returns:
        ``{'folder', 'taus' (N, E), 'thetas' (N, F), 'skill', 'settings', 'generated'}``.

    Raises:
        ValueError: the folder holds an unfinished or non-bootstrap session.
    """
    from psl_bench.learn import run_folder
    from psl_memory.skill_memory import SkillMemory

    folder = run_folder(out, task_name, 'bootstrap', seed, None)
    generated = False
    if not (folder / METRICS_FILE).is_file():
        from psl_optimizer.learning import Learner, LearnSettings
        from psl_optimizer.rollout_modes import make_rollouts
        from psl_task.task import load_task
        if progress is not None:
            progress(f'seed {seed}: no session in {folder}, learning {num_tasks} tasks')
        task = load_task(task_name)
        Learner(task, LearnSettings(strategy='bootstrap', num_tasks=num_tasks, seed=seed),
                folder, make_rollouts('batch', task)).run()
        generated = True
    metrics = read_metrics(folder)
    if not metrics.complete or metrics.strategy != 'bootstrap':
        raise ValueError(f'{folder}: not a complete bootstrap session; remove it or give '
                         f'another --out')
    skill = SkillMemory.read(folder / 'memory.npz').get(task_name)
    if skill.num_samples < 3:
        raise ValueError(f'{folder}: {skill.num_samples} samples, need at least 3')
    return {'folder': str(folder), 'taus': skill.taus, 'thetas': skill.thetas, 'skill': skill,
            'settings': metrics.settings, 'generated': generated}


def _nrmse(errors: list[np.ndarray], sd: np.ndarray) -> float:
    e = np.array(errors) / sd                                       # (n_held_out, dims)
    return float(np.sqrt(np.mean(e**2)))


def evaluate_seed(samples: dict, seed: int, stride: int, kinds: Sequence[str],
                  start: str = 'centre') -> dict:
    """Leave-one-out completion errors and times of each memory (and the references) on one
    session's samples. See the module docstring."""
    from psl_memory.elm import RangeScaler
    from psl_memory.parameterized_skill import ParameterizedSkill

    taus, thetas = samples['taus'], samples['thetas']              # (N, E), (N, F)
    v_all = np.hstack([taus, thetas])                               # (N, D)
    n, e = taus.shape
    d = v_all.shape[1]
    tau_known = np.arange(d) < e
    sd = np.maximum(v_all.std(axis=0), 1e-12)                       # (D,)
    held_out = list(range(0, n, stride))
    result = {}
    for kind in kinds:
        theta_err, tau_err, adds, completes, converged = [], [], [], [], []
        for i in held_out:
            train = np.delete(v_all, i, axis=0)                     # (N - 1, D)
            scaler = RangeScaler.fit(train, margin=MARGIN)
            memory = make_memory(kind, scaler, (e, d - e), seed)
            for v in train:
                began = time.perf_counter()
                memory.add(v)
                adds.append(time.perf_counter() - began)
            guess = (scaler.from_unit(np.zeros(d)) if start == 'centre'
                     else train.mean(axis=0))                       # (D,)
            for known, errors, part in ((tau_known, theta_err, ~tau_known),
                                        (~tau_known, tau_err, tau_known)):
                began = time.perf_counter()
                r = memory.complete(np.where(known, v_all[i], guess), known)
                completes.append(time.perf_counter() - began)
                converged.append(r.converged)
                errors.append(r.pattern[part] - v_all[i, part])
        result[kind] = {'theta_nrmse': _nrmse(theta_err, sd[e:]),
                        'tau_nrmse': _nrmse(tau_err, sd[:e]),
                        'converged': float(np.mean(converged)),
                        'add_ms': 1e3 * statistics.median(adds),
                        'add_max_ms': 1e3 * max(adds),
                        'complete_ms': 1e3 * statistics.median(completes)}
    # references: the training mean, and the session's readout PS(tau) on the same folds
    skill = samples['skill']
    mean_theta, mean_tau, readout = [], [], []
    for i in held_out:
        train = np.delete(v_all, i, axis=0)
        mean_theta.append(train[:, e:].mean(axis=0) - thetas[i])
        mean_tau.append(train[:, :e].mean(axis=0) - taus[i])
        ps = ParameterizedSkill('ref', skill.tau_scaler, skill.theta_scaler, skill.config)
        for tau, theta in zip(np.delete(taus, i, axis=0), np.delete(thetas, i, axis=0)):
            ps.add(tau, theta)
        readout.append(ps.query(taus[i])[0] - thetas[i])
    result['mean'] = {'theta_nrmse': _nrmse(mean_theta, sd[e:]),
                      'tau_nrmse': _nrmse(mean_tau, sd[:e])}
    result['readout'] = {'theta_nrmse': _nrmse(readout, sd[e:]), 'tau_nrmse': None}
    return {'samples': n, 'tau_dim': e, 'theta_dim': d - e, 'held_out': held_out,
            'results': result}


def run(task_name: str = DEFAULT_TASK, seeds: Sequence[int] = (0, 1, 2, 3, 4),
        out: str | Path = 'runs/bench-learn', num_tasks: int = 30, stride: int = 3,
        memories: Sequence[str] = MEMORIES, start: str = 'centre',
        progress: Callable[[str], None] | None = None) -> dict:
    """Compare the associative memories on the sessions' samples (see the module docstring).

    Args:
        seeds: one bootstrap session per seed.
        out: folder of the session folders (shared with ``psl bench learn --out``).
        num_tasks: training tasks of a session learned here (existing ones are used as they
            are).
        stride: every stride-th sample is held out in turn (1: full leave-one-out).
        memories: the memories to compare (default all of `MEMORIES`).
        start: where the free entries start, one of `STARTS`.
        progress: called with one line of text per seed.

    Returns:
        JSON-able dict: ``settings``, ``seeds`` (per seed: sizes, held-out indices, session
        folder and settings, per memory and reference the numbers of `evaluate_seed`),
        ``summary`` (per memory and reference: each number's mean, sd, min, max over seeds).

    Raises:
        ValueError: bad settings or unusable session folders.
    """
    memories = tuple(memories)
    unknown = [m for m in memories if m not in MEMORIES]
    if unknown or not memories or len(set(memories)) != len(memories):
        raise ValueError(f'memories must be distinct names from {", ".join(MEMORIES)}; '
                         f'got {list(memories)}')
    if start not in STARTS:
        raise ValueError(f'start must be one of {", ".join(STARTS)}, got {start!r}')
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError('give at least one seed, each once')
    if stride < 1 or num_tasks < 3:
        raise ValueError(f'need stride >= 1 and num_tasks >= 3, got {stride}, {num_tasks}')
    per_seed = {}
    for seed in seeds:
        samples = session_samples(task_name, seed, Path(out), num_tasks, progress)
        started = time.perf_counter()
        record = evaluate_seed(samples, seed, stride, memories, start)
        record.update(folder=samples['folder'], session_settings=samples['settings'],
                      generated=samples['generated'])
        per_seed[str(seed)] = record
        if progress is not None:
            progress(f'seed {seed}: {record["samples"]} samples, {len(record["held_out"])} '
                     f'held out, {time.perf_counter() - started:.1f} s')
    summary = {}
    for name in memories + REFERENCES:
        rows = [per_seed[str(s)]['results'][name] for s in seeds]
        summary[name] = {key: over_seeds([r[key] for r in rows]) for key in rows[0]
                         if rows[0][key] is not None}
    settings = {'task': task_name, 'seeds': list(seeds), 'out': str(out), 'stride': stride,
                'memories': list(memories), 'start': start, 'margin': MARGIN,
                'numpy': np.__version__, 'python': platform.python_version(),
                'cpus': os.cpu_count(),
                'blas_threads_env': {k: os.environ[k] for k in ('OPENBLAS_NUM_THREADS',
                                                                'OMP_NUM_THREADS')
                                     if k in os.environ}}
    return {'settings': settings, 'seeds': per_seed, 'summary': summary}



LABELS = {'aelm': 'AELM (eq. 2.20-2.21)', 'arbf': 'ARBF (eq. 2.22)',
          'rbm': 'RBM, Gaussian-Bernoulli (eq. 2.17-2.19)',
          'hopfield': 'Hopfield, 16-bit thermometer (eq. 2.15-2.16)',
          'mean': 'reference: mean of the training samples',
          'readout': "reference: the skill's readout PS(tau)"}


def format_table(report: dict) -> str:
    """One markdown table: errors (mean +- sd over seeds), convergence and times."""
    s = report['settings']
    first = next(iter(report['seeds'].values()))
    lines = [f"{s['task']}, seeds {', '.join(map(str, s['seeds']))}: {first['samples']} "
             f"samples per session (E = {first['tau_dim']}, F = {first['theta_dim']}), "
             f"{len(first['held_out'])} held out per seed (stride {s['stride']}), free entries "
             f"start at the {s['start']}", '',
             '| memory | tau -> theta nRMSE | theta -> tau nRMSE | converged | add [ms] '
             '| complete [ms] |',
             '|---|---|---|---|---|---|']

    def cell(row: dict, key: str, fmt: str) -> str:
        if key not in row:
            return '-'
        return f"{row[key]['mean']:{fmt}} ± {row[key]['sd']:{fmt}}"

    for name, row in report['summary'].items():
        conv = f"{100 * row['converged']['mean']:.0f} %" if 'converged' in row else '-'
        add = (f"{row['add_ms']['mean']:.2f} (max {row['add_max_ms']['max']:.1f})"
               if 'add_ms' in row else '-')
        comp = f"{row['complete_ms']['mean']:.2f}" if 'complete_ms' in row else '-'
        lines.append(f"| {LABELS[name]} | {cell(row, 'theta_nrmse', '.2f')} | "
                     f"{cell(row, 'tau_nrmse', '.2f')} | {conv} | {add} | {comp} |")
    seeds = list(report['seeds'])
    lines += ['', 'nRMSE per seed, tau -> theta / theta -> tau:', '',
              '| memory | ' + ' | '.join(f'seed {k}' for k in seeds) + ' |',
              '|---|' + '---|' * len(seeds)]
    for name in report['summary']:
        cells = []
        for k in seeds:
            r = report['seeds'][k]['results'][name]
            tau = '-' if r['tau_nrmse'] is None else f"{r['tau_nrmse']:.2f}"
            cells.append(f"{r['theta_nrmse']:.2f} / {tau}")
        lines.append(f'| {name} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines) + '\n'
