"""``psl bench learn``: policy-search strategies over task instances.

Method, per seed:
- one training sequence (`task_sequence`) and one held-out set (`held_out_tasks`), both drawn
  from the seed by the `Learner` itself, so every strategy of a seed sees the same instances in
  the same order; the bench checks that from the runs' metrics files;
- per strategy and skill map one `Learner` session (batch mode, in-process skill) in its own
  folder ``OUT/<task>-<strategy>[-<readout>][-<map>]-seed<k>/`` holding ``metrics.json``
  (per-task rollouts, the zero-shot test on the held-out set), the checkpoint and the memory
  file. The skill map (`LearnSettings.skill_map`) is the skill memory ('elm', no suffix) or a
  baseline in its place: 'library' (the k nearest solved instances, inverse-distance
  weighted), 'gp' (Gaussian-process regression).
Every number of the report is read back from those metrics files, never from the running
session: a run that was done before (same settings, complete) is reused, not repeated.

Per row, a strategy with a skill map (named `row_name`), over seeds (mean, sample standard
deviation, min, max):
- ``total_rollouts``: rollouts over all training tasks;
- ``late_rollouts``: mean rollouts per new task after ``after`` tasks (tasks after+1 .. N);
- ``speedup``: scratch's ``late_rollouts`` / this row's, per seed (scratch in the run, with
  the same skill map);
- ``zero_shot_success`` and ``zero_shot_reward``: PS(tau) executed once on each held-out
  instance after the last training task;
- ``train_seconds``: wall time of the training tasks (sum of the per-task seconds);
- ``session_seconds`` and ``simulation_share``: wall time of the whole session (training and
  held-out tasks) and the share of it spent in the simulation
  (`BatchRollouts.simulation_seconds`), kept in the run folder (``bench_session.json``);
  ``ik_share`` and ``ik_ms_per_path``: of an end-effector-space task, the share spent in the
  differential inverse kinematics and its wall time per candidate's path it solved
  (`TaskPolicy.ik_seconds`, ``ik_paths``); ``ik_paths`` and ``ik_reused``: the paths it
  solved and those it took again (a theta_K seen before, `TaskPolicy._hand_path`);
- ``consistency_<block>`` (a skill of the skill memory): how well the skill's samples agree
  with each other, per block of theta (the DMP weights, a learned goal, the feed-forward):
  the leave-one-out error of the skill's mean on its own samples (`sample_consistency`), as a
  share of the samples' spread in that block. 0: every sample is what the others predict; 1:
  the others tell nothing about it (a sample's own noise, or a mix the neighbours do not
  share). Samples that contradict each other make a skill that misses between them;
- a task with a target: the hand's final miss on the held-out instances, the mean per seed,
  and the median and 90th percentile of every seed's instances pooled; a task with a
  feed-forward: the held-out tracking RMSE of PD only, the learned feed-forward and the
  inverse-dynamics oracle (`psl_optimizer.learning.tracking_comparison`), mean per seed.
Plain Python, no ROS.
"""
from __future__ import annotations

import dataclasses
import importlib
import json
import tempfile
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from psl_bench import sessions
from psl_bench.stats import over_seeds
from psl_optimizer.metrics import METRICS_FILE, read_metrics
from psl_task import DEFAULT_TASK

TARGETS = {'speedup': 5.0, 'zero_shot_success': 0.8}   # bootstrap vs scratch; every strategy
SESSION_FILE = 'bench_session.json'   # a run folder's session and simulation time
TIMINGS = ('session_seconds', 'simulation_share', 'ik_share', 'ik_ms_per_path',
           'ik_paths', 'ik_reused')
# a task with a target: the hand's final miss on the held-out instances, mean over them (the
# orientation where the reward scores it)
HAND_ERRORS = {'held_out_goal_error': 'goal_error',                 # m
               'held_out_orientation_error': 'orientation_error'}   # rad
METRICS = ('total_rollouts', 'late_rollouts', 'speedup', 'zero_shot_success',
           'zero_shot_reward', 'train_seconds', 'refused')
