"""``psl bench sim-to-real``: a skill learned in simulation, continued on a robot whose model is
wrong (batch mode: the robot is the task's model with a `psl_task.model_error.ModelError`,
optionally measurement noise and a controller of its own gains).

Method, per task:
- ``nominal``: a `Learner` session on the task's own model (seed ``nominal_seed``,
  ``nominal_tasks`` tasks): the simulated skill PS_sim and its memory file;
- the robot: the task's model with ``model_error``, the joint states measured with
  ``measurement_noise`` (`psl_optimizer.batch_rollout.MeasurementNoise`), and the controller's
  gains ``robot_gains`` times the task's (a robot whose own controller is tuned otherwise:
  the robot's task is a copy of the task YAML that differs only in its controller gains,
  `robot_task`, and a skill of the task continues across, the name and sizes being the same);
- per robot seed of ``seeds``: ``before``, PS_sim executed once on each held-out instance of
  the seed on the robot; ``scratch``, ``num_tasks`` tasks of the seed on the robot from an
  empty skill; one session per continuation (`psl_optimizer.learning.CONTINUATIONS`): the same
  tasks on the robot, continuing PS_sim (``continue_from``); 'residual' (the default way)
  learns the robot's correction on top of PS_sim, 'samples' adds the robot's solutions to
  PS_sim's samples;
- a task with feed-forward, per seed: the tracking error [rad] on the robot, per held-out
  instance, of the commanded paths of PS_sim with PD only (``pd_only``), with PS_sim's
  feed-forward (``simulated``), with the nominal model's inverse dynamics (``oracle``), after
  ``ilc_iterations`` ILC steps on the robot from PS_sim's theta (``ilc``: `ilc_step`, no stop at
  success), and the continued skills' learned feed-forward (zero-shot, `Learner.summary`).
Every session of a seed reads the same training instances and the same held-out instances; the
rollouts on the robot of each session are what the table calls "rollouts on the robot".
Each session has rollouts of its own on the robot (its noise draws count its own rollouts), so
a session's result does not depend on which ran before it: once the nominal session has run,
the sessions of the robot seeds are independent, each a `psl_bench.sessions` session (in this
process, or a Ray task). Plain Python, no ROS.
"""
from __future__ import annotations

import importlib
import tempfile
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from psl_bench import sessions
from psl_bench.sessions import Session
from psl_task import DEFAULT_TASK

# the stand-in "real" robot of the measurements (docs/benchmarks.md)
REAL_ROBOT = 'mass_scale=1.3,frictionloss=0.05,damping=0.3'
SEEDS = (11, 12, 13)       # robot seeds: the training and held-out instances on the robot
TASKS = (DEFAULT_TASK, 'payload_transport')
TRACKING = ('pd_only', 'simulated', 'oracle', 'ilc')      # PS_sim's path on the robot


def _tracking_error(rollouts, taus: np.ndarray, thetas: np.ndarray) -> list[float]:
    return [float(r.evaluation.components['tracking_error'])
            for r in rollouts.run(thetas, taus)]


def _ilc(rollouts, taus: np.ndarray, thetas: np.ndarray, iterations: int) -> np.ndarray:
    """thetas after `iterations` ILC steps of theta_D each on its instance (every step one
    rollout on the robot, no stop at success)."""
    from psl_optimizer.ilc import ILCSettings, ilc_step
    settings, out = ILCSettings(), []
    for tau, theta in zip(taus, thetas):
        for _ in range(iterations):
            result = rollouts.run(theta[None], tau)[0]
            theta = ilc_step(rollouts.policy, theta, result, settings, tau)
        out.append(theta)
    return np.array(out)


