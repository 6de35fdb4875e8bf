"""Where the hybrid strategy's rollouts go (docs/benchmarks.md, task variability section).

    python scripts/hybrid_phases.py [TASK] [SEEDS]      # default planar_10dof_reach, 5 seeds

Runs hybrid sessions of 30 tasks in batch mode (the learner's defaults, run folders in a
temporary directory) and splits each task's rollouts into the first one (PS(tau) itself), the
coarse phase (CMA-ES over tau' with theta = PS(tau')) and the refinement (CMA-ES in theta
space), by wrapping `policy_search.cma_search` (the coarse phase is the call with a
``patience``); prints the mean per block of ten tasks over the seeds.
"""
import shutil
import sys
import tempfile

import numpy as np
import psl_optimizer.learning as L
import psl_optimizer.policy_search as PS
from psl_optimizer.learning import Learner, LearnSettings
from psl_optimizer.rollout_modes import make_rollouts
from psl_task.task import load_task

phase_log = []           # (task index, phase, rollouts, fulfilled at end)
current = {'task': -1}
orig = PS.cma_search


def logged(budget, x0, to_theta, sigma0, popsize, seed, max_rollouts, **kw):
    phase = 'coarse' if 'patience' in kw and kw['patience'] is not None else 'refine'
    before = len(budget.rewards)
    orig(budget, x0, to_theta, sigma0, popsize, seed, max_rollouts, **kw)
    phase_log.append((current['task'], phase, len(budget.rewards) - before, budget.fulfilled))


PS.cma_search = logged
orig_search = PS.search


def search(*a, **k):
    current['task'] += 1
    return orig_search(*a, **k)


L.search = search
task = load_task(sys.argv[1] if len(sys.argv) > 1 else 'planar_10dof_reach')
seeds = int(sys.argv[2]) if len(sys.argv) > 2 else 5
root = tempfile.mkdtemp(prefix='psl-hybrid-phases-')
out = []
for seed in range(seeds):
    phase_log.clear(); current['task'] = -1
    folder = f'{root}/seed{seed}'
    m = Learner(task, LearnSettings(strategy='hybrid', num_tasks=30, seed=seed), folder,
                make_rollouts('batch', task)).run()
    r = np.array([t.rollouts for t in m.tasks])
    for block in range(3):
        idx = range(10 * block, 10 * block + 10)
        coarse = sum(n for t, p, n, _ in phase_log if p == 'coarse' and t in idx)
        refine = sum(n for t, p, n, _ in phase_log if p == 'refine' and t in idx)
        coarse_runs = sum(1 for t, p, n, _ in phase_log if p == 'coarse' and t in idx)
        coarse_ok = sum(1 for t, p, n, ok in phase_log if p == 'coarse' and t in idx and ok)
        first_ok = sum(1 for t in idx if r[t] == 1)
        out.append((seed, block, r[list(idx)].sum(), first_ok, coarse_runs, coarse_ok, coarse, refine))
a = np.array(out, dtype=float)
for block in range(3):
    b = a[a[:, 1] == block].mean(axis=0)
    print(f'tasks {10*block+1}-{10*block+10}: rollouts {b[2]:.0f}; solved by PS(tau) alone {b[3]:.1f} of 10; '
          f'coarse phase ran on {b[4]:.1f} tasks, solved {b[5]:.1f}, {b[6]:.0f} rollouts; refinement {b[7]:.0f} rollouts')
shutil.rmtree(root, ignore_errors=True)
