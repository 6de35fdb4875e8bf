"""``psl bench false-successes``: on a noisy robot, how many samples enter the skill on a lucky
rollout, with and without confirming a success first (`LearnSettings.confirm`).

Method, per task, noise level (`psl_optimizer.batch_rollout.MeasurementNoise`: Gaussian noise on
the measured joint angles and velocities) and confirmation (k of n; 1 of 1 is off): one `Learner`
session in batch mode on the noisy robot (seed ``seed``, ``num_tasks`` tasks); then every sample
the session added (tau, theta) is rolled out again ``reruns`` times with fresh noise (another
seed of the same level) and once without noise. A sample is a **false success** when its theta
fails most (more than half) of the fresh noisy rollouts, and **fails noise-free** when the
noise-free rollout misses the instance. The zero-shot success is the session's, on held-out
instances of the noisy robot.

The reward is computed on the measured (noisy) joint angles. Its smoothness term (mean squared
joint acceleration by second differences at the control period) is a noise meter there: with
dt = 2 ms, noise of std s on the angles adds about 6 s^2 / dt^4 to it (1 mrad: 4e5 rad^2/s^4,
times the weight 1e-5 = 4 reward units, twenty times the success margin), so at 1 mrad no
rollout of either embedded task fulfils its instance and nothing is learned; the default
levels include that one and one at the edge where luck decides (reach_over_obstacle: 0.23 mrad
and 0.02 rad/s; payload_transport, whose margin is narrower: velocity noise 0.3 rad/s only).
Plain Python, no ROS.
"""
from __future__ import annotations

import importlib
import tempfile
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from psl_bench import sessions
from psl_task import DEFAULT_TASK

REALISTIC = 'position=0.001,velocity=0.01'
NOISE_LEVELS = {DEFAULT_TASK: (REALISTIC, 'position=0.00023,velocity=0.02'),
                'payload_transport': (REALISTIC, 'velocity=0.3')}
CONFIRMS = ((1, 1), (2, 3), (3, 3))


def parse_confirm(text: str) -> tuple[int, int]:
    """``"k/n"`` -> (k, n) (ValueError naming what is wrong)."""
    k, sep, n = text.partition('/')
    try:
        value = (int(k), int(n))
    except ValueError:
        value = None
    if not sep or value is None or not 1 <= value[0] <= value[1]:
        raise ValueError(f'confirm {text!r}: give k/n with whole numbers 1 <= k <= n')
    return value


def measure(task_name: str, noise: str, confirm: tuple[int, int], seed: int = 21,
            num_tasks: int = 20, num_test: int = 20, budget: int = 200, reruns: int = 10,
            out: str | Path | None = None) -> dict:
    """One session and the re-runs of its samples (module docstring); a JSON-able dict."""
    import dataclasses

    from psl_memory.skill_memory import SkillMemory
    from psl_optimizer.batch_rollout import MeasurementNoise
    from psl_optimizer.learning import Learner, LearnSettings
    from psl_optimizer.policy_search import SearchSettings
    from psl_optimizer.rollout_modes import make_rollouts
    from psl_task.task import load_task

    level = MeasurementNoise.parse(noise)
    if level.is_off:
        raise ValueError('false successes need measurement noise')
    task = load_task(task_name)
    temporary = tempfile.TemporaryDirectory(prefix='psl-bench-false-') if out is None else None
    folder = (Path(temporary.name if temporary else out)
              / f'{task.name}-{noise.replace(",", "_").replace("=", "")}-confirm{confirm[0]}of'
                f'{confirm[1]}')
    try:
        settings = LearnSettings(seed=seed, num_tasks=num_tasks, num_test=num_test,
                                 search=SearchSettings(max_rollouts=budget),
                                 measurement_noise=noise, confirm=tuple(confirm))
        metrics = Learner(task, settings, folder,
                          make_rollouts('batch', task, measurement_noise=level)).run()
        skill = SkillMemory.read(folder / 'memory.npz').get(task.name)
        fresh = make_rollouts('batch', task, measurement_noise=dataclasses.replace(
            level, seed=level.seed + 1))
        clean = make_rollouts('batch', task)
        false = fails_clean = 0
        for tau, theta in zip(skill.taus, skill.thetas):
            _, fulfilled = fresh.evaluate(np.tile(theta, (reruns, 1)), np.tile(tau, (reruns, 1)))
            false += int(reruns - np.sum(fulfilled) > reruns / 2)
            _, fulfilled = clean.evaluate(theta[None], tau[None])
            fails_clean += int(not fulfilled[0])
        s = metrics.summary
        return {'task': task.name, 'noise': noise, 'confirm': list(confirm),
                'rollouts': s.total_rollouts, 'confirm_rollouts': s.confirm_rollouts,
                'fulfilled_tasks': s.fulfilled_tasks, 'unconfirmed': s.unconfirmed_tasks,
                'added': skill.num_samples, 'false_successes': false,
                'fails_noise_free': fails_clean, 'zero_shot_success': s.zero_shot_success_rate}
    finally:
        if temporary is not None:
            temporary.cleanup()