def robot_task(task, folder: Path, gains: float) -> Path:
    """The YAML of the robot's task: `task`'s file with the controller's kp and kd times
    `gains` (the robot's own controller), written into `folder`; everything else as it is
    (the model file by its absolute path, the name kept, so a skill of the task continues on
    it)."""
    import yaml

    data = yaml.safe_load(task.path.read_text())
    robot = data.get('robot') or {}
    if robot.get('model') is not None:
        robot['model'] = str(task.model_path)
        if robot.get('package_paths'):
            robot['package_paths'] = {key: str(value)
                                      for key, value in task.package_paths.items()}
    else:
        data['model'] = str(task.model_path)
    data['name'] = task.name
    data['controller'] = {**data['controller'],
                          **{key: [gains * float(v) for v in data['controller'][key]]
                             for key in ('kp', 'kd')}}
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f'{task.name}.robot.yaml'
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _robot(task_ref: str, model_error: str, measurement_noise: str, threads: int):
    """Batch rollouts on the robot: the task `task_ref` (a name or a YAML path) with the model
    error and measurement noise; each session has its own (its noise draws count its own
    rollouts, `MeasurementNoise`: a session's result does not depend on what ran before)."""
    from psl_optimizer.rollout_modes import make_rollouts
    from psl_task.task import load_task

    task = load_task(task_ref)
    return task, make_rollouts('batch', task, model_error=model_error,
                               measurement_noise=measurement_noise, threads=threads)


def learn_session(task_ref: str, folder: str, settings, model_error: str = '',
                  measurement_noise: str = '', threads: int = 2) -> dict:
    """One `Learner` session (`psl_bench.sessions.Session`): on the task's model, or with a
    model error on the robot; its row of the table, and a ``summary`` line."""
    from psl_optimizer.learning import Learner

    importlib.import_module('cma')
    task, rollouts = _robot(task_ref, model_error, measurement_noise, threads)
    s = Learner(task, settings, Path(folder), rollouts).run().summary
    row = {'rollouts': s.total_rollouts, 'rollouts_per_task': s.rollouts_per_task,
           'fulfilled_tasks': s.fulfilled_tasks,
           'zero_shot_success': s.zero_shot_success_rate,
           'zero_shot_reward': s.zero_shot_mean_reward,
           'tracking_learned': (None if s.tracking_rmse_mean is None
                                else s.tracking_rmse_mean['learned'])}
    return {**row, 'summary': f"{row['rollouts']} rollouts, zero-shot "
                              f"{100 * row['zero_shot_success']:.0f} %"}


def simulated_skill_on_robot(task_ref: str, memory: str, seed: int, num_test: int,
                             ilc_iterations: int, model_error: str,
                             measurement_noise: str, threads: int = 2) -> dict:
    """PS_sim (the nominal session's memory) on the robot (`psl_bench.sessions.Session`):
    ``before``, its zero-shot success on the seed's held-out instances, and with feed-forward
    the ``tracking`` errors of its paths (module docstring)."""
    from psl_optimizer.learning import InProcessSkill, LearnSettings, feedforward_variants
    from psl_optimizer.task_selection import held_out_tasks

    task, robot = _robot(task_ref, model_error, measurement_noise, threads)
    sim = InProcessSkill(task, LearnSettings().skill, robot.policy.default_theta, 'samples')
    sim.start(memory)
    test = held_out_tasks(task, num_test, seed)
    thetas = np.array([sim.query(tau) for tau in test])
    rewards, fulfilled = robot.evaluate(thetas, test)
    record = {'before': {'zero_shot_success': float(np.mean(fulfilled)),
                         'zero_shot_reward': float(np.mean(rewards))}}
    if robot.policy.has_feedforward:
        variants = feedforward_variants(task, test, thetas)
        tracking = {'pd_only': _tracking_error(robot, test, variants['pd_only']),
                    'simulated': _tracking_error(robot, test, variants['learned']),
                    'oracle': _tracking_error(robot, test, variants['oracle']),
                    'ilc': _tracking_error(robot, test, _ilc(robot, test, thetas,
                                                             ilc_iterations))}
        record['tracking'] = {name: {'mean': float(np.mean(v)), 'values': v}
                              for name, v in tracking.items()}
    record['summary'] = (f"zero-shot on the robot "
                         f"{100 * record['before']['zero_shot_success']:.0f} %")
    return record


