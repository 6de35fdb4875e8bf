"""Learning results as a fingerprint: what a set of sessions decided and computed, recorded once
and checked again after a change or on another machine.

Each session of SESSIONS runs as ``psl learn`` (batch mode, the public command line, so the
check does not depend on the code it checks) into a temporary folder; its fingerprint keeps,
from its metrics.json and memory.npz, what it learned. Floats are kept as ``float.hex`` strings
(a bit-exact record). Two kinds of entries, compared differently:

- **decisions**, compared exactly on any machine: the task instances drawn (the session's
  random generator: the same bits everywhere), the rollouts each task took, fulfilled or not,
  the held-out instances and the zero-shot success rate, and which samples the skill holds
  (how many, at which instances);
- **computed floats** (rewards, tracking errors, the samples' thetas), compared within
  RELATIVE_TOLERANCE: OpenBLAS's kernels and numpy's SIMD paths sum and round in an order
  of the CPU's (measured across the five x86-64 OpenBLAS kernels: 4.3e-11 relative at most,
  after hundreds of rollouts); on one machine they are bit-identical, which ``bit_identical``
  asks for (a restructuring recorded before and checked after, on the same machine).

`check` runs the sessions with the OpenBLAS kernel the record names when this CPU can run it
(fewer last-bit differences), else with this process's. Used by scripts/learning_identity.py
and by the suite (src/psl_bench/test/test_learning_identity.py).
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

from psl_bench.openblas import current_kernel, environment, runnable_kernels
from psl_task import DEFAULT_TASK

REACH = DEFAULT_TASK     # reach_over_obstacle
# (label, psl learn arguments)
SESSIONS = (
    ('scratch', ['--task', REACH, '--strategy', 'scratch', '--tasks', '20',
                 '--seed', '4711']),
    ('bootstrap', ['--task', REACH, '--strategy', 'bootstrap', '--tasks', '20',
                   '--seed', '4711']),
    ('hybrid', ['--task', REACH, '--strategy', 'hybrid', '--tasks', '20',
                '--seed', '4711']),
    ('bootstrap_cost', ['--task', REACH, '--strategy', 'bootstrap_cost',
                        '--tasks', '20', '--seed', '4711']),
    ('variance_selection', ['--task', REACH, '--strategy', 'bootstrap',
                            '--tasks', '10', '--seed', '4711', '--task-selection', 'variance']),
    ('reach_4dof', ['--task', 'reach_4dof', '--strategy', 'bootstrap', '--tasks', '10',
                    '--seed', '4711']),
    ('payload_ilc', ['--task', 'payload_transport', '--strategy', 'bootstrap', '--tasks', '5',
                     '--seed', '4711', '--test-tasks', '5']),
)
TASK_DECISIONS = ('tau', 'rollouts', 'fulfilled')
TASK_FLOATS = ('best_reward', 'start_reward')
SUMMARY_DECISIONS = ('total_rollouts', 'rollouts_per_task', 'test_taus',
                     'zero_shot_success_rate')
SAMPLE_DECISIONS = ('count', 'taus')
RELATIVE_TOLERANCE = 1e-9     # computed floats between machines (measured: at most 4.3e-11)


def _exact(value):
    """Floats as hex strings (bit-exact), containers recursively, the rest as it is."""
    if isinstance(value, float):
        return value.hex()
    if isinstance(value, (list, tuple)):
        return [_exact(v) for v in value]
    if hasattr(value, 'tolist'):
        return _exact(value.tolist())
    return value


def fingerprint(run_dir: Path) -> dict:
    """What the session in `run_dir` (its metrics.json and memory.npz) learned."""
    from psl_memory.skill_memory import SkillMemory
    metrics = json.loads((run_dir / 'metrics.json').read_text())
    summary = metrics['summary']
    kept = {key: _exact(value) for key, value in summary.items()
            if key in SUMMARY_DECISIONS or key in ('test_rewards', 'zero_shot_mean_reward')
            or key.startswith('tracking_rmse_')}
    skill = SkillMemory.read(run_dir / 'memory.npz').get(metrics['task'])
    return {'tasks': [{key: _exact(t[key]) for key in TASK_DECISIONS + TASK_FLOATS}
                      for t in metrics['tasks']],
            'summary': kept,
            'samples': {'count': skill.num_samples, 'taus': _exact(skill.taus),
                        'thetas': _exact(skill.thetas)}}


def run_session(arguments: list[str], kernel: str, folder: Path) -> dict:
    """One ``psl learn`` session (`arguments`) with the OpenBLAS `kernel`, into `folder`; its
    fingerprint. RuntimeError with its output if it fails."""
    command = [sys.executable, '-m', 'psl_cli.main', 'learn', *arguments, '--out', str(folder)]
    done = subprocess.run(command, capture_output=True, text=True, env=environment(kernel))
    if done.returncode != 0:
        raise RuntimeError(f'psl learn {" ".join(arguments)} failed ({done.returncode}):\n'
                           f'{done.stderr[-3000:]}')
    return fingerprint(folder)


def run_all(kernel: str, selected: list[str] | None = None,
            sessions=SESSIONS, log=None) -> dict:
    """label -> fingerprint of each session (of `selected`, default all)."""
    out = {}
    with tempfile.TemporaryDirectory(prefix='psl-identity-') as folder:
        for label, arguments in sessions:
            if selected and label not in selected:
                continue
            if log is not None:
                log(f'OPENBLAS_CORETYPE={kernel} psl learn {" ".join(arguments)}')
            out[label] = run_session(arguments, kernel, Path(folder) / label)
    return out


def _float(value) -> float | None:
    """A float kept as hex, or None for anything else."""
    if isinstance(value, str):
        try:
            return float.fromhex(value)
        except ValueError:
            return None
    return None


def same(a, b, bit_identical: bool) -> bool:
    """a == b; a computed float (hex) within RELATIVE_TOLERANCE unless `bit_identical`;
    lists element by element."""
    if a == b:
        return True
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y, bit_identical) for x, y in zip(a, b))
    x, y = _float(a), _float(b)
    if bit_identical or x is None or y is None:
        return False
    return math.isclose(x, y, rel_tol=RELATIVE_TOLERANCE, abs_tol=0.0)


def differences(reference: dict, now: dict, bit_identical: bool = False) -> list[str]:
    """What differs between two fingerprints of the same sessions (labels in both): every
    decision exactly, every computed float within RELATIVE_TOLERANCE (or bit for bit)."""
    found = []
    for label, ref in reference.items():
        if label not in now:
            continue
        got = now[label]
        if len(ref['tasks']) != len(got['tasks']):
            found.append(f'{label}: {len(ref["tasks"])} tasks != {len(got["tasks"])}')
        for k, (a, b) in enumerate(zip(ref['tasks'], got['tasks'])):
            for key in TASK_DECISIONS:
                if a[key] != b[key]:
                    found.append(f'{label}: task {k} {key} (a decision): {a[key]} != {b[key]}')
            for key in TASK_FLOATS:
                if not same(a[key], b[key], bit_identical):
                    found.append(f'{label}: task {k} {key}: {a[key]} != {b[key]}')
        for key in sorted(set(ref['summary']) | set(got['summary'])):
            a, b = ref['summary'].get(key), got['summary'].get(key)
            if key in SUMMARY_DECISIONS and a != b:
                found.append(f'{label}: summary {key} (a decision) differs: {a} != {b}')
            elif key not in SUMMARY_DECISIONS and not same(a, b, bit_identical):
                found.append(f'{label}: summary {key} differs')
        if 'samples' in ref:        # recorded with the skill's samples
            a, b = ref['samples'], got.get('samples', {})
            for key in SAMPLE_DECISIONS:
                if a.get(key) != b.get(key):
                    found.append(f'{label}: the skill\'s samples ({key}, a decision) differ')
            if not same(a.get('thetas'), b.get('thetas'), bit_identical):
                found.append(f'{label}: the skill\'s sample thetas differ')
    return found


def check_kernel(recorded_kernel: str) -> str:
    """The kernel a check runs with: the record's where this CPU runs it, else this one's."""
    return recorded_kernel if recorded_kernel in runnable_kernels() else current_kernel()


def main(argv=None) -> int:
    import argparse
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('action', choices=('record', 'check'))
    parser.add_argument('file', type=Path)
    parser.add_argument('--only', nargs='+', help='session labels (default: all)')
    parser.add_argument('--kernel', help='the OpenBLAS kernel to run with (default: record: '
                        "this process's; check: the file's, if this CPU can run it)")
    parser.add_argument('--bit-identical', action='store_true',
                        help='check: every float bit for bit too (the same machine as the '
                             'record: a restructuring)')
    args = parser.parse_args(argv)

    def log(line: str) -> None:
        print(line, file=sys.stderr, flush=True)
    if args.action == 'record':
        kernel = args.kernel or current_kernel()
        now = run_all(kernel, args.only, log=log)
        args.file.write_text(json.dumps({'openblas_kernel': kernel, 'sessions': now},
                                        indent=1) + '\n')
        print(f'recorded {len(now)} sessions with the OpenBLAS kernel {kernel} into {args.file}')
        return 0
    recorded = json.loads(args.file.read_text())
    reference, recorded_kernel = recorded['sessions'], recorded['openblas_kernel']
    kernel = args.kernel or check_kernel(recorded_kernel)
    now = run_all(kernel, args.only, log=log)
    found = differences(reference, now, args.bit_identical)
    for line in found:
        print(line)
    checked = [label for label in now if label in reference]
    promise = ('bit-identical' if args.bit_identical else
               f'the same decisions, floats within {RELATIVE_TOLERANCE:g} relative (kernel '
               f'{kernel}; recorded with {recorded_kernel})')
    print(f'{len(checked)} sessions checked ({", ".join(checked)}): '
          + (promise if not found else f'{len(found)} differences from "{promise}"'))
    return 1 if found or not checked else 0
