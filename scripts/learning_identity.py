#!/usr/bin/env python3
"""Learning results as a fingerprint, to show a restructuring kept them bit-identical.

Runs ``psl learn`` (batch mode, the public command line, so the script does not depend on the
code it checks) for each session of SESSIONS into a temporary folder and keeps, from each
metrics.json, what the session learned: per task the instance, rollouts, fulfilled, best and
start reward; the held-out test rewards and zero-shot success; for a feed-forward task the
held-out tracking errors. Floats are kept as ``float.hex`` strings: equal means bit-identical.

    scripts/learning_identity.py record docs/learning_identity.json   # before a change
    scripts/learning_identity.py check docs/learning_identity.json    # after it: exit 1 if not

Run it after ``source scripts/env.sh``. Bit-identity holds on one machine and one set of pinned
wheels; BLAS kernels differ between CPU kinds, so a file recorded elsewhere may differ in the
last bits (the check says where).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

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


def run_all(selected: list[str] | None) -> dict:
    out = {}
    with tempfile.TemporaryDirectory(prefix='psl-identity-') as folder:
        for label, arguments in SESSIONS:
            if selected and label not in selected:
                continue
            run_dir = Path(folder) / label
            command = ['psl', 'learn', *arguments, '--out', str(run_dir)]
            print(' '.join(command), file=sys.stderr, flush=True)
            subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
            out[label] = fingerprint(json.loads((run_dir / 'metrics.json').read_text()))
    return out


def differences(reference: dict, now: dict) -> list[str]:
    found = []
    for label, ref in reference.items():
        if label not in now:
            continue
        got = now[label]
        for k, (a, b) in enumerate(zip(ref['tasks'], got['tasks'])):
            for key in TASK_KEYS:
                if a[key] != b[key]:
                    found.append(f'{label}: task {k} {key}: {a[key]} != {b[key]}')
        if len(ref['tasks']) != len(got['tasks']):
            found.append(f'{label}: {len(ref["tasks"])} tasks != {len(got["tasks"])}')
        for key in sorted(set(ref['summary']) | set(got['summary'])):
            if ref['summary'].get(key) != got['summary'].get(key):
                found.append(f'{label}: summary {key} differs')
    return found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('action', choices=('record', 'check'))
    parser.add_argument('file', type=Path)
    parser.add_argument('--only', nargs='+', help='session labels (default: all)')
    args = parser.parse_args(argv)
    now = run_all(args.only)
    if args.action == 'record':
        args.file.write_text(json.dumps(now, indent=1) + '\n')
        print(f'recorded {len(now)} sessions into {args.file}')
        return 0
    reference = json.loads(args.file.read_text())
    found = differences(reference, now)
    for line in found:
        print(line)
    checked = [label for label in now if label in reference]
    print(f'{len(checked)} sessions checked ({", ".join(checked)}): '
          + ('bit-identical' if not found else f'{len(found)} differences'))
    return 1 if found or not checked else 0


if __name__ == '__main__':
    sys.exit(main())