def _plans(task_name: str, model_error: str, nominal_seed: int, nominal_tasks: int,
           seeds: Sequence[int], num_tasks: int, num_test: int, budget: int,
           ilc_iterations: int, continuations: Sequence[str], measurement_noise: str,
           robot_gains: float, root: Path, threads: int = 2
           ) -> tuple[Session, list[Session], dict]:
    """The sessions of one task (module docstring): the nominal one (the others continue its
    skill), those of the robot seeds (independent of each other once it has run), and the
    report's settings."""
    from psl_optimizer.learning import LearnSettings
    from psl_optimizer.policy_search import SearchSettings
    from psl_task.task import load_task, task_id

    task = load_task(task_name)
    root = root / task.name
    search = SearchSettings(max_rollouts=budget)
    # the robot's task: the task itself, or its copy with the robot controller's gains
    real = task_id(task) if robot_gains == 1.0 else str(robot_task(task, root, robot_gains))
    memory = str(root / 'nominal' / 'memory.npz')
    on_robot = {'model_error': model_error, 'measurement_noise': measurement_noise}
    nominal = Session(
        key=(task.name, 'nominal'), label=f'{task.name} nominal', function=learn_session,
        kwargs=dict(task_ref=task_id(task), folder=str(root / 'nominal'), threads=threads,
                    settings=LearnSettings(search=search, num_test=num_test,
                                           seed=nominal_seed, num_tasks=nominal_tasks)))
    robot = []
    for seed in seeds:
        robot.append(Session(
            key=(task.name, seed, 'before'), label=f'{task.name} seed{seed}/sim skill',
            function=simulated_skill_on_robot,
            kwargs=dict(task_ref=real, memory=memory, seed=seed, num_test=num_test,
                        ilc_iterations=ilc_iterations, threads=threads, **on_robot)))
        for way in ('scratch', *continuations):
            continued = {} if way == 'scratch' else dict(continue_from=memory,
                                                         continuation=way)
            name = 'scratch' if way == 'scratch' else f'continued-{way}'
            robot.append(Session(
                key=(task.name, seed, way), label=f'{task.name} seed{seed}/{name}',
                function=learn_session,
                kwargs=dict(task_ref=real, folder=str(root / f'seed{seed}' / name),
                            settings=LearnSettings(search=search, num_test=num_test,
                                                   seed=seed, num_tasks=num_tasks,
                                                   **on_robot, **continued),
                            threads=threads, **on_robot)))
    report = {'task': task.name, 'model_error': model_error,
              'measurement_noise': measurement_noise, 'robot_gains': robot_gains,
              'nominal_seed': nominal_seed, 'nominal_tasks': nominal_tasks,
              'seeds': list(seeds), 'num_tasks': num_tasks, 'num_test': num_test,
              'budget': budget, 'ilc_iterations': ilc_iterations, 'runs': {}}
    return nominal, robot, report


def _row(record: dict) -> dict:
    return {k: v for k, v in record.items() if k not in ('summary', 'ran_on')}


