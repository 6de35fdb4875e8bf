#!/usr/bin/env python3
"""Learning results as a fingerprint, to show a restructuring kept them bit-identical.

Runs ``psl learn`` (batch mode, the public command line, so the script does not depend on the
code it checks) for each session of SESSIONS into a temporary folder and keeps, from each
metrics.json, what the session learned: per task the instance, rollouts, fulfilled, best and
start reward; the held-out test rewards and zero-shot success; for a feed-forward task the
held-out tracking errors. Floats are kept as ``float.hex`` strings: equal means bit-identical.

    scripts/learning_identity.py record docs/learning_identity.json   # before a change
    scripts/learning_identity.py check docs/learning_identity.json    # after it: exit 1 if not

Run it after ``source scripts/env.sh``. What is promised (README, "What is equal to what"):
- with the OpenBLAS kernel the file was recorded with, bit-identical. The file names that
  kernel, and `check` runs the sessions with it (OPENBLAS_CORETYPE) whenever this CPU can run
  it, so the comparison is bit for bit on any machine with that kernel's instructions;
- with another kernel (a CPU that cannot run the recorded one; or ``--kernel``), the same
  decisions (instances, rollouts, fulfilled, zero-shot success) and every float within a
  relative RELATIVE_TOLERANCE: the kernels sum matrix products in other orders (measured
  across the five x86-64 kernels: floats apart by up to 4.3e-11 relative).
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

from psl_bench.openblas import current_kernel, environment, runnable_kernels

# (label, psl learn arguments); the first three are the ones issue 11 names
SESSIONS = (
    ('scratch', ['--task', 'reach_over_obstacle', '--strategy', 'scratch', '--tasks', '20',
                 '--seed', '4711']),
    ('bootstrap', ['--task', 'reach_over_obstacle', '--strategy', 'bootstrap', '--tasks', '20',
                   '--seed', '4711']),
    ('hybrid', ['--task', 'reach_over_obstacle', '--strategy', 'hybrid', '--tasks', '20',
                '--seed', '4711']),
    ('bootstrap_cost', ['--task', 'reach_over_obstacle', '--strategy', 'bootstrap_cost',
                        '--tasks', '20', '--seed', '4711']),
    ('variance_selection', ['--task', 'reach_over_obstacle', '--strategy', 'bootstrap',
                            '--tasks', '10', '--seed', '4711', '--task-selection', 'variance']),
    ('reach_4dof', ['--task', 'reach_4dof', '--strategy', 'bootstrap', '--tasks', '10',
                    '--seed', '4711']),
    ('payload_ilc', ['--task', 'payload_transport', '--strategy', 'bootstrap', '--tasks', '5',
                     '--seed', '4711', '--test-tasks', '5']),
)
TASK_KEYS = ('tau', 'rollouts', 'fulfilled', 'best_reward', 'start_reward')
RELATIVE_TOLERANCE = 1e-9     # between OpenBLAS kernels (measured: at most 4.3e-11)


def _exact(value):
    """Floats as hex strings (bit-exact), containers recursively, the rest as it is."""
    if isinstance(value, float):
        return value.hex()
    if isinstance(value, list):
        return [_exact(v) for v in value]
    return value


def fingerprint(metrics: dict) -> dict:
    summary = metrics['summary']
    kept = {key: _exact(value) for key, value in summary.items()
            if key in ('test_taus', 'test_rewards', 'zero_shot_success_rate',
                       'zero_shot_mean_reward', 'total_rollouts', 'rollouts_per_task')
            or key.startswith('tracking_rmse_')}
    return {'tasks': [{key: _exact(t[key]) for key in TASK_KEYS} for t in metrics['tasks']],
            'summary': kept}


def run_all(selected: list[str] | None, kernel: str) -> dict:
    out = {}
    env = environment(kernel)
    with tempfile.TemporaryDirectory(prefix='psl-identity-') as folder:
        for label, arguments in SESSIONS:
            if selected and label not in selected:
                continue
            run_dir = Path(folder) / label
            command = ['psl', 'learn', *arguments, '--out', str(run_dir)]
            print(f'OPENBLAS_CORETYPE={kernel} ' + ' '.join(command), file=sys.stderr,
                  flush=True)
            subprocess.run(command, check=True, stdout=subprocess.DEVNULL, env=env)
            out[label] = fingerprint(json.loads((run_dir / 'metrics.json').read_text()))
    return out


def _float(value):
    """A float kept as hex, or None for anything else."""
    if isinstance(value, str):
        try:
            return float.fromhex(value)
        except ValueError:
            return None
    return None


def same(a, b, exact: bool) -> bool:
    """a == b; without `exact`, floats (hex strings) within RELATIVE_TOLERANCE."""
    if exact or a == b:
        return a == b
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y, exact) for x, y in zip(a, b))
    x, y = _float(a), _float(b)
    if x is None or y is None:
        return False
    return math.isclose(x, y, rel_tol=RELATIVE_TOLERANCE, abs_tol=0.0)


def differences(reference: dict, now: dict, exact: bool = True) -> list[str]:
    found = []
    for label, ref in reference.items():
        if label not in now:
            continue
        got = now[label]
        for k, (a, b) in enumerate(zip(ref['tasks'], got['tasks'])):
            for key in TASK_KEYS:
                if not same(a[key], b[key], exact):
                    found.append(f'{label}: task {k} {key}: {a[key]} != {b[key]}')
        if len(ref['tasks']) != len(got['tasks']):
            found.append(f'{label}: {len(ref["tasks"])} tasks != {len(got["tasks"])}')
        for key in sorted(set(ref['summary']) | set(got['summary'])):
            if not same(ref['summary'].get(key), got['summary'].get(key), exact):
                found.append(f'{label}: summary {key} differs')
    return found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('action', choices=('record', 'check'))
    parser.add_argument('file', type=Path)
    parser.add_argument('--only', nargs='+', help='session labels (default: all)')
    parser.add_argument('--kernel', help='the OpenBLAS kernel to run with (default: record: '
                        "this process's; check: the file's, if this CPU can run it)")
    args = parser.parse_args(argv)
    if args.action == 'record':
        kernel = args.kernel or current_kernel()
        now = run_all(args.only, kernel)
        args.file.write_text(json.dumps({'openblas_kernel': kernel, 'sessions': now},
                                        indent=1) + '\n')
        print(f'recorded {len(now)} sessions with the OpenBLAS kernel {kernel} into {args.file}')
        return 0
    recorded = json.loads(args.file.read_text())
    reference, recorded_kernel = recorded['sessions'], recorded['openblas_kernel']
    kernel = args.kernel or (recorded_kernel if recorded_kernel in runnable_kernels()
                             else current_kernel())
    exact = kernel == recorded_kernel
    now = run_all(args.only, kernel)
    found = differences(reference, now, exact)
    for line in found:
        print(line)
    checked = [label for label in now if label in reference]
    promise = ('bit-identical' if exact else
               f'the same decisions, floats within {RELATIVE_TOLERANCE:g} relative (kernel '
               f'{kernel}; recorded with {recorded_kernel})')
    print(f'{len(checked)} sessions checked ({", ".join(checked)}): '
          + (promise if not found else f'{len(found)} differences from "{promise}"'))
    return 1 if found or not checked else 0


if __name__ == '__main__':
    sys.exit(main())
