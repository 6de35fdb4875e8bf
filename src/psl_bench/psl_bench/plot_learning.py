"""``psl plot``: one PNG figure of one or more learning runs (output folders of ``psl learn``).

Panels:
  (a) rollouts per task against the task index, one line per strategy: a single run as it is,
      several seeds of one strategy as their mean with a min-max band;
  (b) reward over tau for the first run: each training instance's best reward (marker: fulfilled
      or not) and the held-out instances' zero-shot rewards; reward against tau for a 1-D tau,
      a scatter over the first two tau dimensions coloured by reward otherwise;
  (c) predictive variance of the first run's skill over the tau range (`variance_grid`): a curve
      for a 1-D tau, a heat map over the first two dimensions otherwise (the rest held at the
      centre of their ranges), with the training instances on top. A skill whose readout has no
      variance (e.g. 'incremental_ridge') gets a Bayesian readout fitted to its stored samples
      for the plot (`bayesian_stand_in`); the panel title says so.

A run without memory.npz, with an unreadable one, or without a summary (an incomplete session)
is drawn with what it has; a missing or corrupt metrics.json is a ValueError naming the file.
Uses matplotlib's object interface (``Figure``, Agg), so no display, no pyplot state and no
global style change. Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from matplotlib import colors
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter

from psl_memory.parameterized_skill import ParameterizedSkill
from psl_memory.skill_memory import MemoryFileError, SkillMemory
from psl_optimizer.metrics import METRICS_FILE, Metrics, read_metrics

FIGSIZE = (18.0, 5.5)        # inches
DPI = 100                    # the PNG is FIGSIZE * DPI pixels: 1800 x 550
GRID_POINTS = 60             # per tau dimension in the variance panel
LOG_RANGE = 10.0             # a positive quantity spanning more than this factor gets a log axis
PLAIN = FuncFormatter(lambda value, _: f'{value:g}')     # tick labels 0.01, 20, 300


# -- loading ----------------------------------------------------------------------------------
def load_run(directory: str | Path) -> dict[str, Any]:
    """Read and check one run folder.

    Args:
        directory: an output folder of ``psl learn`` (holds metrics.json, maybe memory.npz).

    Returns:
        {'dir': Path, 'metrics': its `Metrics`, 'memory_path': Path or None when the folder
        has no memory.npz}.

    Raises:
        ValueError: the folder does not exist, or its metrics.json is missing, not JSON, or
            lacks what the plot needs; the message names the file.
    """
    folder = Path(directory)
    if not folder.is_dir():
        raise ValueError(f'{folder}: no such folder')
    metrics = read_metrics(folder)              # MetricsError (a ValueError) names the file
    _check_drawable(metrics, folder / METRICS_FILE)
    memory = folder / 'memory.npz'
    return {'dir': folder, 'metrics': metrics,
            'memory_path': memory if memory.is_file() else None}


def _check_drawable(metrics: Metrics, path: Path) -> None:
    """ValueError naming `path` unless the numbers the plot draws are finite and of one size."""
    taus = [_float_array(t.tau, path, 'tau') for t in metrics.tasks]
    _float_array([t.best_reward for t in metrics.tasks], path, 'best_reward')
    summary = metrics.summary
    if summary is not None:
        test_taus = _float_array(summary.test_taus, path, 'test_taus')
        rewards = _float_array(summary.test_rewards, path, 'test_rewards')
        if test_taus.ndim != 2 or rewards.shape != (test_taus.shape[0],):
            raise ValueError(f'{path}: corrupt metrics (test_taus {test_taus.shape} and '
                             f'test_rewards {rewards.shape} do not match)')
        taus += list(test_taus)
    if len({np.shape(t) for t in taus}) > 1 or any(np.ndim(t) != 1 for t in taus):
        raise ValueError(f'{path}: corrupt metrics (task parameters tau of different sizes)')


def _float_array(value: Any, path: Path, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{path}: corrupt metrics ({name} is not finite)')
    return array


def run_label(run: dict[str, Any]) -> str:
    """'strategy seed K' of a run from `load_run`."""
    m = run['metrics']
    return f"{m.strategy} seed {m.seed}"


# -- variance over tau ------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class VarianceGrid:
    """The mean per-dimension predictive variance of theta on a regular grid over tau.

    axes: one (n,) array per plotted tau dimension (the first one or two).
    values: (n,) for one plotted dimension; (n, n) for two, row i at axes[1][i], column j at
        axes[0][j] (the layout of ``pcolormesh(axes[0], axes[1], values)``).
    centre: (E,) the tau that dimensions beyond the first two are held at (their range centre).
    fitted: True when the skill's readout has no variance and a Bayesian readout was fitted to
        its samples for this grid (`bayesian_stand_in`).
    num_samples: samples of the skill.
    """

    axes: tuple[np.ndarray, ...]
    values: np.ndarray
    centre: np.ndarray
    fitted: bool
    num_samples: int


def bayesian_stand_in(skill: ParameterizedSkill) -> ParameterizedSkill:
    """The skill with the Bayesian readout ('bayes', eq. 2.12-2.14) in place of its own, fed
    the same samples (`ParameterizedSkill.refitted`); the precisions come from the skill's
    configuration, so with fixed precisions and beta = 1 its mean is the skill's ridge mean
    (eq. 2.8) and only the variance is new."""
    return skill.refitted(dataclasses.replace(skill.config, readout='bayes'))


def variance_grid(skill: ParameterizedSkill, n: int = GRID_POINTS) -> VarianceGrid:
    """Query `skill` on an n (x n) grid over its tau range (the range of its tau scaler).

    Args:
        skill: a parameterized skill; if its readout gives no variance, a Bayesian readout
            fitted to its samples is queried instead (``fitted`` is then True).
        n: grid points per plotted dimension, >= 2.

    Returns:
        The grid; values are the mean over theta's dimensions of the predictive variance from
        ``query`` (theta's units squared), so > 0.

    Raises:
        ValueError: n < 2.
    """
    if int(n) < 2:
        raise ValueError(f'a grid needs n >= 2 points per dimension, got {n}')
    n = int(n)
    low, high = skill.tau_scaler.low, skill.tau_scaler.high
    centre = 0.5 * (low + high)                                   # (E,)
    model, fitted = skill, skill.query(centre)[1] is None
    if fitted:
        model = bayesian_stand_in(skill)
    axes = tuple(np.linspace(low[d], high[d], n) for d in range(min(2, skill.tau_dim)))
    mesh = np.meshgrid(*axes)                                    # each (n,) or (n, n)
    points = np.tile(centre, (mesh[0].size, 1))                  # (n or n*n, E)
    for d, coordinate in enumerate(mesh):
        points[:, d] = coordinate.ravel()
    values = np.array([np.mean(model.query(p)[1]) for p in points]).reshape(mesh[0].shape)
    return VarianceGrid(axes, values, centre, fitted, skill.num_samples)


# -- the figure -------------------------------------------------------------------------------
def plot_runs(dirs: Sequence[str | Path], out_path: str | Path,
              grid_points: int = GRID_POINTS) -> Path:
    """Write the figure of the runs in `dirs` (panels: see the module docstring) as a PNG.

    Args:
        dirs: run folders; all are checked before anything is drawn. Panels (b) and (c) show
            the first one.
        out_path: the PNG file; its folder must exist.
        grid_points: grid points per tau dimension in the variance panel.

    Returns:
        out_path as a Path.

    Raises:
        ValueError: no folders, or one that `load_run` refuses.
        OSError: the PNG cannot be written.
    """
    if not dirs:
        raise ValueError('give at least one run folder')
    runs = [load_run(d) for d in dirs]
    out_path = Path(out_path)
    first = runs[0]
    names, threshold = _task_info(first['metrics'])
    fig = Figure(figsize=FIGSIZE, dpi=DPI, layout='constrained')
    ax_rollouts, ax_reward, ax_variance = fig.subplots(1, 3)
    _draw_rollouts(ax_rollouts, runs)
    _draw_rewards(fig, ax_reward, first, names, threshold)
    _draw_variance(fig, ax_variance, first, names, grid_points)
    fig.suptitle(f"Learning runs: {', '.join(sorted({r['metrics'].task for r in runs}))}"
                 f"  (b, c: {run_label(first)}, {first['dir']})", fontsize=11)
    fig.savefig(out_path, format='png', dpi=DPI)
    return out_path


def run_task(metrics: Metrics):
    """A run's task (`psl_task.task.TaskDefinition`): from its YAML where it was learned
    (`Metrics.task_path`), else by name on the task search path (an embedded task, a run
    older than task_path).

    Raises:
        ValueError: neither loads (the file has gone and no task of that name is found).
    """
    from psl_task.task import TaskError, load_task
    reasons = []
    for source in (metrics.task_path, metrics.task):
        try:
            if source:
                return load_task(source)
        except (OSError, TaskError) as exc:
            reasons.append(str(exc))
    raise ValueError(f"the run's task {metrics.task!r} does not load: " + '; '.join(reasons))


def _task_info(metrics: Metrics) -> tuple[list[str] | None, float | None]:
    """Axis names 'name [unit]' of tau and the success threshold of a run's task: from
    `run_task`, or from the copy of the YAML text the metrics keep; (None, None) when none of
    them gives them."""
    import yaml
    try:
        task = run_task(metrics)
        names = [f'{p.name} [{p.unit}]' if p.unit else p.name for p in task.parameters]
        return names, task.reward.success_threshold
    except ValueError:
        pass
    try:
        data = yaml.safe_load(metrics.task_yaml) if metrics.task_yaml else None
        names = [f"{p['name']} [{p['unit']}]" if p.get('unit') else str(p['name'])
                 for p in data['task_parameters']]
        return names, float(data['reward']['success_threshold'])
    except (yaml.YAMLError, TypeError, KeyError, ValueError):
        return None, None


def _tau_name(names: list[str] | None, d: int, dim: int) -> str:
    if names is not None and len(names) == dim:
        return names[d]
    return f'tau[{d}]'


def _message(ax: Axes, title: str, text: str) -> None:
    ax.set_title(title, fontsize=10)
    ax.text(0.5, 0.5, text, ha='center', va='center', wrap=True, transform=ax.transAxes)
    ax.set_xticks([])
    ax.set_yticks([])


def _progress(metrics: Metrics) -> str:
    """'' for a complete run, else ' (incomplete: k/N tasks)'."""
    if metrics.complete:
        return ''
    return f" (incomplete: {len(metrics.tasks)}/{metrics.num_tasks} tasks)"


def _flat(settings: dict, prefix: str = '') -> dict[str, str]:
    """Nested settings as {'search.max_rollouts': '200', ...}."""
    out = {}
    for key, value in settings.items():
        if isinstance(value, dict):
            out.update(_flat(value, f'{prefix}{key}.'))
        else:
            out[f'{prefix}{key}'] = json.dumps(value)
    return out


def group_label(run: dict[str, Any], runs: list[dict[str, Any]]) -> str:
    """What a run is averaged with: its strategy, and its task and every setting (but the
    seed) in which the runs differ — seeds of one experiment share a curve, runs of different
    tasks or settings (a 15-task batch session and a 2-task graph session) are drawn apart."""
    flats = [_flat(r['metrics'].settings) for r in runs]
    keys = sorted(set().union(*flats))
    differ = [k for k in keys if k != 'seed' and len({f.get(k) for f in flats}) > 1]
    m, flat = run['metrics'], _flat(run['metrics'].settings)
    label = m.strategy
    if len({r['metrics'].task for r in runs}) > 1:
        label = f'{m.task}: {label}'
    extra = [f'{k}={json.loads(flat[k]) if k in flat else "?"}' for k in differ
             if k != 'strategy']
    return f"{label} ({', '.join(extra)})" if extra else label


def _draw_rollouts(ax: Axes, runs: list[dict[str, Any]]) -> None:
    """Panel (a): rollouts per task, grouped by `group_label` (seeds of one experiment)."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for run in runs:
        groups.setdefault(group_label(run, runs), []).append(run)
    positive = True
    for i, (key, members) in enumerate(groups.items()):
        colour = f'C{i % 10}'
        length = max((r.index for m in members for r in m['metrics'].tasks), default=-1) + 1
        if length == 0:
            ax.plot([], [], color=colour, label=f'{key}: no task finished')
            continue
        rollouts = np.full((len(members), length), np.nan)      # (runs, tasks)
        for k, run in enumerate(members):
            for record in run['metrics'].tasks:
                rollouts[k, record.index] = record.rollouts
        positive = positive and bool(np.nanmin(rollouts) > 0)
        index = np.arange(length)
        totals = np.nansum(rollouts, axis=1)
        if len(members) == 1:
            run = members[0]
            label = (f"{key} seed {run['metrics'].seed}: {totals[0]:.0f} rollouts"
                     f"{_zero_shot(run['metrics'])}{_progress(run['metrics'])}")
            ax.plot(index, rollouts[0], 'o-', color=colour, ms=4, label=label)
            continue
        seeds = ', '.join(str(r['metrics'].seed) for r in members)
        rates = [r['metrics'].summary.zero_shot_success_rate for r in members
                 if r['metrics'].summary is not None]
        zero_shot = f', zero-shot {100 * np.mean(rates):.0f} %' if rates else ''
        ax.plot(index, np.nanmean(rollouts, axis=0), 'o-', color=colour, ms=4,
                label=f'{key}, mean of seeds {seeds}: {np.mean(totals):.0f} rollouts{zero_shot}')
        ax.fill_between(index, np.nanmin(rollouts, axis=0), np.nanmax(rollouts, axis=0),
                        color=colour, alpha=0.2, lw=0, label=f'{key}: min-max over seeds')
    ax.set_title('(a) rollouts per task instance', fontsize=10)
    ax.set_xlabel('task index (order of learning)')
    ax.set_ylabel('rollouts to solve the task')
    if positive:
        ax.set_yscale('log')
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(PLAIN)
        ax.yaxis.set_minor_formatter(NullFormatter())
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc='upper center', bbox_to_anchor=(0.5, -0.1), frameon=False)


