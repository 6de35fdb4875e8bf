"""``psl bench rollout``: batch mode against raw ``mujoco.rollout`` on the same population.

Batch mode (DMP references, controls, ``mujoco.rollout``, rewards) and ``mujoco.rollout`` alone
on the same model with the same controls, back to back in every repeat (so a drifting load
hits both alike), and where batch mode's extra time goes. Imports no ROS.
"""
from __future__ import annotations

import statistics
import time

import numpy as np

from psl_task import DEFAULT_TASK


def measure(task_name: str = DEFAULT_TASK, population: int = 32,
            repeats: int = 7) -> dict:
    """Steps per second of both, their ratio (of medians, and the median of the paired
    ratios) and the milliseconds per population of each part of batch mode."""
    from mujoco import rollout as mj_rollout

    from psl_optimizer.batch_rollout import CONTROL, BatchRollouts, stacked
    from psl_task.task import load_task

    if population < 1 or repeats < 1:
        raise ValueError('population and repeats must be at least 1')
    task = load_task(task_name)
    batch = BatchRollouts(task)
    rng = np.random.default_rng(0)
    default = batch.policy.default_theta
    thetas = default + rng.normal(0.0, 0.1 * np.abs(default).max(), (population, default.size))
    taus = np.array([task.sample_tau(rng) for _ in range(population)])
    control = batch.controls(*stacked(batch.policy.references(thetas, taus)), taus)
    steps = population * control.shape[1]
    raw, full, refs, ctrls = [], [], [], []
    for _ in range(repeats):
        start = time.perf_counter()
        mj_rollout.rollout(batch.model, batch.datas, batch.initial_state[None], control,
                           control_spec=CONTROL, persistent_pool=True)
        raw.append(time.perf_counter() - start)
        start = time.perf_counter()
        batch.run(thetas, taus)
        full.append(time.perf_counter() - start)
        start = time.perf_counter()                  # where batch mode's extra time goes
        references = batch.policy.references(thetas, taus)
        refs.append(time.perf_counter() - start)
        start = time.perf_counter()
        batch.controls(*stacked(references), taus)
        ctrls.append(time.perf_counter() - start)
    med = statistics.median
    report = {'task': task.name, 'population': population, 'repeats': repeats,
              'steps_per_rollout': control.shape[1], 'threads': len(batch.datas),
              'raw_steps_per_second': steps / med(raw),
              'batch_steps_per_second': steps / med(full),
              'ratio_paired_median': med([r / f for r, f in zip(raw, full)]),
              'ms_per_population': {'total': 1e3 * med(full), 'mujoco_rollout': 1e3 * med(raw),
                                    'references': 1e3 * med(refs), 'controls': 1e3 * med(ctrls),
                                    'rewards_and_rest': 1e3 * (med(full) - med(raw) - med(refs)
                                                               - med(ctrls))}}
    report['ratio'] = report['batch_steps_per_second'] / report['raw_steps_per_second']
    return report


def format_report(report: dict) -> str:
    ms = report['ms_per_population']
    return (f"raw mujoco.rollout: {report['raw_steps_per_second']:.0f} steps/s; batch mode "
            f"(DMP references, controls, rollout, rewards): "
            f"{report['batch_steps_per_second']:.0f} steps/s; ratio {report['ratio']:.2f} "
            f"(paired median {report['ratio_paired_median']:.2f}; population "
            f"{report['population']}, {report['threads']} threads)\n"
            'ms per population: ' + ', '.join(f'{k} {v:.1f}' for k, v in ms.items()) + '\n')