def run(tasks: Sequence[str] = TASKS, model_error: str = REAL_ROBOT, nominal_seed: int = 3,
        nominal_tasks: int = 30, seeds: Sequence[int] = SEEDS, num_tasks: int = 10,
        num_test: int = 20, budget: int = 200, ilc_iterations: int = 10,
        continuations: Sequence[str] = ('residual', 'samples'), measurement_noise: str = '',
        robot_gains: float = 1.0, out: str | Path | None = None,
        progress: Callable[[str], None] | None = None, runner: str = 'serial',
        address: str | None = None) -> dict:
    """The sessions of each task (module docstring), run by `psl_bench.sessions` (serially
    here, or each a Ray task: first the nominal sessions, then every robot seed's); the
    report of `format_table`, with ``runner``, ``nodes`` and ``missing`` (the sessions that
    failed twice: their task's or seed's rows are left out).

    Raises:
        ValueError: no model error, an unknown task or continuation, bad sizes, seeds, noise
            or gains.
        RuntimeError: no session finished.
    """
    from psl_optimizer.batch_rollout import MeasurementNoise
    from psl_optimizer.learning import CONTINUATIONS
    from psl_task.model_error import ModelError

    if not tasks or len(set(tasks)) != len(tasks):
        raise ValueError('give each task once, at least one')
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f'give each robot seed once, at least one, got {list(seeds)}')
    for name, value in (('nominal_tasks', nominal_tasks), ('num_tasks', num_tasks),
                        ('num_test', num_test), ('budget', budget)):
        if value < 1:
            raise ValueError(f'{name} must be at least 1, got {value}')
    if ilc_iterations < 0:
        raise ValueError(f'ilc_iterations must be >= 0, got {ilc_iterations}')
    if not (np.isfinite(robot_gains) and robot_gains > 0.0):
        raise ValueError(f'robot_gains must be a finite share > 0 of the task\'s gains, got '
                         f'{robot_gains}')
    if ModelError.parse(model_error).is_identity:
        raise ValueError('sim to real needs a model error (the robot is the model otherwise)')
    MeasurementNoise.parse(measurement_noise)        # ValueError naming what is wrong
    unknown = [c for c in continuations if c not in CONTINUATIONS]
    if unknown or len(set(continuations)) != len(continuations):
        raise ValueError(f'continuations: each of {", ".join(CONTINUATIONS)} at most once, '
                         f'got {list(continuations)}')
    temporary = tempfile.TemporaryDirectory(prefix='psl-bench-s2r-') if out is None else None
    root = Path(temporary.name if temporary else out)
    try:
        plans = [_plans(name, model_error, nominal_seed, nominal_tasks, seeds, num_tasks,
                        num_test, budget, ilc_iterations, continuations, measurement_noise,
                        robot_gains, root, threads=1 if runner == 'ray' else 2)
                 for name in tasks]
        with sessions.cluster(runner, address):      # one cluster for both stages
            first = sessions.run([nominal for nominal, _, _ in plans], runner, address,
                                 progress)
            later = sessions.run([s for nominal, robot, _ in plans
                                  if nominal.key in first.records for s in robot],
                                 runner, address, progress)
    finally:
        if temporary is not None:
            temporary.cleanup()
    records = {**first.records, **later.records}
    reports = {}
    for nominal, robot, report in plans:
        if nominal.key not in records:
            continue
        report['nominal'] = _row(records[nominal.key])
        for seed in seeds:
            keys = [s.key for s in robot if s.key[1] == seed]
            if all(key in records for key in keys):
                before = records[keys[0]]
                run = report['runs'][str(seed)] = {
                    'before': before['before'],
                    'sessions': {key[2]: _row(records[key]) for key in keys[1:]}}
                if 'tracking' in before:
                    run['tracking'] = before['tracking']
        if report['runs']:
            reports[report['task']] = report
    if not reports:
        raise RuntimeError('no session of the sweep finished: '
                           + '; '.join(first.missing() + later.missing()))
    return {'tasks': reports, 'runner': later.runner,
            'nodes': {node: first.nodes.get(node, 0) + later.nodes.get(node, 0)
                      for node in {**first.nodes, **later.nodes}},
            'missing': first.missing() + later.missing()}


def _percent(share: float) -> str:
    return f'{100 * share:.0f} %'


