"""``psl bench sim-to-real``: a skill learned in simulation, continued on a robot whose model is
wrong (batch mode: the robot is the task's model with a `psl_task.model_error.ModelError`).

Method, per task:
- ``nominal``: a `Learner` session on the task's own model (seed ``nominal_seed``,
  ``nominal_tasks`` tasks): the simulated skill PS_sim and its memory file;
- ``before``: PS_sim executed once on each held-out instance of ``seed`` on the robot;
- ``scratch``: ``num_tasks`` tasks of ``seed`` on the robot from an empty skill;
- one session per continuation (`psl_optimizer.learning.CONTINUATIONS`): the same tasks on the
  robot, continuing PS_sim (``continue_from``); 'residual' (the default way) learns the robot's
  correction on top of PS_sim, 'samples' adds the robot's solutions to PS_sim's samples;
- a task with feed-forward: the tracking error [rad] on the robot, per held-out instance, of
  the commanded paths of PS_sim with PD only (``pd_only``), with PS_sim's feed-forward
  (``simulated``), with the nominal model's inverse dynamics (``oracle``), after
  ``ilc_iterations`` ILC steps on the robot from PS_sim's theta (``ilc``: `ilc_step`, no stop at
  success), and the continued skills' learned feed-forward (zero-shot, `Learner.summary`).
Every session reads the same training instances (its seed) and the same held-out instances; the
rollouts on the robot of each session are what the table calls "rollouts on the robot".
Plain Python, no ROS.
"""
from __future__ import annotations

import importlib
import tempfile
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from psl_task import DEFAULT_TASK

# the stand-in "real" robot of the measurements (docs/benchmarks.md)
REAL_ROBOT = 'mass_scale=1.3,frictionloss=0.05,damping=0.3'
TASKS = (DEFAULT_TASK, 'payload_transport')
TRACKING = ('pd_only', 'simulated', 'oracle', 'ilc')      # PS_sim's path on the robot


def _tracking_error(rollouts, taus: np.ndarray, thetas: np.ndarray) -> list[float]:
    return [float(r.evaluation.components['tracking_error'])
            for r in rollouts.run(thetas, taus)]


def _ilc(rollouts, taus: np.ndarray, thetas: np.ndarray, iterations: int) -> np.ndarray:
    """thetas after `iterations` ILC steps of theta_D each on its instance (every step one
    rollout on the robot, no stop at success)."""
    from psl_optimizer.ilc import ILCSettings, ilc_step
    settings, out = ILCSettings(), []
    for tau, theta in zip(taus, thetas):
        for _ in range(iterations):
            result = rollouts.run(theta[None], tau)[0]
            theta = ilc_step(rollouts.policy, theta, result, settings, tau)
        out.append(theta)
    return np.array(out)


def measure_task(task_name: str, model_error: str = REAL_ROBOT, nominal_seed: int = 3,
                 nominal_tasks: int = 30, seed: int = 11, num_tasks: int = 10,
                 num_test: int = 20, budget: int = 200, ilc_iterations: int = 10,
                 continuations: Sequence[str] = ('residual', 'samples'),
                 out: str | Path | None = None,
                 progress: Callable[[str], None] | None = None) -> dict:
    """The sessions of one task (module docstring); a JSON-able dict."""
    from psl_optimizer.learning import (CONTINUATIONS, InProcessSkill, Learner, LearnSettings,
                                        feedforward_variants)
    from psl_optimizer.policy_search import SearchSettings
    from psl_optimizer.rollout_modes import make_rollouts
    from psl_optimizer.task_selection import held_out_tasks
    from psl_task.model_error import ModelError
    from psl_task.task import load_task

    if ModelError.parse(model_error).is_identity:
        raise ValueError('sim to real needs a model error (the robot is the model otherwise)')
    unknown = [c for c in continuations if c not in CONTINUATIONS]
    if unknown or len(set(continuations)) != len(continuations):
        raise ValueError(f'continuations: each of {", ".join(CONTINUATIONS)} at most once, '
                         f'got {list(continuations)}')
    importlib.import_module('cma')
    task = load_task(task_name)
    temporary = tempfile.TemporaryDirectory(prefix='psl-bench-s2r-') if out is None else None
    root = Path(temporary.name if temporary else out) / task.name
    search = SearchSettings(max_rollouts=budget)
    nominal, robot = make_rollouts('batch', task), make_rollouts('batch', task,
                                                                 model_error=model_error)

    def session(name, rollouts, **changes) -> dict:
        settings = LearnSettings(search=search, num_test=num_test, **changes)
        learner = Learner(task, settings, root / name, rollouts)
        metrics = learner.run()
        s = metrics.summary
        row = {'rollouts': s.total_rollouts, 'rollouts_per_task': s.rollouts_per_task,
               'fulfilled_tasks': s.fulfilled_tasks,
               'zero_shot_success': s.zero_shot_success_rate,
               'zero_shot_reward': s.zero_shot_mean_reward,
               'tracking_learned': (None if s.tracking_rmse_mean is None
                                    else s.tracking_rmse_mean['learned'])}
        if progress is not None:
            progress(f'{task.name} {name}: {row["rollouts"]} rollouts, zero-shot '
                     f'{100 * row["zero_shot_success"]:.0f} %')
        return row

    try:
        report = {'task': task.name, 'model_error': model_error, 'nominal_seed': nominal_seed,
                  'nominal_tasks': nominal_tasks, 'seed': seed, 'num_tasks': num_tasks,
                  'num_test': num_test, 'budget': budget, 'ilc_iterations': ilc_iterations,
                  'sessions': {}}
        report['nominal'] = session('nominal', nominal, seed=nominal_seed,
                                    num_tasks=nominal_tasks)
        memory = root / 'nominal' / 'memory.npz'
        sim = InProcessSkill(task, LearnSettings().skill, robot.policy.default_theta, 'samples')
        sim.start(str(memory))
        test = held_out_tasks(task, num_test, seed)
        thetas = np.array([sim.query(tau) for tau in test])
        rewards, fulfilled = robot.evaluate(thetas, test)
        report['before'] = {'zero_shot_success': float(np.mean(fulfilled)),
                            'zero_shot_reward': float(np.mean(rewards))}
        report['sessions']['scratch'] = session('scratch', robot, seed=seed,
                                                num_tasks=num_tasks, model_error=model_error)
        for way in continuations:
            report['sessions'][way] = session(
                f'continued-{way}', robot, seed=seed, num_tasks=num_tasks,
                model_error=model_error, continue_from=str(memory), continuation=way)
        if robot.policy.has_feedforward:
            variants = feedforward_variants(task, test, thetas)
            tracking = {'pd_only': _tracking_error(robot, test, variants['pd_only']),
                        'simulated': _tracking_error(robot, test, variants['learned']),
                        'oracle': _tracking_error(robot, test, variants['oracle']),
                        'ilc': _tracking_error(robot, test, _ilc(robot, test, thetas,
                                                                 ilc_iterations))}
            report['tracking'] = {name: {'mean': float(np.mean(v)), 'values': v}
                                  for name, v in tracking.items()}
        return report
    finally:
        if temporary is not None:
            temporary.cleanup()


