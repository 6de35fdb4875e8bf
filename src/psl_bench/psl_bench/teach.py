"""``psl bench teach``: a skill taught with 3, 5 or 10 demonstrations against the single
demonstration of the task YAML: rollouts for the training tasks, zero-shot success after.

Method, per task and seed (batch mode, plain Python, no ROS):
1. The demonstrator's instances: a scratch session (``psl learn``'s `Learner`, seed 1000 +
   seed) solves ``max(counts)`` instances; its fulfilled samples (tau, theta) are what a person
   would show (instances solved, as a person knows how).
2. Each shown on the robot as a person's guided motion would be measured: the theta rolled
   out in batch mode with measurement noise (``noise``, 0.2 mrad on the angles by default),
   the measured joint angles of the whole episode, from rest to rest (the settling
   included), are the demonstration.
3. `psl_optimizer.teaching.teach_one` fits and checks each (the refused ones are counted), the
   first ``count`` accepted ones are the taught skill's samples.
4. A bootstrap session (seed ``seed``, ``num_tasks`` tasks) continues the taught skill
   (``continue_from`` it, ``continuation`` samples), against one from an empty skill (count
   0: the YAML demonstration only): total rollouts, rollouts per late task, zero-shot
   success on the held-out instances.
The path through a bag (psl record, psl teach) is tested in test_teach_graph.py; this bench
measures what the samples are worth.
"""
from __future__ import annotations

import dataclasses
import importlib
import tempfile
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from psl_bench import sessions
from psl_task import DEFAULT_TASK

COUNTS = (0, 3, 5, 10)
TASKS = (DEFAULT_TASK, 'planar_10dof_reach')
NOISE = 'position=0.0002'
THROUGH = ('batch', 'graph')    # how the demonstrations are shown and recorded
SHOWN = 3                   # instances shown through the graph per one to teach (refusals)
LATE = 20                   # rollouts per task are averaged over the tasks after this many


def demonstrator(task, count: int, seed: int, folder: Path):
    """The instances a person knows how to solve: the fulfilled samples of a scratch session
    (seed 1000 + seed) over max(3 count, 10) instances (the skill of its memory)."""
    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_optimizer.learning import Learner, LearnSettings

    settings = LearnSettings(strategy='scratch', num_tasks=max(3 * count, 10),
                             seed=1000 + seed, num_test=1)
    source = Learner(task, settings, folder / 'demonstrator', rollouts=BatchRollouts(task))
    source.run()
    return source.skill.memory.get(task.name)


def demonstrations(task_name: str, count: int, seed: int, noise: str, folder: Path
                   ) -> tuple[list, int]:
    """(tau, t, q) of `count` demonstrations accepted by `teach_one` and the number refused
    on the way (module docstring, 1-3)."""
    from psl_controller.policy import TaskPolicy
    from psl_optimizer import teaching
    from psl_optimizer.batch_rollout import BatchRollouts, MeasurementNoise
    from psl_task.arm_model import ArmModel
    from psl_task.safety_check import SafetyCheck
    from psl_task.task import load_task

    task = load_task(task_name)
    memory = demonstrator(task, count, seed, folder)
    robot = BatchRollouts(task, measurement_noise=MeasurementNoise.parse(
        f'{noise},seed={seed}'))
    policy, safety = TaskPolicy(task), SafetyCheck(ArmModel(task))
    shown, refused = [], 0
    for tau, theta in zip(memory.taus, memory.thetas):
        if len(shown) == count:
            break
        result = robot.run(np.asarray(theta)[None], tau)[0]
        t = np.arange(len(result.q)) * task.control_period      # the episode, rest to rest
        outcome = teaching.teach_one(task, policy, t, result.q, tau, safety=safety)
        if outcome.accepted:
            shown.append(outcome)
        else:
            refused += 1
    if len(shown) < count:
        raise ValueError(f'{task_name}: {len(shown)} of {count} demonstrations accepted '
                         f'({refused} refused): solve more instances')
    return shown, refused