CONSISTENCY = ('weights', 'goal', 'feedforward')     # the blocks of theta `sample_consistency`
TRACKING = ('pd_only', 'learned', 'oracle')          # held-out tracking RMSE [rad]
SPREAD_FLOOR = 1e-9      # unit coordinates: samples that spread less share the block


def run_folder(out: Path, task: str, strategy: str, seed: int, readout: str | None,
               skill_map: str = 'elm') -> Path:
    readout_part = f'-{readout}' if readout else ''
    return Path(out) / f'{task}-{strategy}{readout_part}{_map_part(skill_map)}-seed{seed}'


def row_name(strategy: str, skill_map: str = 'elm') -> str:
    """The report's key of a strategy with a skill map: the strategy for the skill memory
    ('elm'), ``<strategy>-<map>`` for a baseline."""
    return f'{strategy}{_map_part(skill_map)}'


def _map_part(skill_map: str) -> str:
    return '' if skill_map == 'elm' else f'-{skill_map}'


def read_run(folder: Path, after: int) -> dict:
    """One run's numbers from its metrics.json (see the module docstring).

    Raises:
        ValueError: the run is incomplete or has no more than `after` tasks.
    """
    metrics = read_metrics(folder)
    if not metrics.complete:
        raise ValueError(f'{folder}: the learning session is not complete')
    if len(metrics.tasks) <= after:
        raise ValueError(f'{folder}: {len(metrics.tasks)} tasks, need more than after={after}')
    rollouts = [t.rollouts for t in metrics.tasks]
    summary = metrics.summary
    timed = _timing(folder / SESSION_FILE)
    return {
        **{key: float(timed[key]) for key in TIMINGS if key in timed},
        **{key: float(np.nanmean(summary.test_hand_errors[name]))
           for key, name in HAND_ERRORS.items() if name in (summary.test_hand_errors or {})},
        'folder': str(folder),
        'seed': metrics.seed,
        'strategy': metrics.strategy,
        'skill_map': metrics.settings.get('skill_map', 'elm'),
        'taus': [t.tau for t in metrics.tasks],
        'test_taus': summary.test_taus,
        'rollouts_per_task': rollouts,
        'fulfilled_tasks': sum(t.fulfilled for t in metrics.tasks),
        'total_rollouts': sum(rollouts),
        'late_rollouts': float(np.mean(rollouts[after:])),
        'zero_shot_success': summary.zero_shot_success_rate,
        'zero_shot_reward': summary.zero_shot_mean_reward,
        'train_seconds': float(sum(t.seconds for t in metrics.tasks)),
        # candidates the safety check refused (not executed), of total_rollouts
        'refused': sum(t.refused for t in metrics.tasks),
        **{f'consistency_{block}': value
           for block, value in _run_consistency(folder).items()},
        **({'held_out_goal_errors': list(summary.test_hand_errors['goal_error'])}
           if 'goal_error' in (summary.test_hand_errors or {}) else {}),
        **{f'tracking_{name}': float(value)
           for name, value in (summary.tracking_rmse_mean or {}).items()},
    }


def sample_consistency(skill, blocks: dict[str, np.ndarray]) -> dict[str, float]:
    """How well a skill's samples agree (module docstring), per block of theta (name -> the
    indices of its entries): for the ridge mean of the skill (`SkillConfig.regularization`
    over `noise_precision`: the Bayesian readout's mean, and the one the incremental readouts
    agree with) on its own samples, the leave-one-out residuals in closed form,
    e_i = (y_i - yhat_i) / (1 - H_ii) with the hat matrix H of ridge regression, their RMS
    over the block's entries and the samples over the RMS of the samples about their mean
    (unit coordinates). A block the samples share (spread below SPREAD_FLOOR) is left out;
    {} for fewer than 3 samples."""
    if skill.num_samples < 3:
        return {}
    h = skill.features.transform(skill.taus)                           # (N, N_H)
    y = skill.theta_scaler.to_unit(skill.thetas)                       # (N, F)
    ridge = skill.config.regularization / skill.config.noise_precision
    hat = h @ np.linalg.solve(h.T @ h + ridge * np.eye(h.shape[1]), h.T)
    loo = (y - hat @ y) / (1.0 - np.diag(hat))[:, None]                # (N, F)
    spread = y - y.mean(axis=0)
    rms = {name: float(np.sqrt(np.mean(spread[:, block] ** 2))) if len(block) else 0.0
           for name, block in blocks.items()}
    return {name: float(np.sqrt(np.mean(loo[:, block] ** 2))) / rms[name]
            for name, block in blocks.items() if rms[name] > SPREAD_FLOOR}