def _zero_shot(metrics: Metrics) -> str:
    if metrics.summary is None:
        return ''
    return f", zero-shot {100 * metrics.summary.zero_shot_success_rate:.0f} %"


def _reward_norm(rewards: np.ndarray) -> colors.Normalize:
    """Symmetric-log colour scale: rewards reach from -0.005 (solved) to -5 (crashed)."""
    low, high = float(np.min(rewards)), float(np.max(rewards))
    if low == high:
        low, high = low - 0.5, high + 0.5
    nonzero = np.abs(rewards[rewards != 0])
    linthresh = float(np.min(nonzero)) if nonzero.size else 1.0
    return colors.SymLogNorm(linthresh=linthresh, vmin=low, vmax=high, base=10)


def _draw_rewards(fig: Figure, ax: Axes, run: dict[str, Any], names: list[str] | None,
                  threshold: float | None) -> None:
    """Panel (b): best training rewards and held-out zero-shot rewards over tau."""
    m = run['metrics']
    title = f'(b) reward over tau: {run_label(run)}{_progress(m)}'
    tasks, summary = m.tasks, m.summary
    taus = np.array([t.tau for t in tasks], dtype=float)                  # (N, E)
    best = np.array([t.best_reward for t in tasks], dtype=float)          # (N,)
    done = np.array([t.fulfilled for t in tasks], dtype=bool)             # (N,)
    test_taus = np.array(summary.test_taus, dtype=float) if summary else np.zeros((0, 0))
    test_rewards = np.array(summary.test_rewards, dtype=float) if summary else np.zeros(0)
    if summary:
        title += (f"\nheld-out zero-shot success {100 * summary.zero_shot_success_rate:.0f} %"
                  f", mean reward {summary.zero_shot_mean_reward:.3g}")
    else:
        title += '\nno held-out test yet'
    if not tasks and not summary:
        _message(ax, title, 'no task finished yet')
        return
    dim = taus.shape[1] if tasks else test_taus.shape[1]
    taus, test_taus = taus.reshape(-1, dim), test_taus.reshape(-1, dim)
    rewards = np.r_[best, test_rewards]
    if dim == 1:
        ax.plot(taus[done, 0], best[done], 'o', color='C0', label='training: best reward, '
                'fulfilled')
        ax.plot(taus[~done, 0], best[~done], 'X', color='C3', ms=8,
                label='training: best reward, not fulfilled')
        ax.plot(test_taus[:, 0], test_rewards, '^', color='C2', mfc='none',
                label='held-out: zero-shot reward')
        if threshold is not None:
            ax.axhline(threshold, color='k', ls='--', lw=1, label='success threshold')
        norm = _reward_norm(np.r_[rewards, [] if threshold is None else [threshold]])
        ax.set_yscale('symlog', linthresh=norm.linthresh)
        ax.yaxis.set_major_formatter(PLAIN)
        low, high = norm.vmin, norm.vmax          # margins: the axis would run to +-0.1
        ax.set_ylim(low * 2 if low < 0 else low - norm.linthresh,
                    high * 2 if high > 0 else high + 0.5 * norm.linthresh)
        ax.set_xlabel(_tau_name(names, 0, dim))
        ax.set_ylabel('reward (symmetric log scale)')
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc='best')
        ax.set_title(title, fontsize=10)
        return
    norm, cmap = _reward_norm(rewards), 'viridis'
    style = {'cmap': cmap, 'norm': norm, 'edgecolors': 'k', 'linewidths': 0.6}
    image = ax.scatter(taus[done, 0], taus[done, 1], c=best[done], marker='o', s=55, **style)
    ax.scatter(taus[~done, 0], taus[~done, 1], c=best[~done], marker='X', s=90, **style)
    ax.scatter(test_taus[:, 0], test_taus[:, 1], c=test_rewards, marker='^', s=55, **style)
    bar = fig.colorbar(image, ax=ax, format=PLAIN)
    label = 'reward (symmetric log scale)'
    if threshold is not None and norm.vmin <= threshold <= norm.vmax:
        bar.ax.axhline(threshold, color='r', lw=2)
        label += '; red: success threshold'
    bar.set_label(label)
    grey = {'ls': 'none', 'mfc': '0.7', 'mec': 'k'}
    handles = [Line2D([], [], marker='o', label='training, fulfilled: best reward', **grey),
               Line2D([], [], marker='X', ms=9, label='training, not fulfilled', **grey),
               Line2D([], [], marker='^', label='held-out: zero-shot reward', **grey)]
    ax.legend(handles=handles, fontsize=8, loc='upper center', bbox_to_anchor=(0.5, -0.1),
              ncol=2, frameon=False)
    ax.set_xlabel(_tau_name(names, 0, dim))
    ax.set_ylabel(_tau_name(names, 1, dim))
    if dim > 2:
        title += ' (tau[2:] not shown)'
    ax.set_title(title, fontsize=10)


