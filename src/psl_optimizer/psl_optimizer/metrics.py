"""What a learning session leaves in its output folder, read and written in one place.

``metrics.json`` holds a `Metrics`: the session's identity and settings, one `TaskRecord` per
finished training task (also the content of ``checkpoint.json``) and, once every task is done,
the `Summary` of the zero-shot test on held-out instances. The learner writes it; the CLI, the
plots and the benchmarks read it with `read_metrics`, never by string keys of their own. The
JSON layout is the file format (documented in docs/learning.md): flat keys, one JSON object.
Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

METRICS_FILE = 'metrics.json'
FEEDFORWARD_VARIANTS = ('pd_only', 'learned', 'oracle')   # tracking_rmse_<variant>[_mean]


class MetricsError(ValueError):
    """A metrics file that is missing, not JSON or not a psl learning session."""


@dataclasses.dataclass(frozen=True)
class TaskRecord:
    """One training task instance of a session."""

    index: int                  # position in the session's task sequence
    tau: list[float]            # the task instance
    rollouts: int               # candidates its search evaluated (every one counted)
    fulfilled: bool             # a rollout reached the success threshold
    best_reward: float
    start_reward: float         # the search's first rollout: PS(tau), or the default policy
    seconds: float              # wall time of the search
    refused: int = 0            # of the candidates, those the safety check refused: not
                                # executed (executed rollouts = rollouts - refused)
    # LearnSettings.confirm: a fulfilled search whose theta then did not confirm (its sample
    # did not enter the skill), and the confirming rollouts (counted in rollouts too)
    unconfirmed: bool = False
    confirm_rollouts: int = 0
    # of the candidates, those a reward component could not score (it raised or its cost was
    # not finite: the penalty), and the newest such reason
    failed: int = 0
    failure: str = ''
    # episodes a goal that was not psl's preempted (graph mode on a robot whose controller
    # someone else commands too): each run again, not counted in rollouts
    preempted: int = 0

    @classmethod
    def from_dict(cls, data: dict) -> 'TaskRecord':
        return cls(index=int(data['index']), tau=[float(x) for x in data['tau']],
                   rollouts=int(data['rollouts']), fulfilled=bool(data['fulfilled']),
                   best_reward=float(data['best_reward']),
                   start_reward=float(data['start_reward']), seconds=float(data['seconds']),
                   refused=int(data.get('refused', 0)),
                   unconfirmed=bool(data.get('unconfirmed', False)),
                   confirm_rollouts=int(data.get('confirm_rollouts', 0)),
                   failed=int(data.get('failed', 0)), failure=str(data.get('failure', '')),
                   preempted=int(data.get('preempted', 0)))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class Summary:
    """The end of a complete session: training totals and the held-out zero-shot test."""

    total_rollouts: int
    rollouts_per_task: list[int]
    fulfilled_tasks: int
    test_taus: list[list[float]]            # the held-out instances, never trained on
    test_rewards: list[float]               # PS(tau) executed once on each
    zero_shot_success_rate: float
    zero_shot_mean_reward: float
    # a task with feed-forward: RMS tracking error [rad] per held-out instance of each variant
    # of FEEDFORWARD_VARIANTS (the learned feed-forward, PD only, the inverse-dynamics oracle),
    # and its mean over the instances
    # a task with a target: the hand's final position [m] and, where the reward scores it,
    # orientation [rad] errors on each held-out instance (components goal_error,
    # orientation_error)
    test_hand_errors: dict[str, list[float]] | None = None
    tracking_rmse: dict[str, list[float]] | None = None
    tracking_rmse_mean: dict[str, float] | None = None
    # LearnSettings.confirm: fulfilled tasks whose success did not confirm (no sample added),
    # and the confirming rollouts (of total_rollouts)
    unconfirmed_tasks: int = 0
    confirm_rollouts: int = 0

    @classmethod
    def from_dict(cls, data: dict) -> 'Summary':
        tracking = means = None
        if f'tracking_rmse_{FEEDFORWARD_VARIANTS[0]}' in data:
            tracking = {v: [float(x) for x in data[f'tracking_rmse_{v}']]
                        for v in FEEDFORWARD_VARIANTS}
            means = {v: float(data[f'tracking_rmse_{v}_mean']) for v in FEEDFORWARD_VARIANTS}
        return cls(total_rollouts=int(data['total_rollouts']),
                   rollouts_per_task=[int(r) for r in data['rollouts_per_task']],
                   fulfilled_tasks=int(data['fulfilled_tasks']),
                   test_taus=[[float(x) for x in tau] for tau in data['test_taus']],
                   test_rewards=[float(r) for r in data['test_rewards']],
                   zero_shot_success_rate=float(data['zero_shot_success_rate']),
                   zero_shot_mean_reward=float(data['zero_shot_mean_reward']),
                   test_hand_errors=({name: [float(x) for x in values] for name, values
                                      in data['test_hand_errors'].items()}
                                     if data.get('test_hand_errors') else None),
                   tracking_rmse=tracking, tracking_rmse_mean=means,
                   unconfirmed_tasks=int(data.get('unconfirmed_tasks', 0)),
                   confirm_rollouts=int(data.get('confirm_rollouts', 0)))

    def to_dict(self) -> dict:
        """The JSON form: the tracking errors as flat keys tracking_rmse_<variant>[_mean]."""
        data = dataclasses.asdict(self)
        tracking, means = data.pop('tracking_rmse'), data.pop('tracking_rmse_mean')
        for variant in tracking or ():
            data[f'tracking_rmse_{variant}'] = tracking[variant]
            data[f'tracking_rmse_{variant}_mean'] = means[variant]
        return data


@dataclasses.dataclass(frozen=True)
class Metrics:
    """One learning session (see the module docstring)."""

    task: str                           # the task's name
    strategy: str
    seed: int
    settings: dict[str, Any]            # the session's LearnSettings, as JSON
    tasks: list[TaskRecord]
    complete: bool                      # every training task is done (then summary is set)
    summary: Summary | None = None
    task_path: str = ''                 # the task's YAML file, absolute (where it was learned)
    task_yaml: str = ''                 # a copy of its text (names, units, threshold for plots)

    @property
    def num_tasks(self) -> int:
        """Training tasks the session was set up for (finished or not)."""
        return int(self.settings.get('num_tasks', len(self.tasks)))

    @property
    def preempted(self) -> int:
        """Episodes of the training tasks that foreign goals preempted (each run again)."""
        return sum(t.preempted for t in self.tasks)

    @classmethod
    def from_dict(cls, data: dict) -> 'Metrics':
        return cls(task=str(data['task']), strategy=str(data['strategy']),
                   seed=int(data['seed']), settings=dict(data.get('settings', {})),
                   tasks=[TaskRecord.from_dict(t) for t in data['tasks']],
                   complete=bool(data.get('complete', 'summary' in data)),
                   summary=Summary.from_dict(data['summary']) if data.get('summary') else None,
                   task_path=str(data.get('task_path', '')),
                   task_yaml=str(data.get('task_yaml', '')))

    def to_dict(self) -> dict:
        data = {'task': self.task, 'task_path': self.task_path, 'task_yaml': self.task_yaml,
                'strategy': self.strategy, 'seed': self.seed,
                'settings': self.settings, 'tasks': [t.to_dict() for t in self.tasks],
                'complete': self.complete}
        if self.summary is not None:
            data['summary'] = self.summary.to_dict()
        return data

    def write(self, folder: str | Path) -> Path:
        path = Path(folder) / METRICS_FILE
        path.write_text(json.dumps(self.to_dict(), indent=1))
        return path


def read_metrics(folder: str | Path) -> Metrics:
    """The metrics of the session in `folder` (a run folder of ``psl learn``).

    Raises:
        MetricsError: no metrics.json, not JSON, or not a learning session's; the message
            names the file.
    """
    path = Path(folder) / METRICS_FILE
    if not path.is_file():
        raise MetricsError(f'{path}: no such file (not an output folder of psl learn, or the '
                           'session never finished a first task)')
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MetricsError(f'{path}: not readable as JSON ({exc})') from exc
    if not isinstance(data, dict):
        raise MetricsError(f'{path}: corrupt metrics (not a JSON object)')
    try:
        return Metrics.from_dict(data)
    except KeyError as exc:
        raise MetricsError(f'{path}: corrupt metrics (no {exc.args[0]!r})') from exc
    except (TypeError, ValueError, AttributeError) as exc:
        raise MetricsError(f'{path}: corrupt metrics ({exc})') from exc