def _run_consistency(folder: Path) -> dict[str, float]:
    """`sample_consistency` of a run's skill (its memory file) over the blocks of CONSISTENCY
    its task has; {} for a baseline's run."""
    from psl_controller.policy import policy_for
    from psl_memory.skill_memory import SkillMemory
    from psl_task.task import load_task
    metrics = read_metrics(folder)
    if metrics.settings.get('skill_map', 'elm') != 'elm':
        return {}
    task = load_task(metrics.task_path)
    skill = SkillMemory.read(folder / 'memory.npz').get(task.name)
    policy = policy_for(task)
    index = np.arange(skill.theta_dim)
    goal = index[policy.goal] if task.policy.learn_goal else index[:0]
    feedforward = index[policy.dynamics] if policy.has_feedforward else index[:0]
    return sample_consistency(skill, {
        'weights': np.setdiff1d(index, np.r_[goal, feedforward]), 'goal': goal,
        'feedforward': feedforward})


def _settings_json(settings) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(settings)))


def run(task_name: str = DEFAULT_TASK, strategies: Sequence[str] | None = None,
        seeds: Sequence[int] = (0, 1, 2, 3, 4), num_tasks: int = 30, budget: int = 300,
        num_test: int = 20, after: int = 20, out: str | Path | None = None,
        readout: str | None = None, skill_maps: Sequence[str] = ('elm',),
        progress: Callable[[str], None] | None = None, runner: str = 'serial',
        address: str | None = None) -> dict:
    """Learn `task_name` with each strategy for each seed and compare them.

    Args:
        strategies: policy-search strategies (default: all of `STRATEGIES`).
        seeds: one task sequence and held-out set per seed, shared by the strategies.
        num_tasks: training task instances per session.
        budget: rollouts per task instance at most.
        num_test: held-out instances for the zero-shot test.
        after: late tasks are those after this many (0 <= after < num_tasks).
        out: folder that keeps every run's folder; None: a temporary folder, removed after.
        readout: the skill's readout (`SkillConfig.readout`); None: `LearnSettings`' default.
        skill_maps: what fills the skill slot (`LearnSettings.skill_map`), each a session per
            strategy and seed: 'elm' (the skill memory) and/or the baselines 'library', 'gp'.
        progress: called with one line of text per finished run.
        runner: 'serial' (one session after the other, here) or 'ray' (each session a Ray
            task: `psl_bench.sessions`); the same seeds give the same records either way.
        address: the Ray cluster (``HOST:PORT``); None: $RAY_ADDRESS, else this machine's.

    Returns:
        JSON-able dict: ``settings``, ``rows`` (per row name, `row_name`: its strategy and
        skill map), ``runs`` (per seed and row, see `read_run`), ``strategies`` (per row:
        each metric of `METRICS` as mean/sd/min/max/values), ``targets`` (the targets and
        whether they are met), ``runner``, ``nodes`` (sessions per node) and ``missing``
        (the sessions that failed twice, with why: their seeds' rows are left out).

    Raises:
        ValueError: bad settings, or a run folder holding another session.
        RuntimeError: strategies of one seed saw different task instances; no session
            finished.
    """
    from psl_optimizer.learning import SKILL_MAPS, LearnSettings
    from psl_optimizer.policy_search import STRATEGIES, SearchSettings
    from psl_task.task import load_task, task_id

    strategies = tuple(strategies or STRATEGIES)
    unknown = [s for s in strategies if s not in STRATEGIES]
    if unknown or not strategies:
        raise ValueError(f'unknown strategies {unknown}; known: {", ".join(STRATEGIES)}')
    skill_maps = tuple(skill_maps)
    unknown = [m for m in skill_maps if m not in SKILL_MAPS]
    if unknown or not skill_maps:
        raise ValueError(f'unknown skill maps {unknown}; known: {", ".join(SKILL_MAPS)}')
    if (len(set(strategies)) != len(strategies) or len(set(seeds)) != len(seeds) or not seeds
            or len(set(skill_maps)) != len(skill_maps)):
        raise ValueError('give at least one seed, and each strategy, seed and skill map once')
    if not 0 <= after < num_tasks or budget < 1 or num_test < 1:
        raise ValueError(f'need 0 <= after < num_tasks, budget >= 1 and num_test >= 1; got '
                         f'after={after}, num_tasks={num_tasks}, budget={budget}, '
                         f'num_test={num_test}')
    base = LearnSettings()
    skill = base.skill if readout is None else dataclasses.replace(base.skill, readout=readout)
    task = load_task(task_name)
    temporary = tempfile.TemporaryDirectory(prefix='psl-bench-learn-') if out is None else None
    root = Path(temporary.name if temporary else out)
    rows = {row_name(strategy, skill_map): {'strategy': strategy, 'skill_map': skill_map}
            for strategy in strategies for skill_map in skill_maps}
    plan = []
    for seed in seeds:
        for name, row in rows.items():
            settings = LearnSettings(strategy=row['strategy'], num_tasks=num_tasks,
                                     seed=seed, num_test=num_test, skill=skill,
                                     search=SearchSettings(max_rollouts=budget),
                                     skill_map=row['skill_map'])
            folder = run_folder(root, task.name, row['strategy'], seed, readout,
                                row['skill_map'])
            _reusable(folder, settings, resumable=False)   # refused before any work
            plan.append(sessions.Session(
                key=(seed, name), label=f"seed {seed} {row['strategy']} ({row['skill_map']})",
                function=learn_session,
                kwargs=dict(task_name=task_id(task), settings=settings, folder=str(folder),
                            after=after, threads=1 if runner == 'ray' else 2)))
    try:
        swept = sessions.run(plan, runner, address, progress)
    finally:
        if temporary is not None:
            temporary.cleanup()
    runs: dict[int, dict[str, dict]] = {}
    for seed in seeds:
        runs[seed] = {name: swept.records[(seed, name)] for name in rows
                      if (seed, name) in swept.records}
        if runs[seed]:
            _check_same_instances(seed, runs[seed])
        else:
            del runs[seed]
    report = {'settings': {'task': task.name, 'strategies': list(strategies),
                           'seeds': list(seeds), 'num_tasks': num_tasks, 'budget': budget,
                           'num_test': num_test, 'after': after,
                           'readout': skill.readout, 'skill_maps': list(skill_maps),
                           'out': None if out is None else str(out)},
              'rows': rows,
              'runs': {str(seed): by_row for seed, by_row in runs.items()},
              'runner': swept.runner, 'nodes': swept.nodes,
              'missing': swept.missing()}
    report['strategies'] = _aggregate(runs, rows)
    report['targets'] = _targets(report['strategies'])
    return report


