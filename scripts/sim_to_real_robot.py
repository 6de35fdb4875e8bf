#!/usr/bin/env python3
"""Sim to real on a robot psl does not simulate: the table of docs/benchmarks.md ("Sim to real
on a robot's own JointTrajectoryController").

The robot: test/jtc_robot.py (MuJoCo on the wall clock with its own JointTrajectoryController on
the effort interface, written from JTC's source; its own joint order, an extra joint, masses and
inertias +30 %, joint damping +0.3 N m s/rad and friction +0.05 N m, 1 mrad / 10 mrad/s of
measurement noise, one period of latency, the task's gains), driven by ``psl up --robot external
--controller /arm_controller``. Per task (a copy of the embedded YAML with ``reward:
{smoothness_of: reference}``, which noise needs, and ``homing: {settle_time: 1.0}``):

1. ``nominal``: a skill learned in batch mode on the task's model (30 tasks, seed 3);
2. ``before``: that skill's answers at each seed's held-out instances, rolled out on the robot;
3. per seed: ``scratch`` (``psl learn --mode graph --learner here`` from an empty skill) and
   ``continued`` (the same with ``--continue-from`` the nominal skill, the residual way), the
   same training and held-out instances.

Writes ``OUT/<task>/...`` (each session's metrics.json) and ``OUT/summary_<task>.json``; prints the
table. Runs for an hour or two (a rollout on the wall clock takes 4-7 s). After ``source
scripts/env.sh``:

    scripts/sim_to_real_robot.py --out runs/s2r_robot --seeds 11 12 13 --tasks 10 --test 10
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
TASKS = ('reach_over_obstacle', 'payload_transport')
CONTROLLER = 'arm_controller'


def task_copy(name: str, folder: Path) -> Path:
    """The embedded task with the smoothness of the reference and a second to settle."""
    from psl_task.task import EMBEDDED_TASKS, load_task
    task = load_task(name)
    data = yaml.safe_load((EMBEDDED_TASKS / f'{name}.yaml').read_text())
    data['model'] = str(task.model_path)
    data.setdefault('reward', {})['smoothness_of'] = 'reference'
    data.setdefault('homing', {})['settle_time'] = 1.0
    path = folder / f'{name}.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


def start_robot(name: str, folder: Path) -> subprocess.Popen:
    from psl_task.arm_model import joint_names_of
    from psl_task.task import load_task
    task = load_task(name)
    joints = joint_names_of(task)
    order = list(reversed(joints))
    index = [joints.index(j) for j in order]
    command = [sys.executable, str(ROOT / 'test' / 'jtc_robot.py'), '--model',
               str(task.model_path), '--joints', *order,
               '--start', *map(str, task.start_posture[index] + 0.2), '--interface', 'effort',
               '--controller', CONTROLLER,
               '--kp', *map(str, np.asarray(task.controller.kp)[index]),
               '--kd', *map(str, np.asarray(task.controller.kd)[index])]
    if task.policy.feedforward:
        command += ['--payload', 'payload:0']
    return subprocess.Popen(command, stdout=open(folder / 'robot.log', 'wb'),
                            stderr=subprocess.STDOUT, start_new_session=True)


def psl(*args: str, log: Path) -> None:
    """A psl command, its output in `log`; RuntimeError if it fails."""
    with open(log, 'ab') as out:
        code = subprocess.call(['psl', *args], stdout=out, stderr=subprocess.STDOUT)
    if code != 0:
        raise RuntimeError(f'psl {" ".join(args)} failed ({code}); see {log}')


def before(task_path: Path, memory: Path, seed: int, count: int) -> dict:
    """The nominal skill's answers at the held-out instances of `seed`, on the robot."""
    from psl_memory.skill_memory import SkillMemory
    from psl_optimizer.task_selection import held_out_tasks
    from psl_ros.client import RosClient
    from psl_task.task import load_task
    task = load_task(str(task_path))
    skill = SkillMemory.read(memory).get(task.name)
    rewards, fulfilled = [], []
    with RosClient() as client:
        for tau in held_out_tasks(task, count, seed):
            result = client.rollout(str(task_path), tau, skill.query(tau)[0], timeout=300)
            if not result.success:
                raise RuntimeError(result.message)
            rewards.append(result.evaluation.reward)
            fulfilled.append(result.evaluation.fulfilled)
    return {'zero_shot': float(np.mean(fulfilled)), 'rewards': rewards}


