#!/usr/bin/env python3
"""The throwing task's learned throws (ball_throw): a figure and whether they form charts.

    psl bench learn --task ball_throw ... -o RUNS          # the sessions, kept
    scripts/throwing_figure.py RUNS -o docs/figures/ball_throw.png [--json FILE]

For every session folder under RUNS (its memory.npz: the skill's samples, one learned theta
per training task), every sample is rolled out again in batch mode and its ball's flight
described: the launch angle and speed (the ball's velocity where the free flight that ends at
its landing began: from there on its acceleration is gravity's) and the flight's apex. da
Silva et al. (ICML 2012) found the policies of a throwing skill on a piecewise-smooth manifold:
several charts, one regression each. Here the charts would show as separate branches of launch
angle over target distance (a high lob and a flat throw reach the same target). The figure:
(left) the ball's paths of zero-shot throws of one learned skill at targets across the range,
(right) launch angle over target distance for the samples of every session, by strategy.
Run it after ``source scripts/env.sh``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

G = 9.81
FREE = 0.5          # m/s^2: a state flies freely when its acceleration is within this of -g


def flight(world: np.ndarray, dt: float, height: float) -> dict:
    """Launch angle [deg] and speed [m/s] of a ball's path (T, 7) — its velocity where the free
    flight that ends at its landing (the first time its centre comes down through `height`)
    began — and the highest point of that flight [m]."""
    p = world[:, :3]
    acc = np.diff(p, n=2, axis=0) / dt**2                 # acc[i]: at state i + 1
    free = np.linalg.norm(acc - [0.0, 0.0, -G], axis=1) < FREE
    down = np.flatnonzero((p[:-1, 2] > height) & (p[1:, 2] <= height))
    k = int(down[0]) if len(down) else len(p) - 2       # the state before the landing
    while k > 1 and free[k - 2]:                         # back while state k - 1 flies freely
        k -= 1
    v = (p[k + 1] - p[k - 1]) / (2 * dt)
    return {'apex': float(p[k:, 2].max()), 'launch_angle': float(np.degrees(np.arctan2(
        v[2], np.hypot(v[0], v[1])))), 'speed': float(np.linalg.norm(v)), 'release_step': k}


def samples_of(path: Path, task: str) -> tuple[np.ndarray, np.ndarray]:
    """The (tau, theta) samples of a session's memory.npz: the skill memory's (elm), or a
    baseline skill map's samples file (library, gp)."""
    from psl_memory.skill_memory import MemoryFileError, SkillMemory

    try:
        skill = SkillMemory.read(path).get(task)
        return skill.taus, skill.thetas
    except MemoryFileError:
        with np.load(path, allow_pickle=False) as data:
            return data['taus'], data['thetas']


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('runs', type=Path, help='psl bench learn -o folder')
    parser.add_argument('-o', '--output', type=Path, required=True, help='figure (.png)')
    parser.add_argument('--json', type=Path, help='also write every sample\'s flight here')
    parser.add_argument('--skill', default='ball_throw-bootstrap-seed0',
                        help='the session whose skill throws the zero-shot throws')
    args = parser.parse_args()

    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from psl_memory.skill_memory import SkillMemory
    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_optimizer.landing import landing_points
    from psl_task.task import load_task

    task = load_task('ball_throw')
    rollouts = BatchRollouts(task)
    samples = []
    for folder in sorted(p.parent for p in args.runs.glob('*/memory.npz')):
        taus, thetas = samples_of(folder / 'memory.npz', task.name)
        for tau, result in zip(taus, rollouts.run(thetas, taus)):
            samples.append({'session': folder.name, 'tau': float(tau[0]),
                            'landing_error': result.evaluation.components.get(
                                'landing_error', float('nan')),
                            **flight(result.world['ball'], task.control_period,
                                     task.target.position[2])})
    if not samples:
        print(f'no session with a memory.npz under {args.runs}', file=sys.stderr)
        return 1
    skill = SkillMemory.read(args.runs / args.skill / 'memory.npz').get(task.name)
    targets = np.linspace(task.tau_low[0], task.tau_high[0], 5)
    thrown = rollouts.run(np.array([skill.query([t])[0] for t in targets]), targets[:, None])

    figure, (paths, charts) = plt.subplots(1, 2, figsize=(11, 4.2))
    for target, result in zip(targets, thrown):
        ball = result.world['ball']
        point, _ = landing_points(ball[None], np.array([task.target.position[2]]))
        line, = paths.plot(ball[:, 0], ball[:, 2], lw=1.2)
        paths.plot([target], [0.0], 'v', color=line.get_color(), ms=8)
        paths.plot([point[0, 0]], [point[0, 2]], 'o', color=line.get_color(), ms=4)
    paths.axhline(0.0, color='0.6', lw=0.8)
    paths.set(xlabel='x [m]', ylabel='z [m]', aspect='equal',
              title=f'zero-shot throws of {args.skill}\n(targets ▼, landings ●)')
    strategies = sorted({s['session'].split('-')[1] for s in samples})
    for strategy in strategies:
        mine = [s for s in samples if s['session'].split('-')[1] == strategy]
        charts.plot([s['tau'] for s in mine], [s['launch_angle'] for s in mine], '.',
                    alpha=0.6, label=f'{strategy} ({len(mine)} samples)')
    charts.set(xlabel='target distance [m]', ylabel='launch angle [deg]',
               title='every learned sample of every session')
    charts.legend(fontsize=8)
    figure.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.output, dpi=110)
    if args.json:
        args.json.write_text(json.dumps(samples, indent=1))
    angles = np.array([s['launch_angle'] for s in samples])
    print(f'{len(samples)} samples of {len({s["session"] for s in samples})} sessions: '
          f'launch angle {angles.min():.1f}..{angles.max():.1f} deg; figure {args.output}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