def learn_session(task_name: str, settings, folder: str, after: int, threads: int = 2) -> dict:
    """One session of the sweep (`psl_bench.sessions.Session`), wherever it runs: the
    `Learner` in batch mode into `folder` (or the complete session found there reused; a
    retry resumes from the checkpoint its first attempt left), its timing beside its
    metrics; returns `read_run` of the folder, with ``reused`` and a ``summary`` line.
    `threads`: of `mujoco.rollout` for a population (2: a serial sweep's sessions use both
    cores; 1: as a Ray task, the cores are the sweep's); the same results either way."""
    from psl_optimizer.learning import Learner
    from psl_optimizer.rollout_modes import make_rollouts
    from psl_task.task import load_task

    importlib.import_module('cma')    # policy_search imports it on first use: not in a session
    folder = Path(folder)
    reused = _reusable(folder, settings, resumable=True)
    if not reused:
        task = load_task(task_name)
        rollouts = make_rollouts('batch', task, threads=threads)
        policy = rollouts.policy        # whose references the rollouts solve (their IK)
        start, simulated = time.perf_counter(), rollouts.simulation_seconds
        solving, paths, reused = policy.ik_seconds, policy.ik_paths, policy.ik_reused
        Learner(task, settings, folder, rollouts=rollouts).run()
        session = time.perf_counter() - start
        # the session's wall time and its shares spent simulating and in the inverse
        # kinematics, kept beside its metrics for a later reuse
        timing = {'session_seconds': session,
                  'simulation_share': (rollouts.simulation_seconds - simulated) / session}
        if policy.ik_paths > paths:
            timing.update(ik_share=(policy.ik_seconds - solving) / session,
                          ik_ms_per_path=1e3 * (policy.ik_seconds - solving)
                          / (policy.ik_paths - paths),
                          ik_paths=policy.ik_paths - paths,
                          ik_reused=policy.ik_reused - reused)
        (folder / SESSION_FILE).write_text(json.dumps(timing))
    record = read_run(folder, after)
    record['reused'] = reused
    record['summary'] = (f"{record['total_rollouts']} rollouts, zero-shot "
                         f"{100 * record['zero_shot_success']:.0f} %, "
                         f"{record['train_seconds']:.1f} s{' (reused)' if reused else ''}")
    return record