def _draw_variance(fig: Figure, ax: Axes, run: dict[str, Any], names: list[str] | None,
                   grid_points: int) -> None:
    """Panel (c): the skill's predictive variance over the tau range, samples on top."""
    m = run['metrics']
    title = f'(c) predictive variance of theta: {run_label(run)}'
    if run['memory_path'] is None:
        _message(ax, title, f"no memory.npz in {run['dir']}")
        return
    try:
        skill = SkillMemory.read(run['memory_path']).get(m.task)
    except (MemoryFileError, KeyError) as exc:
        _message(ax, title, f'cannot plot the skill: {exc}')
        return
    grid = variance_grid(skill, grid_points)
    if grid.fitted:
        precisions = 'estimated' if skill.config.estimate_precisions else 'fixed'
        title += (f"\nthe run's readout '{skill.config.readout}' gives no variance: a Bayesian"
                  f' readout\n({precisions} precisions) was fitted to its {grid.num_samples} '
                  'samples for this plot')
    else:
        title += f"\nthe run's readout '{skill.config.readout}', {grid.num_samples} samples"
        if skill.config.readout == 'bayes':
            title += (f" ({'estimated' if skill.config.estimate_precisions else 'fixed'} "
                      'precisions)')
    dim = skill.tau_dim
    values = grid.values
    log = bool(values.max() > LOG_RANGE * values.min())
    failed = np.array([t.tau for t in m.tasks if not t.fulfilled],
                      dtype=float).reshape(-1, dim)
    samples = skill.taus                                                  # (N, E)
    if dim == 1:
        ax.plot(grid.axes[0], values, color='C4', label='mean predictive variance')
        bottom = values.min()
        ax.plot(samples[:, 0], np.full(len(samples), bottom), '|', color='k', ms=18, mew=1.5,
                label='samples in the skill')
        ax.plot(failed[:, 0], np.full(len(failed), bottom), 'x', color='C3', ms=8,
                label='training: not fulfilled (not stored)')
        if log:
            ax.set_yscale('log')
        ax.set_xlabel(_tau_name(names, 0, dim))
        ax.set_ylabel('mean predictive variance of theta')
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc='best')
        ax.set_title(title, fontsize=10)
        return
    norm = (colors.LogNorm if log else colors.Normalize)(vmin=values.min(), vmax=values.max())
    mesh = ax.pcolormesh(grid.axes[0], grid.axes[1], values, norm=norm, cmap='magma',
                         shading='auto')
    bar = fig.colorbar(mesh, ax=ax, label='mean predictive variance of theta'
                       + (' (log scale)' if log else ''))
    if log:        # label the minor ticks (20, 30, ...) too when there are few decades
        bar.ax.yaxis.set_major_formatter(PLAIN)
        few = values.max() < LOG_RANGE**2 * values.min()
        bar.ax.yaxis.set_minor_formatter(PLAIN if few else NullFormatter())
    ax.scatter(samples[:, 0], samples[:, 1], marker='o', s=30, facecolors='w',
               edgecolors='k', linewidths=0.8, label=f'samples in the skill ({len(samples)})')
    if len(failed):
        ax.scatter(failed[:, 0], failed[:, 1], marker='X', s=60, color='C2', edgecolors='k',
                   linewidths=0.6, label='training: not fulfilled (not stored)')
    ax.legend(fontsize=8, loc='upper center', bbox_to_anchor=(0.5, -0.1), ncol=2,
              frameon=False)
    ax.set_xlabel(_tau_name(names, 0, dim))
    ax.set_ylabel(_tau_name(names, 1, dim))
    if dim > 2:
        title += ' (tau[2:] at their range centre)'
    ax.set_title(title, fontsize=10)
