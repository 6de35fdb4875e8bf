"""``psl bench workers``: one graph-mode learning session over 1, 2, ... rollout workers.

Per worker count N a fresh graph (`psl_ros.graph.Graph` with ``workers=N``: N rollout loops
under ``worker0..N-1``, one skill memory and one learner, all lockstep) runs the same
learning session through the learner node (``learn_skill`` goal, ``mode='graph'``): the learner
spreads each CMA-ES population over the workers, one rollout per worker at a time. The wall
time is the goal's, from sending it to its result (the graph is up and ready before); the
training and held-out rollouts and the zero-shot result come from the session's metrics.json
(`psl_optimizer.metrics.read_metrics`). Lockstep rollouts do not depend on the worker, so the
sessions must be the same (rollouts, fulfilled flags and task instances exactly; rewards to
`REWARD_TOLERANCE`); the report says whether they are and, if not, where they differ.

Every graph gets a fresh skill memory, so each session starts from the same empty skill. The
graphs run on the current ``ROS_DOMAIN_ID``: nothing else may serve ``learn_skill`` there.
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Callable, Sequence

from psl_task import DEFAULT_TASK

REWARD_TOLERANCE = 1e-9     # between two sessions' rewards (graph mode vs graph mode)


def session_differences(a, b) -> list[str]:
    """Where two sessions' `Metrics` differ (tasks and held-out test; wall times ignored):
    one line per difference, empty when they are the same."""
    out = []
    if len(a.tasks) != len(b.tasks):
        out.append(f'{len(a.tasks)} vs {len(b.tasks)} training tasks')
    for x, y in zip(a.tasks, b.tasks):
        for field in ('tau', 'rollouts', 'fulfilled'):
            if getattr(x, field) != getattr(y, field):
                out.append(f'task {x.index}: {field} {getattr(x, field)} vs {getattr(y, field)}')
        for field in ('best_reward', 'start_reward'):
            if abs(getattr(x, field) - getattr(y, field)) > REWARD_TOLERANCE:
                out.append(f'task {x.index}: {field} {getattr(x, field)!r} vs '
                           f'{getattr(y, field)!r}')
    sa, sb = a.summary, b.summary
    if sa is None or sb is None:
        out.append('a session has no summary (not complete)')
        return out
    if sa.test_taus != sb.test_taus:
        out.append('different held-out instances')
    if len(sa.test_rewards) != len(sb.test_rewards) or any(
            abs(ra - rb) > REWARD_TOLERANCE for ra, rb in zip(sa.test_rewards, sb.test_rewards)):
        out.append(f'held-out rewards {sa.test_rewards} vs {sb.test_rewards}')
    return out


def _session(workers: int, task_name: str, strategy: str, tasks: int, budget: int, seed: int,
             out: Path, log_dir: Path) -> dict:
    """Start a graph of `workers` loops, run the session, end the graph; its numbers."""
    from psl_optimizer.metrics import read_metrics
    from psl_ros.client import RosClient
    from psl_ros.graph import Graph
    from psl_task.task import load_task, task_id

    task = load_task(task_name)
    # the session's folder inside the memory node's: it writes the session's memory there
    graph = Graph(task=task_id(task), workers=workers, log_dir=log_dir,
                  extra_params={'skill_memory': {'memory_dir': str(out.parent)}})
    with graph:
        graph.wait_ready(timeout=90)
        with RosClient() as client:
            start = time.perf_counter()
            result = client.learn(task=task_id(task), strategy=strategy, num_tasks=tasks,
                                  max_rollouts_per_task=budget, seed=seed, mode='graph',
                                  output_dir=str(out))
            seconds = time.perf_counter() - start
    if not result.success:
        raise RuntimeError(f'the session with {workers} worker(s) failed: {result.message} '
                           f'(logs in {log_dir})')
    metrics = read_metrics(Path(result.metrics_path).parent)
    s = metrics.summary
    return {'workers': workers, 'seconds': seconds, 'training_rollouts': s.total_rollouts,
            'test_rollouts': len(s.test_rewards), 'fulfilled_tasks': s.fulfilled_tasks,
            'zero_shot_success': s.zero_shot_success_rate, 'metrics': metrics}


def measure(task_name: str = DEFAULT_TASK, workers: Sequence[int] = (1, 2),
            strategy: str = 'scratch', tasks: int = 3, budget: int = 22, seed: int = 5,
            progress: Callable[[str], None] | None = None) -> dict:
    """The same graph-mode session with each worker count (see the module docstring).

    Args:
        task_name: the task (name or YAML path).
        workers: rollout worker counts, each >= 1, each once; the first is the baseline of
            the speed-ups.
        strategy, tasks, budget, seed: the session (``psl learn --strategy --tasks --budget
            --seed``).
        progress: called with one line of text per finished session.

    Returns:
        JSON-able dict: the settings, ``sessions`` (per worker count: wall time [s], training
        and held-out rollouts, fulfilled tasks, zero-shot success, speed-up over the first),
        ``sessions_equal`` and ``differences`` (against the first session).

    Raises:
        ValueError: bad worker counts.
        RuntimeError: a graph did not come up or a session failed.
    """
    from psl_ros.graph import default_log_dir
    from psl_task.task import load_task

    workers = [int(n) for n in workers]
    if not workers or min(workers) < 1 or len(set(workers)) != len(workers):
        raise ValueError(f'workers must be distinct counts >= 1, got {workers}')
    task = load_task(task_name)
    runs = []
    with tempfile.TemporaryDirectory(prefix='psl-bench-workers-') as tmp:
        for n in workers:
            runs.append(_session(n, task_name, strategy, tasks, budget, seed,
                                 Path(tmp) / f'workers{n}', default_log_dir(f'-workers{n}')))
            if progress is not None:
                r = runs[-1]
                progress(f'{n} worker(s): {r["seconds"]:.1f} s for {r["training_rollouts"]} '
                         f'training + {r["test_rollouts"]} held-out rollouts')
    differences = {r['workers']: session_differences(runs[0]['metrics'], r['metrics'])
                   for r in runs[1:]}
    sessions = []
    for r in runs:
        r = {k: v for k, v in r.items() if k != 'metrics'}
        r['speedup'] = runs[0]['seconds'] / r['seconds']
        sessions.append(r)
    return {'task': task.name, 'steps_per_rollout': task.num_steps, 'strategy': strategy,
            'tasks': tasks, 'budget': budget, 'seed': seed, 'machine_cores': os.cpu_count(),
            'sessions': sessions,
            'sessions_equal': not any(differences.values()),
            'differences': {str(n): d for n, d in differences.items()}}


def format_report(report: dict) -> str:
    """Markdown: the session, one row per worker count, whether the sessions are the same."""
    first = report['sessions'][0]
    lines = [f"{report['task']}, {report['strategy']}, {report['tasks']} tasks, budget "
             f"{report['budget']}, seed {report['seed']}: {first['training_rollouts']} training "
             f"+ {first['test_rollouts']} held-out rollouts of {report['steps_per_rollout']} "
             f"lockstep steps, {report['machine_cores']} cores", '',
             '| workers | session [s] | speed-up | fulfilled tasks | zero-shot success |',
             '|---|---|---|---|---|']
    for r in report['sessions']:
        lines.append(f"| {r['workers']} | {r['seconds']:.1f} | {r['speedup']:.2f}× | "
                     f"{r['fulfilled_tasks']} of {report['tasks']} | "
                     f"{100 * r['zero_shot_success']:.0f} % |")
    lines.append('')
    if report['sessions_equal']:
        lines.append('the sessions are the same (rollouts, fulfilled, task instances, rewards '
                     f'to {REWARD_TOLERANCE:g})')
    else:
        for n, diffs in report['differences'].items():
            if diffs:
                lines.append(f"SESSIONS DIFFER: {n} workers against {first['workers']}: "
                             + '; '.join(diffs))
    return '\n'.join(lines) + '\n'