def _timing(path: Path) -> dict:
    """A run's session time and its shares (`SESSION_FILE`; {} for runs kept from before the
    bench wrote it). ValueError naming the file: damaged (not a file, not JSON, not an object
    of numbers)."""
    if not path.exists():
        return {}
    try:
        timed = json.loads(path.read_text())
    except (OSError, ValueError) as exc:        # UnicodeDecodeError, JSONDecodeError too
        raise ValueError(f'{path}: damaged ({getattr(exc, "strerror", None) or exc}); remove '
                         'it (the run is then reported without its timing)') from None
    if not isinstance(timed, dict) or not all(isinstance(timed.get(key, 0.0), (int, float))
                                              for key in TIMINGS):
        raise ValueError(f'{path}: damaged (not an object of numbers); remove it (the run is '
                         'then reported without its timing)')
    return timed


def _reusable(folder: Path, settings, resumable: bool = False) -> bool:
    """True if folder holds a complete session with exactly these settings; False if it holds
    nothing yet, or (`resumable`: a session's retry) an unfinished one whose checkpoint the
    learner resumes (it refuses one of other settings). Anything else is refused (a partial
    or different session would mix in)."""
    from psl_optimizer.learning import holds_checkpoint

    metrics_path = folder / METRICS_FILE
    if not metrics_path.exists() and not holds_checkpoint(folder):
        return False
    if metrics_path.exists():           # read_metrics names a damaged one
        metrics = read_metrics(folder)
        stored = {'skill_map': 'elm', **metrics.settings}     # runs from before the option
        if metrics.complete and stored == _settings_json(settings):
            return True
    if resumable and not (metrics_path.exists() and read_metrics(folder).complete):
        return False
    raise ValueError(f'{folder} holds another or an unfinished learning session; remove it or '
                     f'give another --out')


def _check_same_instances(seed: int, by_row: dict[str, dict]) -> None:
    first_name, first = next(iter(by_row.items()))
    for name, record in by_row.items():
        if record['taus'] != first['taus'] or record['test_taus'] != first['test_taus']:
            raise RuntimeError(f'seed {seed}: {name} saw other task instances than '
                               f'{first_name}')