def demonstrations_through_graph(task_name: str, count: int, seed: int, noise: str,
                                 folder: Path, robot: str = 'standard') -> tuple[list, int]:
    """(accepted outcomes, refused) of `count` demonstrations shown through the graph on the
    standard robot and recorded (module docstring); the first SHOWN x `count` solutions of
    the demonstrator are shown (psl teach refuses some: on planar_10dof_reach 9 of 14).
    ``robot='sim'``: on psl's lockstep simulator instead (drive resets too, no noise: it
    measures exactly)."""
    import threading

    from psl_memory.skill_memory import SkillMemory
    from psl_optimizer import teaching
    from psl_optimizer.batch_rollout import MeasurementNoise
    from psl_optimizer.learning import LearnSettings
    from psl_ros import names
    from psl_ros.bag_recorder import make_typestore, record
    from psl_ros.client import RosClient
    from psl_ros.graph import ROBOT_KINDS, Graph
    from psl_task.arm_model import joint_names_of
    from psl_task.task import load_task, task_id

    task = load_task(task_name)
    memory = demonstrator(task, count, seed, folder)
    shown = list(zip(memory.taus, memory.thetas))[:SHOWN * count]
    sigma = MeasurementNoise.parse(noise).position
    bag = folder / 'guided'
    loop = (('dmp_executor', 'psl_controller', 'dmp_executor'),
            ('reward_evaluator', 'psl_optimizer', 'reward_evaluator'))
    streams = ROBOT_KINDS[robot].clock == 'robot'   # a robot streams; the simulator pauses
    graph = Graph(task=task_id(task), robot=robot, reset='drive', nodes=loop,
                  log_dir=folder / 'graph_logs',
                  extra_params={'robot': {'position_noise': sigma, 'seed': seed}})
    counts: dict = {}
    stop = threading.Event()
    recorder = threading.Thread(target=record, args=(bag, ['/' + names.JOINT_STATES,
                                                           '/' + names.TASK_INSTANCE]),
                                kwargs={'stop': stop, 'discovery_timeout': 10.0,
                                        'progress': lambda r: counts.update(r.counts)})
    with graph, RosClient() as client:
        recorder.start()
        try:
            states = '/' + names.JOINT_STATES
            deadline = time.monotonic() + 60.0
            while states not in counts:                        # the recorder subscribed
                if time.monotonic() > deadline or not recorder.is_alive():
                    raise RuntimeError('the recorder did not subscribe to the joint states')
                stop.wait(0.05)
            if streams:                   # ... and takes what the robot streams
                while counts.get(states, 0) < 100:
                    if time.monotonic() > deadline or not recorder.is_alive():
                        raise RuntimeError('the recorder got no joint states from the robot')
                    stop.wait(0.05)
            else:                         # ... and is matched (the simulator's report)
                client.wait_for_subscribers([names.JOINT_STATES])
            for tau, theta in shown:
                result = client.rollout(task_id(task), tau, theta)
                if not result.success:
                    raise RuntimeError(f'showing tau {list(tau)}: {result.message}')
            # the last states in the bag: a robot streams on (the arm at rest after the last
            # motion: 0.5 s of it); the lockstep simulator is paused after the episode
            mark, last, quiet = counts.get(states, 0), -1, time.monotonic()
            while (counts.get(states, 0) < mark + 250 if streams
                   else time.monotonic() - quiet < 0.5):
                if not recorder.is_alive():
                    raise RuntimeError('the recorder ended early')
                if counts.get(states, 0) != last:
                    last, quiet = counts.get(states, 0), time.monotonic()
                stop.wait(0.05)
        finally:
            stop.set()
            recorder.join()
    recording = teaching.read_joint_states(bag, '/' + names.JOINT_STATES, joint_names_of(task))
    spans, _ = teaching.split_returns(task, recording, teaching.rest_to_rest(recording))
    taus = teaching.taus_from_topic(teaching.read_announcements(
        bag, '/' + names.TASK_INSTANCE, make_typestore()), recording, spans)
    outcomes = teaching.teach(task, recording, spans, taus, SkillMemory(LearnSettings().skill))
    accepted = [o for o in outcomes if o.accepted][:count]
    refused = sum(not o.accepted for o in outcomes)
    if len(accepted) < count:
        raise ValueError(f'{task_name}: {len(accepted)} of {count} demonstrations accepted '
                         f'({refused} refused) of {len(shown)} shown: show more')
    return accepted, refused


def session(task_name: str, taught: list, seed: int, num_tasks: int, num_test: int,
            budget: int, folder: Path) -> dict:
    """A bootstrap session from the taught skill (empty: none taught)."""
    from psl_memory.skill_memory import SkillMemory
    from psl_optimizer.batch_rollout import BatchRollouts
    from psl_optimizer.learning import Learner, LearnSettings
    from psl_controller.policy import policy_for
    from psl_task.task import load_task

    task = load_task(task_name)
    defaults = LearnSettings()
    continue_from = ''
    if taught:
        memory = SkillMemory(defaults.skill)
        memory.create(task.name, task.tau_low, task.tau_high, policy_for(task).default_theta)
        for outcome in taught:
            memory.add(task.name, outcome.tau, outcome.theta)
        folder.mkdir(parents=True, exist_ok=True)
        continue_from = str(folder / 'taught.npz')
        memory.save(continue_from)
    settings = LearnSettings(strategy='bootstrap', num_tasks=num_tasks, seed=seed,
                             num_test=num_test, continue_from=continue_from,
                             continuation='samples' if taught else '',
                             search=dataclasses.replace(defaults.search, max_rollouts=budget))
    learner = Learner(task, settings, folder / 'session', rollouts=BatchRollouts(task))
    metrics = learner.run()
    rollouts = [t.rollouts for t in metrics.tasks]
    return {'total_rollouts': int(sum(rollouts)),
            'late_rollouts': float(np.mean(rollouts[min(LATE, len(rollouts) - 1):])),
            'zero_shot_success': float(metrics.summary.zero_shot_success_rate)}