def summary(path: Path) -> dict:
    s = json.loads((path / 'metrics.json').read_text())['summary']
    return {'rollouts': s['total_rollouts'], 'zero_shot': s['zero_shot_success_rate'],
            'fulfilled': s['fulfilled_tasks'], 'tracking': s.get('tracking_rmse_mean')}


def run_task(name: str, out: Path, seeds: list[int], tasks: int, test: int,
             budget: int, ways: list[str]) -> dict:
    folder = out / name
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / 'psl.log'
    task_path = task_copy(name, folder)
    nominal = folder / 'nominal'
    if not (nominal / 'memory.npz').exists():
        psl('learn', '--task', str(task_path), '--tasks', '30', '--seed', '3', '--out',
            str(nominal), log=log)
    robot = start_robot(name, folder)
    graph = subprocess.Popen(['psl', 'up', '--task', str(task_path), '--robot', 'external',
                              '--controller', f'/{CONTROLLER}', '--joint-states',
                              '/joint_states', '--memory-dir', str(folder), '--log-dir',
                              str(folder / 'graph_logs')],
                             stdout=open(folder / 'up.log', 'wb'), stderr=subprocess.STDOUT,
                             start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while 'graph ready' not in (folder / 'up.log').read_text():
            if graph.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f'psl up did not come up: {(folder / "up.log").read_text()}')
            time.sleep(0.5)
        rows = {}
        for seed in seeds:
            row = {'before': before(task_path, nominal / 'memory.npz', seed, test)}
            for way, extra in (('scratch', []),
                               ('continued', ['--continue-from',
                                              str(nominal / 'memory.npz')])):
                if way not in ways:
                    continue
                session = folder / f'{way}-seed{seed}'
                psl('learn', '--task', str(task_path), '--mode', 'graph', '--learner', 'here',
                    '--tasks', str(tasks), '--seed', str(seed), '--test-tasks', str(test),
                    '--budget', str(budget), '--out', str(session), *extra, log=log)
                row[way] = summary(session)
            rows[seed] = row
            print(name, seed, json.dumps(row), flush=True)
        return rows
    finally:
        for process in (graph, robot):
            try:
                os.killpg(process.pid, signal.SIGINT if process is graph else signal.SIGKILL)
                process.wait(timeout=30)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                os.killpg(process.pid, signal.SIGKILL)


def table(results: dict) -> str:
    lines = ['| task | seed | rollouts scratch | rollouts continued | zero-shot: simulated skill '
             '/ scratch / continued |', '|---|---|---|---|---|']
    for name, rows in results.items():
        for seed, row in list(rows.items()) + [('all', None)]:
            if row is None:
                rs = [rows[s] for s in rows]
                sums = {w: sum(r[w]['rollouts'] for r in rs) if all(w in r for r in rs)
                        else '—' for w in ('scratch', 'continued')}
                zs = {w: f"{100 * np.mean([r[w]['zero_shot'] for r in rs]):.0f}"
                      if all(w in r for r in rs) else '—'
                      for w in ('before', 'scratch', 'continued')}
            else:
                sums = {w: row[w]['rollouts'] if w in row else '—'
                        for w in ('scratch', 'continued')}
                zs = {w: f"{100 * row[w]['zero_shot']:.0f}" if w in row else '—'
                      for w in ('before', 'scratch', 'continued')}
            lines.append(f"| {name} | {seed} | {sums['scratch']} | {sums['continued']} | "
                         f"{zs['before']} / {zs['scratch']} / {zs['continued']} % |")
    return '\n'.join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--out', default='runs/s2r_robot')
    parser.add_argument('--tasks-of', nargs='+', default=list(TASKS), dest='names')
    parser.add_argument('--seeds', nargs='+', type=int, default=[11, 12, 13])
    parser.add_argument('--tasks', type=int, default=10)
    parser.add_argument('--test', type=int, default=10)
    parser.add_argument('--budget', type=int, default=100)
    parser.add_argument('--ways', nargs='+', choices=('scratch', 'continued'),
                        default=['scratch', 'continued'],
                        help='the sessions per seed (the simulated skill is always rolled out)')
    args = parser.parse_args()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in args.names:
        results[name] = run_task(name, out, args.seeds, args.tasks, args.test, args.budget,
                                 args.ways)
        (out / f'summary_{name}.json').write_text(json.dumps(results[name], indent=1))
    print(table(results))
    return 0


if __name__ == '__main__':
    sys.exit(main())