def _aggregate(runs: dict[int, dict[str, dict]], rows: dict[str, dict]) -> dict:
    result = {}
    for name, spec in rows.items():
        records = [runs[seed][name] for seed in runs]
        row = {key: over_seeds([r[key] for r in records]) for key in METRICS
               if key != 'speedup'}
        scratch = row_name('scratch', spec['skill_map'])
        if scratch in rows:
            row['speedup'] = over_seeds([runs[seed][scratch]['late_rollouts'] /
                                         runs[seed][name]['late_rollouts'] for seed in runs])
        row['fulfilled_tasks'] = over_seeds([r['fulfilled_tasks'] for r in records])
        for key in (*TIMINGS, *HAND_ERRORS,      # not for runs of old folders, nor without
                    *(f'consistency_{b}' for b in CONSISTENCY),     # IK, a target, a block,
                    *(f'tracking_{t}' for t in TRACKING)):          # a feed-forward
            if all(key in r for r in records):
                row[key] = over_seeds([r[key] for r in records])
        if all('held_out_goal_errors' in r for r in records):
            pooled = np.concatenate([r['held_out_goal_errors'] for r in records])
            pooled = pooled[np.isfinite(pooled)]            # a refused rollout has none
            if pooled.size:
                row['held_out_goal_error_median'] = float(np.median(pooled))
                row['held_out_goal_error_p90'] = float(np.percentile(pooled, 90))
        result[name] = row
    return result


def _targets(rows: dict) -> dict:
    targets = {'zero_shot_success': {'min': TARGETS['zero_shot_success'], 'met': {
        strategy: row['zero_shot_success']['mean'] >= TARGETS['zero_shot_success']
        for strategy, row in rows.items()}}}
    if 'bootstrap' in rows and 'speedup' in rows['bootstrap']:
        speedup = rows['bootstrap']['speedup']['mean']
        targets['speedup'] = {'min': TARGETS['speedup'], 'bootstrap': speedup,
                              'met': speedup >= TARGETS['speedup']}
    return targets


