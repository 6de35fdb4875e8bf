"""Figure of the dynamics modality for one run folder of a task with feed-forward.

For one held-out task instance of the run (metrics.json ``summary.test_taus``) the skill in
the folder's memory.npz gives theta = [theta_K, theta_D]; three batch rollouts of the same
commanded path follow: PD only (theta_D = 0), learned (the skill's theta_D) and the oracle
(inverse dynamics from the simulator's model, `psl_optimizer.inverse_dynamics`). Top row, per
joint: commanded against executed joint angle; bottom row, per joint: the torque applied by
the controller and, dashed, the feed-forward part of it.

Uses matplotlib's object interface (``Figure``, Agg): no display, no pyplot state, no global
style. `psl plot` calls `plot_dynamics`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from psl_bench.plot_learning import load_run, run_task

VARIANTS = (('pd_only', 'PD only', 'tab:red'), ('learned', 'learned', 'tab:blue'),
            ('oracle', 'oracle', 'tab:green'))
FIGSIZE_PER_JOINT = (5.0, 6.5)    # inches, one column per joint
DPI = 100


def dynamics_rollouts(task, tau: np.ndarray, theta: np.ndarray) -> dict:
    """Batch rollouts of theta's commanded path on tau with PD only, theta's own theta_D and
    the oracle's (`feedforward_variants`): {variant: RolloutResult}.

    Raises:
        ValueError: a task without feed-forward.
    """
    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_optimizer.learning import feedforward_variants

    variants = feedforward_variants(task, tau, theta)
    results = BatchRollouts(task).run(np.vstack(list(variants.values())), tau)
    return dict(zip(variants, results))


def plot_dynamics(directory: str | Path, out_path: str | Path, test_index: int = 0) -> Path:
    """Write the dynamics figure of one held-out instance of a run folder as a PNG.

    Args:
        directory: an output folder of ``psl learn`` on a feed-forward task (metrics.json with
            a summary, memory.npz).
        out_path: the PNG file; its folder must exist.
        test_index: which held-out instance (index into ``summary.test_taus``).

    Returns:
        out_path as a Path.

    Raises:
        ValueError: the folder is not a finished run of a feed-forward task, has no memory,
            test_index is out of range, or its task does not load (`run_task`).
        OSError: the PNG cannot be written.
    """
    from psl_memory.skill_memory import SkillMemory
    from psl_task.arm_model import joint_names_of

    run = load_run(directory)
    metrics = run['metrics']
    summary = metrics.summary
    if not summary or run['memory_path'] is None:
        raise ValueError(f"{run['dir']}: needs a finished session (metrics.json summary) and "
                         'its memory.npz')
    taus = summary.test_taus
    if not 0 <= test_index < len(taus):
        raise ValueError(f'test_index {test_index} outside the {len(taus)} held-out tasks')
    task = run_task(metrics)           # a YAML task from its file, an embedded one by name
    tau = np.asarray(taus[test_index], dtype=float)
    theta = SkillMemory.read(run['memory_path']).get(task.name).query(tau)[0]
    rollouts = dynamics_rollouts(task, tau, theta)

    joints = joint_names_of(task)
    n = len(joints)
    fig = Figure(figsize=(FIGSIZE_PER_JOINT[0] * n, FIGSIZE_PER_JOINT[1]), dpi=DPI,
                 layout='constrained')
    axes = np.asarray(fig.subplots(2, n, sharex=True, squeeze=False))
    reference = rollouts['learned'].reference
    t = reference.t
    for j, name in enumerate(joints):
        ax_q, ax_u = axes[0, j], axes[1, j]
        ax_q.plot(t, reference.q[:, j], color='black', linestyle='--', linewidth=1.5,
                  label='commanded')
        for key, label, color in VARIANTS:
            result = rollouts[key]
            ref = result.reference
            rmse = np.sqrt(np.mean((result.q_ref - result.q) ** 2))
            ax_q.plot(t, result.q[:, j], color=color, linewidth=1.2,
                      label=f'{label} (RMSE {rmse:.4f} rad)')
            ax_u.plot(t, result.torque[:, j], color=color, linewidth=1.2, label=f'{label} torque')
            if key != 'pd_only':
                ax_u.plot(t, ref.u_ffwd[:, j], color=color, linewidth=1.0, linestyle=':',
                          label=f'{label} feed-forward')
        ax_q.axvline(task.duration, color='grey', linewidth=0.8)
        ax_u.axvline(task.duration, color='grey', linewidth=0.8)
        ax_q.set_title(f'{name}: joint angle')
        ax_q.set_ylabel('rad')
        ax_u.set_title(f'{name}: torque')
        ax_u.set_ylabel('N m')
        ax_u.set_xlabel('time [s] (grey: end of the motion)')
        ax_q.legend(fontsize=8)
        ax_u.legend(fontsize=8)
    tau_text = ', '.join(f'{name} = {value:.3g}' for name, value in zip(task.tau_names, tau))
    fig.suptitle(f"{task.name}: held-out instance {test_index} ({tau_text}), "
                 f"{metrics.strategy} seed {metrics.seed}", fontsize=11)
    out_path = Path(out_path)
    fig.savefig(out_path, format='png', dpi=DPI)
    return out_path