def format_table(report: dict) -> str:
    """Markdown: per task and robot seed, and over the seeds (rollouts and fulfilled tasks
    summed, zero-shot success averaged), the rollouts on the robot, the training tasks
    fulfilled and the zero-shot success of each session; then the tracking errors of the tasks
    with feed-forward, averaged over the seeds."""
    first = next(iter(report['tasks'].values()))
    ways = list(next(iter(first['runs'].values()))['sessions'])
    robot = [f"the task's model with {first['model_error']}"]
    if first['measurement_noise']:
        robot.append(f"measurement noise {first['measurement_noise']}")
    if first['robot_gains'] != 1.0:
        robot.append(f"controller gains {first['robot_gains']:g} times the task's")
    lines = [f"robot = {', '.join(robot)}; simulated skill: {first['nominal_tasks']} tasks of "
             f"seed {first['nominal_seed']} on the model; on the robot, per seed: "
             f"{first['num_tasks']} tasks (budget {first['budget']}), zero-shot on "
             f"{first['num_test']} held-out instances", '',
             '| task | robot seed | ' + ' | '.join(f'rollouts {w}' for w in ways)
             + f" | tasks fulfilled ({' / '.join(ways)}) | zero-shot sim skill | "
             + ' | '.join(f'zero-shot {w}' for w in ways) + ' |',
             '|---' * (4 + 2 * len(ways)) + '|']
    for name, r in report['tasks'].items():
        runs = r['runs']
        for seed, run in runs.items():
            s = run['sessions']
            lines.append(
                f'| {name} | {seed} | ' + ' | '.join(str(s[w]['rollouts']) for w in ways)
                + ' | ' + ' / '.join(str(s[w]['fulfilled_tasks']) for w in ways)
                + f" | {_percent(run['before']['zero_shot_success'])} | "
                + ' | '.join(_percent(s[w]['zero_shot_success']) for w in ways) + ' |')
        if len(runs) > 1:           # over the seeds: sums, and the mean zero-shot success
            sessions = [run['sessions'] for run in runs.values()]
            before = np.mean([run['before']['zero_shot_success'] for run in runs.values()])
            lines.append(
                f'| {name} | all {len(runs)} | '
                + ' | '.join(f"**{sum(s[w]['rollouts'] for s in sessions)}**" for w in ways)
                + ' | ' + ' / '.join(str(sum(s[w]['fulfilled_tasks'] for s in sessions))
                                     for w in ways)
                + f' | {_percent(before)} | '
                + ' | '.join(_percent(np.mean([s[w]['zero_shot_success'] for s in sessions]))
                             for w in ways) + ' |')
    tracked = {n: r for n, r in report['tasks'].items()
               if all('tracking' in run for run in r['runs'].values())}
    if tracked:
        lines += ['', 'tracking RMSE on the robot [rad], mean over the held-out instances and '
                  "seeds: the simulated skill's path with PD only, its simulated feed-forward, "
                  "the model's inverse dynamics, after ILC on the robot; the learned "
                  'feed-forward of each session (zero-shot)', '',
                  '| task | PD only | simulated ff | oracle (model) | ILC on robot | '
                  + ' | '.join(ways) + ' |', '|---' * (5 + len(ways)) + '|']
        for name, r in tracked.items():
            runs = list(r['runs'].values())

            def tracking(key):
                return float(np.mean([run['tracking'][key]['mean'] for run in runs]))

            def learned(way):
                return float(np.mean([run['sessions'][way]['tracking_learned'] for run in runs]))
            lines.append(f"| {name} | {tracking('pd_only'):.4f} | {tracking('simulated'):.4f} | "
                         f"{tracking('oracle'):.4f} | {tracking('ilc'):.4f} "
                         f"({r['ilc_iterations']} steps) | "
                         + ' | '.join(f'{learned(w):.4f}' for w in ways) + ' |')
    if 'runner' in report:
        lines += ['', f"sessions run {report['runner']}; per node: " + ', '.join(
            f'{node} {count}' for node, count in report['nodes'].items())]
    for missing in report.get('missing', []):
        lines.append(f'MISSING (failed twice, left out of its rows): {missing}')
    return '\n'.join(lines) + '\n'
