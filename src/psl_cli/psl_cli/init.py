"""``psl init``: a task file from a robot description as published, in one command.

``psl init MODEL --end-effector LINK [--kind pose]`` writes a commented point- (or pose-)
reaching task for the chain
from the base (``--base``, default the world) to LINK: the joints, the locked rest, the gains,
the postures, the end-effector point and the target box all from the model
(`psl_optimizer.task_generator`), checked as ``psl check`` checks it. A model that cannot
be made a task (unreadable, an unknown link, a link not below the base, no joint to drive)
gets one line and exit code 2; nothing is written.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from psl_cli.options import fail

KINDS = ('point', 'pose')   # task_generator.KINDS, not imported here (MuJoCo at start-up)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument('model', help='the URDF or MJCF: a path or package://NAME/... (as a task '
                   "file's robot.model)")
    p.add_argument('--end-effector', required=True, metavar='LINK',
                   help='the link (body) whose point reaches the target')
    p.add_argument('--base', metavar='LINK',
                   help='the link the driven chain starts from (default: the world); every '
                   'joint off the chain is locked')
    p.add_argument('--posture', type=float, nargs='+', metavar='Q',
                   help='the start posture, one value per driven joint (base outward) '
                   '[rad (m)] (default: drawn from the ranges)')
    p.add_argument('--kind', default='point', choices=KINDS,
                   help='the task: point (reach a target point) or pose (a point and a '
                   'turn about the vertical; 6 driven joints or more) (default point)')
    p.add_argument('--out', '-o', metavar='FILE',
                   help='the task file to write (default: <model>_<link>_<kind>_reach.yaml)')
    p.add_argument('--force', action='store_true', help='overwrite FILE if it exists')


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from psl_optimizer.task_generator import InitError, generate

    stem = Path(args.model.split('/')[-1]).stem
    out = Path(args.out or f'{stem}_{args.end_effector}_{args.kind}_reach.yaml')
    if out.exists() and not args.force:
        return fail('psl init', f'{out} exists: give another --out, or --force', 2)
    try:
        generated = generate(args.model, args.end_effector, out, base=args.base,
                             posture=None if args.posture is None else np.array(args.posture),
                             kind=args.kind)
    except InitError as exc:
        return fail('psl init', exc, 2)
    if generated.warnings:        # the generator fits until psl check has none: say so
        return fail('psl init', f'psl check warns about the draft: {generated.warnings[0]}', 1)
    try:
        out.write_text(generated.text)
    except OSError as exc:
        return fail('psl init', exc, 1)
    task = generated.task
    worst = max(miss for _, miss in generated.reach)
    box = [p for p in task.parameters if p.binds.kind == 'target_position']
    turns = [p for p in task.parameters if p.binds.kind == 'target_orientation']
    print(f'wrote {out}: {len(task.start_posture)} driven joints, target box '
          + ' x '.join(f'{100 * (p.high - p.low):.1f}' for p in box) + ' cm'
          + ''.join(f', {p.name} +-{(p.high - p.low) / 2:.2f} rad' for p in turns)
          + f', every corner reached within {1000 * worst:.1f} mm; psl check: no warnings')
    return 0
