"""``psl bench encodings``: trajectory encodings and task selection, on the same tasks and seeds.

Two tables from `Learner` sessions in batch mode (bootstrap strategy):

1. **DMP vs GMR** (``policy.kind``): the same task YAML with theta_K encoded by the DMP (the
   default) or by Gaussian Mixture Regression (`psl_controller.gmr_trajectory`): total
   rollouts, rollouts per task after `after` tasks, tasks fulfilled, held-out zero-shot
   success and reward, and the demonstration's own zero-shot success in each encoding.
2. **random vs variance-driven task selection** (``LearnSettings.task_selection``): after every
   training task the skill is tested zero-shot on the held-out instances (measurement rollouts,
   not counted as training); reported: the training rollouts (and tasks) spent until the
   zero-shot success first reaches the target (80 %), and the final success.

Every session of a seed sees the same held-out instances; the random sessions of a seed the
same training sequence. Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from psl_bench.stats import mean_sd
from psl_task import DEFAULT_TASK

TARGET = 0.8



def encoding_variant(task, kind: str, n_components: int):
    """The task with theta_K encoded by `kind` ('dmp' or 'gmr'); everything else unchanged."""
    policy = dataclasses.replace(task.policy, kind=kind)
    if kind == 'gmr':
        policy = dataclasses.replace(policy, n_components=n_components)
    return dataclasses.replace(task, policy=policy)


def run_encodings(task_name: str, seeds: Sequence[int], num_tasks: int, budget: int,
                  num_test: int, after: int, n_components: int,
                  progress: Callable[[str], None] = lambda line: None) -> dict:
    from psl_controller.policy import policy_for
    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_optimizer.learning import Learner, LearnSettings
    from psl_optimizer.task_selection import held_out_tasks
    from psl_optimizer.policy_search import SearchSettings
    from psl_task.task import load_task

    base = load_task(task_name)
    rows: dict[str, list[dict]] = {}
    for kind in ('dmp', 'gmr'):
        task = encoding_variant(base, kind, n_components)
        batch = BatchRollouts(task)
        theta0 = policy_for(task).default_theta
        for seed in seeds:
            settings = LearnSettings(strategy='bootstrap', num_tasks=num_tasks, seed=seed,
                                     num_test=num_test,
                                     search=SearchSettings(max_rollouts=budget))
            start = time.perf_counter()
            with tempfile.TemporaryDirectory() as out:
                metrics = Learner(task, settings, out, batch).run()
            test = held_out_tasks(task, num_test, seed)
            demo = batch.run(np.tile(theta0, (len(test), 1)), test)
            rollouts = [t.rollouts for t in metrics.tasks]
            row = {'seed': seed, 'theta_size': int(theta0.size),
                   'total_rollouts': int(sum(rollouts)),
                   'late_rollouts_per_task': float(np.mean(rollouts[after:])),
                   'fulfilled_tasks': metrics.summary.fulfilled_tasks,
                   'zero_shot_success': metrics.summary.zero_shot_success_rate,
                   'zero_shot_reward': metrics.summary.zero_shot_mean_reward,
                   'demonstration_success': float(np.mean([r.evaluation.fulfilled
                                                           for r in demo])),
                   'seconds': time.perf_counter() - start}
            rows.setdefault(kind, []).append(row)
            progress(f"{kind} seed {seed}: {row['total_rollouts']} rollouts, zero-shot "
                     f"{100 * row['zero_shot_success']:.0f} %")
    return rows


def run_selection(task_name: str, seeds: Sequence[int], num_tasks: int, budget: int,
                  num_test: int, progress: Callable[[str], None] = lambda line: None) -> dict:
    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_optimizer.learning import Learner, LearnSettings
    from psl_optimizer.task_selection import held_out_tasks
    from psl_optimizer.policy_search import SearchSettings
    from psl_task.task import load_task

    task = load_task(task_name)
    batch = BatchRollouts(task)
    rows: dict[str, list[dict]] = {}
    for selection in ('random', 'variance'):
        for seed in seeds:
            settings = LearnSettings(strategy='bootstrap', num_tasks=num_tasks, seed=seed,
                                     num_test=num_test, task_selection=selection,
                                     search=SearchSettings(max_rollouts=budget))
            test = held_out_tasks(task, num_test, seed)
            curve: list[tuple[int, float]] = []     # (training rollouts so far, success)
            with tempfile.TemporaryDirectory() as out:
                learner = Learner(task, settings, out, batch)

                def measure(record) -> None:
                    thetas = np.array([learner.skill.query(t) for t in test])
                    fulfilled = [r.evaluation.fulfilled for r in batch.run(thetas, test)]
                    used = sum(d.rollouts for d in learner.done)
                    curve.append((used, float(np.mean(fulfilled))))
                learner.run(progress=measure)
            reached = next((i for i, (_, ok) in enumerate(curve) if ok >= TARGET), None)
            row = {'seed': seed, 'curve': curve,
                   'rollouts_to_target': None if reached is None else curve[reached][0],
                   'tasks_to_target': None if reached is None else reached + 1,
                   'final_success': curve[-1][1], 'total_rollouts': curve[-1][0]}
            rows.setdefault(selection, []).append(row)
            progress(f"{selection} seed {seed}: {TARGET:.0%} zero-shot after "
                     f"{row['tasks_to_target']} tasks / {row['rollouts_to_target']} rollouts")
    return rows


def run(task_name: str = DEFAULT_TASK, seeds: Sequence[int] = (0, 1, 2, 3, 4),
        num_tasks: int = 30, budget: int = 300, num_test: int = 20, after: int = 20,
        n_components: int = 6, progress: Callable[[str], None] = lambda line: None) -> dict:
    """Both tables' sessions (see the module docstring); the report of `format_tables`.

    Raises:
        ValueError: after >= num_tasks, or settings the learner refuses.
    """
    if not 0 <= after < num_tasks:
        raise ValueError(f'--after must be below --tasks (got {after} and {num_tasks})')
    return {'settings': {'task': task_name, 'seeds': list(seeds), 'tasks': num_tasks,
                         'budget': budget, 'test_tasks': num_test, 'after': after,
                         'n_components': n_components},
            'encodings': run_encodings(task_name, seeds, num_tasks, budget, num_test, after,
                                       n_components, progress),
            'selection': run_selection(task_name, seeds, num_tasks, budget, num_test,
                                       progress)}


def format_tables(report: dict) -> str:
    s = report['settings']
    lines = [f"{s['task']}: bootstrap, {s['tasks']} training tasks, budget {s['budget']}, "
             f"{s['test_tasks']} held-out tasks, seeds {' '.join(map(str, s['seeds']))}; "
             'mean ± SD over seeds', '',
             f"| encoding | theta size | demonstration zero-shot | total rollouts | rollouts "
             f"per task after {s['after']} | fulfilled tasks | zero-shot success | zero-shot "
             'reward |', '|---|---|---|---|---|---|---|---|']
    for kind, rows in report['encodings'].items():
        label = kind if kind == 'dmp' else f"gmr ({s['n_components']} components)"
        lines.append(
            f"| {label} | {rows[0]['theta_size']} | "
            f"{mean_sd([100 * r['demonstration_success'] for r in rows])} % | "
            f"{mean_sd([r['total_rollouts'] for r in rows])} | "
            f"{mean_sd([r['late_rollouts_per_task'] for r in rows])} | "
            f"{mean_sd([r['fulfilled_tasks'] for r in rows])} | "
            f"{mean_sd([100 * r['zero_shot_success'] for r in rows])} % | "
            f"{mean_sd([r['zero_shot_reward'] for r in rows])} |")
    lines += ['', f'| task selection | training tasks to {TARGET:.0%} zero-shot | training '
              f'rollouts to {TARGET:.0%} | final zero-shot success | total rollouts |',
              '|---|---|---|---|---|']
    for selection, rows in report['selection'].items():
        reached = [r for r in rows if r['tasks_to_target'] is not None]
        missed = len(rows) - len(reached)
        note = f' ({missed} of {len(rows)} seeds never reached it)' if missed else ''
        lines.append(
            f"| {selection} | {mean_sd([r['tasks_to_target'] for r in reached])}{note} | "
            f"{mean_sd([r['rollouts_to_target'] for r in reached])} | "
            f"{mean_sd([100 * r['final_success'] for r in rows])} % | "
            f"{mean_sd([r['total_rollouts'] for r in rows])} |")
        lines.append(f"|   per seed | {', '.join(str(r['tasks_to_target']) for r in rows)} | "
                     f"{', '.join(str(r['rollouts_to_target']) for r in rows)} | | |")
    return '\n'.join(lines) + '\n'


def plot_selection(report: dict, out_path: str | Path) -> Path:
    """Zero-shot success on the held-out instances against training tasks and against
    training rollouts, random vs variance-driven selection: mean over seeds and each seed."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4), dpi=110, layout='constrained')
    by_task, by_rollout = fig.subplots(1, 2)
    for (selection, rows), colour in zip(report['selection'].items(), ('C0', 'C3')):
        curves = np.array([[ok for _, ok in r['curve']] for r in rows])       # (seeds, tasks)
        tasks = np.arange(1, curves.shape[1] + 1)
        by_task.plot(tasks, 100 * curves.mean(axis=0), color=colour, lw=2,
                     label=f'{selection}: mean of {len(rows)} seeds')
        for r in rows:
            used = [u for u, _ in r['curve']]
            ok = [100 * o for _, o in r['curve']]
            by_task.plot(tasks, ok, color=colour, lw=0.6, alpha=0.4)
            by_rollout.plot(used, ok, color=colour, lw=0.8, alpha=0.7,
                            label=f"{selection}" if r is rows[0] else None)
    for ax, xlabel in ((by_task, 'training tasks'), (by_rollout, 'training rollouts')):
        ax.axhline(100 * TARGET, color='k', ls='--', lw=0.8)
        ax.set_xlabel(xlabel)
        ax.set_ylabel('held-out zero-shot success [%]')
        ax.grid(alpha=0.3)
        ax.legend(loc='lower right')
    by_rollout.set_xscale('log')
    fig.suptitle(f"{report['settings']['task']}: task selection (bootstrap; dashed: "
                 f'{TARGET:.0%})')
    fig.savefig(out_path)
    return Path(out_path)