def measure_session(**kwargs) -> dict:
    """`measure` as a session of the sweep (`psl_bench.sessions`): its row and a summary."""
    row = measure(**kwargs)
    return {**row, 'summary': f"{row['added']} added, {row['false_successes']} false"}


def run(tasks: Sequence[str] = tuple(NOISE_LEVELS), noise: Sequence[str] | None = None,
        confirms: Sequence[tuple[int, int]] = CONFIRMS, seed: int = 21, num_tasks: int = 20,
        num_test: int = 20, budget: int = 200, reruns: int = 10,
        out: str | Path | None = None,
        progress: Callable[[str], None] | None = None, runner: str = 'serial',
        address: str | None = None) -> dict:
    """Every task x noise level x confirmation; the report of `format_table`.

    Args:
        noise: the levels (`MeasurementNoise.parse` text) for every task; None: each task's
            of `NOISE_LEVELS` (a task not named there: the realistic level only).
        runner, address: where the sessions run (`psl_bench.sessions.run`); rows in the same
            order either way, a session that failed twice under ``missing``.

    Raises:
        ValueError: bad sizes, no noise, a confirmation that is not k <= n.
    """
    from psl_optimizer.batch_rollout import MeasurementNoise

    if not tasks or len(set(tasks)) != len(tasks):
        raise ValueError('give each task once, at least one')
    for name, value in (('num_tasks', num_tasks), ('num_test', num_test), ('budget', budget),
                        ('reruns', reruns)):
        if value < 1:
            raise ValueError(f'{name} must be at least 1, got {value}')
    for k, n in confirms:
        if not 1 <= k <= n:
            raise ValueError(f'confirm {k}/{n}: need 1 <= k <= n')
    for level in noise or ():
        if MeasurementNoise.parse(level).is_off:
            raise ValueError(f'noise level {level!r} is no noise')
    importlib.import_module('cma')
    plan = [sessions.Session(
        key=(task, level, tuple(confirm)),
        label=f'{task} {level} confirm {confirm[0]}/{confirm[1]}', function=measure_session,
        kwargs=dict(task_name=task, noise=level, confirm=tuple(confirm), seed=seed,
                    num_tasks=num_tasks, num_test=num_test, budget=budget, reruns=reruns,
                    out=None if out is None else str(out)))
        for task in tasks for level in (noise or NOISE_LEVELS.get(task, (REALISTIC,)))
        for confirm in confirms]
    swept = sessions.run(plan, runner, address, progress)
    rows = [{k: v for k, v in swept.records[s.key].items() if k not in ('summary', 'ran_on')}
            for s in plan if s.key in swept.records]
    return {'seed': seed, 'num_tasks': num_tasks, 'num_test': num_test, 'budget': budget,
            'reruns': reruns, 'rows': rows, 'runner': swept.runner, 'nodes': swept.nodes,
            'missing': swept.missing()}


def format_table(report: dict) -> str:
    """Markdown, one row per session."""
    lines = [f"{report['num_tasks']} tasks of seed {report['seed']} on the noisy robot (budget "
             f"{report['budget']}); each added sample re-run {report['reruns']} times with "
             'fresh noise (false: fails more than half) and once without noise; zero-shot on '
             f"{report['num_test']} held-out instances, noisy", '',
             '| task | noise | confirm | rollouts | of them confirming | fulfilled | '
             'unconfirmed | added | false successes | fail noise-free | zero-shot |',
             '|---' * 11 + '|']
    for r in report['rows']:
        k, n = r['confirm']
        lines.append(f"| {r['task']} | {r['noise']} | {'off' if n == 1 else f'{k} of {n}'} | "
                     f"{r['rollouts']} | {r['confirm_rollouts']} | {r['fulfilled_tasks']} | "
                     f"{r['unconfirmed']} | {r['added']} | {r['false_successes']} | "
                     f"{r['fails_noise_free']} | {100 * r['zero_shot_success']:.0f} % |")
    for missing in report.get('missing', []):
        lines.append(f'MISSING (failed twice): {missing}')
    return '\n'.join(lines) + '\n'