def format_table(report: dict) -> str:
    """A Markdown table (mean ± sample SD over seeds) and the targets, for docs/benchmarks.md."""
    s = report['settings']
    late = f"tasks {s['after'] + 1}–{s['num_tasks']}"
    lines = [f"{s['task']}: {s['num_tasks']} training tasks, budget {s['budget']} rollouts "
             f"per task, readout {s['readout']}, seeds {' '.join(map(str, s['seeds']))}, "
             f"{s['num_test']} held-out tasks per seed; mean ± SD over seeds", '']
    # the skill-map column only when a baseline ran (the skill memory's table stays as it was)
    maps = s.get('skill_maps', ['elm']) != ['elm']
    lines += [f"| strategy |{' skill map |' if maps else ''} total rollouts | rollouts per "
              f'task, {late} | scratch / strategy, {late} | zero-shot success | zero-shot '
              'reward | training wall time [s] |', '|---|' + '---|' * (6 + int(maps))]

    def cell(row, key, digits, factor=1.0, unit=''):
        if key not in row:
            return '—'
        stat = row[key]
        return f"{factor * stat['mean']:.{digits}f} ± {factor * stat['sd']:.{digits}f}{unit}"

    for name, row in report['strategies'].items():
        spec = report.get('rows', {}).get(name, {'strategy': name, 'skill_map': 'elm'})
        label = f"{spec['strategy']} | {spec['skill_map']}" if maps else name
        lines.append(f"| {label} | {cell(row, 'total_rollouts', 1)} | "
                     f"{cell(row, 'late_rollouts', 2)} | {cell(row, 'speedup', 1, unit='×')} | "
                     f"{cell(row, 'zero_shot_success', 0, 100.0, ' %')} | "
                     f"{cell(row, 'zero_shot_reward', 3)} | {cell(row, 'train_seconds', 1)} |")
    t, rows = report['targets'], report['strategies']
    lines.append('')
    if 'runner' in report:
        lines.append(f"sessions run {report['runner']}; per node: " + ', '.join(
            f'{node} {count}' for node, count in report['nodes'].items()))
    for missing in report.get('missing', []):
        lines.append(f'MISSING (failed twice, left out of its rows): {missing}')
    lines.append('training wall time per rollout: ' + ', '.join(
        f"{name} {1e3 * row['train_seconds']['mean'] / max(row['total_rollouts']['mean'], 1):.1f} ms"
        for name, row in rows.items() if 'train_seconds' in row and 'total_rollouts' in row))
    if any('session_seconds' in row for row in rows.values()):
        lines.append('session wall time (training and held-out tasks), of it simulating: '
                     + ', '.join(f"{name} {row['session_seconds']['mean']:.1f} s, "
                                 f"{100 * row['simulation_share']['mean']:.0f} %"
                                 for name, row in rows.items() if 'session_seconds' in row))
    if any('ik_share' in row for row in rows.values()):
        lines.append('of it in the differential inverse kinematics (per candidate\'s path): '
                     + ', '.join(f"{name} {100 * row['ik_share']['mean']:.0f} % "
                                 f"({row['ik_ms_per_path']['mean']:.1f} ms"
                                 + (f"; {row['ik_paths']['mean']:.0f} paths solved, "
                                    f"{row['ik_reused']['mean']:.0f} taken again"
                                    if 'ik_paths' in row else '') + ')'
                                 for name, row in rows.items() if 'ik_share' in row))
    if any('held_out_goal_error' in row for row in rows.values()):
        lines.append('the hand\'s final miss on the held-out instances (mean): ' + ', '.join(
            f"{name} {1000 * row['held_out_goal_error']['mean']:.1f} mm"
            + (f" (median {1000 * row['held_out_goal_error_median']:.1f}, 90th percentile "
               f"{1000 * row['held_out_goal_error_p90']:.1f} mm)"
               if 'held_out_goal_error_median' in row else '')
            + (f", {row['held_out_orientation_error']['mean']:.3f} rad"
               if 'held_out_orientation_error' in row else '')
            for name, row in rows.items() if 'held_out_goal_error' in row))
    if any('tracking_learned' in row for row in rows.values()):
        lines.append('held-out tracking RMSE, PD only / learned feed-forward / oracle: ' + ', '.join(
            f"{name} " + ' / '.join(f"{row[f'tracking_{t}']['mean']:.4f}" for t in TRACKING)
            + ' rad' for name, row in rows.items() if 'tracking_learned' in row))
    consistent = {name: [b for b in CONSISTENCY if f'consistency_{b}' in row]
                  for name, row in rows.items()}
    if any(consistent.values()):
        lines.append('sample consistency (the skill\'s leave-one-out error on its own samples, '
                     'share of their spread): ' + '; '.join(
                         f"{name} " + ', '.join(f"{b} {row[f'consistency_{b}']['mean']:.2f}"
                                                for b in consistent[name])
                         for name, row in rows.items() if consistent[name]))
    lines.append('safety check, candidates refused (not executed) per session: ' + ', '.join(
        f"{name} {cell(row, 'refused', 1)} of {row['total_rollouts']['mean']:.0f}"
        for name, row in rows.items() if 'refused' in row))
    if 'speedup' in t:
        per_seed = ', '.join(f'{v:.1f}' for v in rows['bootstrap']['speedup']['values'])
        lines.append(f"target scratch / bootstrap ≥ {t['speedup']['min']:g}× ({late}): "
                     f"{t['speedup']['bootstrap']:.1f}× (per seed {per_seed}) — "
                     f"{'met' if t['speedup']['met'] else 'MISSED'} on the mean")
    z = t['zero_shot_success']
    lines.append(f"target zero-shot success ≥ {100 * z['min']:.0f} % after {s['num_tasks']} "
                 f"tasks, mean (lowest seed): " + '; '.join(
                     f"{k} {100 * rows[k]['zero_shot_success']['mean']:.0f} % "
                     f"({100 * rows[k]['zero_shot_success']['min']:.0f} %) "
                     f"{'met' if ok else 'MISSED'}" for k, ok in z['met'].items()))
    return '\n'.join(lines) + '\n'