def teach_seed(task: str, seed: int, counts: Sequence[int], num_tasks: int, num_test: int,
               budget: int, noise: str, folder: str, through: str, robot: str) -> dict:
    """One task and seed of the sweep (`psl_bench.sessions`): the demonstrations shown once,
    then a session per count; ``rows`` and a ``summary``."""
    folder = Path(folder)
    if not max(counts):
        taught, refused = [], 0
    elif through == 'batch':
        taught, refused = demonstrations(task, max(counts), seed, noise, folder)
    else:
        taught, refused = demonstrations_through_graph(task, max(counts), seed, noise, folder,
                                                       robot)
    rows = []
    for count in counts:
        row = session(task, taught[:count], seed, num_tasks, num_test, budget,
                      folder / f'taught{count}')
        row.update(task=task, seed=seed, count=count, refused=refused)
        rows.append(row)
    return {'rows': rows, 'summary': ', '.join(
        f"{r['count']} taught: {r['total_rollouts']} rollouts, zero-shot "
        f"{100 * r['zero_shot_success']:.0f} %" for r in rows)}


def run(tasks: Sequence[str] = TASKS, counts: Sequence[int] = COUNTS,
        seeds: Sequence[int] = (0, 1, 2), num_tasks: int = 30, num_test: int = 20,
        budget: int = 300, noise: str = NOISE, out: str | Path | None = None,
        progress: Callable[[str], None] | None = None, through: str = 'batch',
        robot: str = 'standard', runner: str = 'serial', address: str | None = None) -> dict:
    """Every task x count x seed (module docstring); the report of `format_table`. Each task
    and seed is a session of `psl_bench.sessions` (`runner`, `address`); demonstrations shown
    through the graph run here, one after the other (Ray stays out of the ROS graph).

    Raises:
        ValueError: bad settings, a task that cannot be loaded (TaskError: its file named).
        RuntimeError: no session of the sweep finished (`psl_bench.sessions.run`).
    """
    if through not in THROUGH:
        raise ValueError(f'through must be one of {", ".join(THROUGH)}, got {through!r}')
    if robot not in ('standard', 'sim'):
        raise ValueError(f"robot must be 'standard' or 'sim', got {robot!r}")

    if not counts or min(counts) < 0 or len(set(counts)) != len(counts):
        raise ValueError(f'counts must be distinct and >= 0, got {list(counts)}')
    if num_tasks <= LATE:
        raise ValueError(f'num_tasks must exceed {LATE} (the late tasks), got {num_tasks}')
    from psl_task.task import load_task
    for task in tasks:
        load_task(task)             # a task file that cannot be read: refused before any work
    importlib.import_module('cma')
    with tempfile.TemporaryDirectory() as scratch:
        base = Path(out) if out is not None else Path(scratch)
        plan = [sessions.Session(
            key=(task, seed), label=f'{task} seed {seed}', function=teach_seed,
            kwargs=dict(task=task, seed=seed, counts=list(counts), num_tasks=num_tasks,
                        num_test=num_test, budget=budget, noise=noise,
                        folder=str(base / f'{Path(task).stem}-seed{seed}'), through=through,
                        robot=robot))
            for task in tasks for seed in seeds]
        swept = sessions.run(plan, runner if through == 'batch' else 'serial', address,
                             progress)
    rows = [row for s in plan if s.key in swept.records for row in swept.records[s.key]['rows']]
    return {'runner': swept.runner, 'nodes': swept.nodes, 'missing': swept.missing(), 'tasks': list(tasks), 'counts': list(counts), 'seeds': list(seeds),
            'num_tasks': num_tasks, 'num_test': num_test, 'budget': budget,
            'noise': noise if through == 'batch' or robot == 'standard' else 'none',
            'through': through if through == 'batch' else f'graph ({robot} robot)',
            'rows': rows}


def format_table(report: dict) -> str:
    """Markdown: per task and count the mean ± SD over seeds."""
    lines = [f"{report['num_tasks']} bootstrap tasks (budget {report['budget']}) from a skill "
             f"taught with N demonstrations (shown {report.get('through', 'batch')}, noise "
             f"{report['noise']}) or none (the YAML "
             f"demonstration only), seeds {report['seeds']}, zero-shot on "
             f"{report['num_test']} held-out instances", '',
             f'| task | taught | total rollouts | per task after {LATE} | zero-shot |',
             '|---|---|---|---|---|']
    for task in report['tasks']:
        for count in report['counts']:
            rows = [r for r in report['rows'] if r['task'] == task and r['count'] == count]

            def cell(key, scale=1.0, digits=1, unit=''):
                values = scale * np.array([r[key] for r in rows])
                return f'{values.mean():.{digits}f} ± {values.std():.{digits}f}{unit}'
            lines.append(f"| {Path(task).stem} | {count or 'none'} | {cell('total_rollouts')} "
                         f"| {cell('late_rollouts', digits=2)} | "
                         f"{cell('zero_shot_success', 100.0, 0, ' %')} |")
    refused = sum(r['refused'] for r in report['rows'] if r['count'] == max(report['counts']))
    lines.append(f'\ndemonstrations refused by psl teach\'s checks on the way: {refused}')
    for missing in report.get('missing', []):
        lines.append(f'MISSING (failed twice): {missing}')
    return '\n'.join(lines) + '\n'