def run(tasks: Sequence[str] = TASKS, model_error: str = REAL_ROBOT, nominal_seed: int = 3,
        nominal_tasks: int = 30, seed: int = 11, num_tasks: int = 10, num_test: int = 20,
        budget: int = 200, ilc_iterations: int = 10,
        continuations: Sequence[str] = ('residual', 'samples'),
        out: str | Path | None = None,
        progress: Callable[[str], None] | None = None) -> dict:
    """`measure_task` for each task; the report of `format_table`.

    Raises:
        ValueError: no model error, an unknown task or continuation, bad sizes.
    """
    if not tasks or len(set(tasks)) != len(tasks):
        raise ValueError('give each task once, at least one')
    for name, value in (('nominal_tasks', nominal_tasks), ('num_tasks', num_tasks),
                        ('num_test', num_test), ('budget', budget)):
        if value < 1:
            raise ValueError(f'{name} must be at least 1, got {value}')
    if ilc_iterations < 0:
        raise ValueError(f'ilc_iterations must be >= 0, got {ilc_iterations}')
    return {'tasks': {name: measure_task(
        name, model_error, nominal_seed, nominal_tasks, seed, num_tasks, num_test, budget,
        ilc_iterations, continuations, out, progress) for name in tasks}}


def format_table(report: dict) -> str:
    """Markdown: rollouts and zero-shot success on the robot per task and session, then the
    tracking errors of the tasks with feed-forward."""
    first = next(iter(report['tasks'].values()))
    ways = list(first['sessions'])[1:]
    lines = [f"robot = the task's model with {first['model_error']}; simulated skill: "
             f"{first['nominal_tasks']} tasks of seed {first['nominal_seed']} on the model; "
             f"on the robot: {first['num_tasks']} tasks of seed {first['seed']} (budget "
             f"{first['budget']}), zero-shot on {first['num_test']} held-out instances", '',
             '| task | rollouts scratch | ' + ' | '.join(f'rollouts {w}' for w in ways)
             + ' | zero-shot sim skill | zero-shot scratch | '
             + ' | '.join(f'zero-shot {w}' for w in ways) + ' |',
             '|---' * (3 + 2 * len(ways) + 1) + '|']
    for name, r in report['tasks'].items():
        s = r['sessions']
        lines.append(
            f"| {name} | {s['scratch']['rollouts']} | "
            + ' | '.join(str(s[w]['rollouts']) for w in ways)
            + f" | {100 * r['before']['zero_shot_success']:.0f} % | "
            f"{100 * s['scratch']['zero_shot_success']:.0f} % | "
            + ' | '.join(f"{100 * s[w]['zero_shot_success']:.0f} %" for w in ways) + ' |')
    tracked = {n: r for n, r in report['tasks'].items() if 'tracking' in r}
    if tracked:
        lines += ['', 'tracking RMSE on the robot [rad], mean over the held-out instances: '
                  "the simulated skill's path with PD only, its simulated feed-forward, the "
                  "model's inverse dynamics, after ILC on the robot; the learned feed-forward "
                  'of scratch and the continued skills (zero-shot)', '',
                  '| task | PD only | simulated ff | oracle (model) | ILC on robot | scratch | '
                  + ' | '.join(ways) + ' |', '|---' * (6 + len(ways)) + '|']
        for name, r in tracked.items():
            t, s = r['tracking'], r['sessions']
            lines.append(f"| {name} | {t['pd_only']['mean']:.4f} | "
                         f"{t['simulated']['mean']:.4f} | {t['oracle']['mean']:.4f} | "
                         f"{t['ilc']['mean']:.4f} ({r['ilc_iterations']} steps) | "
                         f"{s['scratch']['tracking_learned']:.4f} | "
                         + ' | '.join(f"{s[w]['tracking_learned']:.4f}" for w in ways) + ' |')
    return '\n'.join(lines) + '\n'
