"""The learning loop: for each new task instance, search theta starting from the skill, add the
solution to the memory at once, go on; then measure zero-shot success on held-out instances.

Task sequences come from a seed (`task_stream`); the held-out test instances come from a
separate stream and are never trained on. After every task the loop writes a checkpoint
(memory file + progress JSON) into its output folder, and `Learner.run` resumes from it, so a
crash or a cancel loses no finished task. Imports no ROS; the learner node and ``psl learn``
wrap it.

Rollouts come from one `psl_optimizer.rollouts.Rollouts` object (batch mode in-process by
default, or graph mode through the rollout workers): the learner does not know which.

Dynamics modality (a task with ``policy.feedforward: true``): the search covers the whole
theta = [theta_K, theta_D], with theta_D in its own CMA-ES units (`search_normalisation`); each
instance first gets ILC of theta_D from the search's start (`psl_optimizer.ilc`, far fewer
rollouts than CMA-ES: docs/benchmarks.md, ``psl bench dynamics``; it needs rollouts that carry
their measured trajectories), and CMA-ES goes on from ILC's best if that falls short. The
summary then adds the held-out tracking errors of the learned feed-forward beside PD only and
the inverse-dynamics oracle (`tracking_comparison`).

Sim to real (`LearnSettings.continue_from` with `LearnSettings.continuation`): a skill learned
on the task's model is continued on a robot whose dynamics differ (batch mode: rollouts with a
`psl_task.model_error.ModelError`, recorded as `LearnSettings.model_error`; a robot whose own
controller has other gains: a copy of the task YAML with those gains, the skill of the same
name continued on it). The robot's solutions contradict the simulated ones (the same tau,
another feed-forward), so adding them to the simulated skill's samples ('samples', the old way)
makes a skill that averages both and is wrong for either. The default, 'residual', keeps the
simulated skill as it is and learns the robot's correction on top of it: ``PS(tau) =
PS_sim(tau) + C(tau)``, C learned from the robot's solutions minus PS_sim
(`ResidualComposition`: in this process and in the memory node alike).

Where PS_sim + C misses an instance, the search does not pay a CMA-ES generation and its mean
(popsize + 1 rollouts) before it has tried the continued skill's other guesses, one rollout each
(`ResidualComposition.alternatives`, `psl_optimizer.policy_search.try_guesses`): PS_sim alone
(C generalises each robot solution over the whole task space, and a correction found at one
instance can spoil instances PS_sim solved) and the answer of a skill without samples (what a
session from scratch tries first: on a robot where the simulated skill is worse than none);
CMA-ES then starts from the best of the guesses. A session that continues nothing has no other
guess, and its search is what it was. A task with feed-forward starts ILC from PS_sim + C (ILC
pays one rollout per step already). Measured: docs/benchmarks.md, ``psl bench sim-to-real``.

A noisy robot (`LearnSettings.measurement_noise`): a candidate whose rollout fulfils its
instance may have been lucky. With `LearnSettings.confirm` = (k, n) the search's successful
theta is rolled out n - 1 more times and its sample enters the skill only if at least k of the
n rollouts fulfil the instance (the extra rollouts count; `TaskRecord.unconfirmed` marks a
success that did not confirm). Measured: docs/benchmarks.md, ``psl bench false-successes``
(with the reward's smoothness of the measured angles, 1 mrad of noise spoils every reward;
``reward: {smoothness_of: reference}`` scores the commanded motion instead).
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from psl_controller.pd_law import law_for
from psl_controller.policy import policy_for
from psl_memory.gaussian_process_map import GaussianProcessMap
from psl_memory.nearest_neighbour_library import NearestNeighbourLibrary
from psl_memory.parameterized_skill import scaler_around
from psl_memory.skill_config import SkillConfig
from psl_memory.skill_memory import MAX_FILE_BYTES, SkillMemory, write_npz_atomically
from psl_optimizer.ilc import ILCSettings, ilc_search
from psl_optimizer.inverse_dynamics import oracle_theta
from psl_optimizer.metrics import Metrics, Summary, TaskRecord
from psl_optimizer.policy_search import SearchResult, SearchSettings, search
from psl_optimizer.rollouts import Rollouts
from psl_optimizer.task_selection import (TASK_SELECTIONS, held_out_tasks, most_uncertain,
                                          task_stream)
from psl_task.model_error import ModelError
from psl_task.task import TaskDefinition

FEEDFORWARD_SCALE = 0.5          # theta_D's CMA-ES unit: this share of the joint's torque limit
# after ILC, CMA-ES refines theta_D in this share of that unit (2 % of the torque limit): with
# the full unit its steps undid what ILC had learned and the skill learned the noise
# (point_reach_3d's zero-shot success: docs/benchmarks.md, "Task variability")
ILC_REFINE_SHARE = 0.04
GOAL_SCALE = {'joint': 0.3,      # a learned goal's CMA-ES unit: rad (joint space) ...
              'end_effector': 0.1}    # ... or m (end-effector space)
HAND_ERRORS = ('goal_error', 'orientation_error')   # [m], [rad]: a held-out instance's final miss
ORIENTATION_GOAL_SCALE = 0.3  # rad: a learned goal orientation's CMA-ES unit (policy.orientation)
# with a learned goal the goal carries where to go and the weights only shape the way: their
# CMA-ES unit shrinks to this share of the common spread (docs/benchmarks.md, psl bench learn
# on planar_10dof_reach: with the full spread bootstrap needed 75 rollouts per late task, 2
# with this share)
GOAL_WEIGHT_SHARE = 0.3

# the baselines that can take the skill memory's place in the skill slot (batch mode), by the
# name `LearnSettings.skill_map` gives them: each is built from the task's tau ranges and the
# default theta, and is a function of its samples (docs/benchmarks.md, psl bench learn)
BASELINE_MAPS = {cls.name: cls for cls in (NearestNeighbourLibrary, GaussianProcessMap)}
SKILL_MAPS = ('elm', *BASELINE_MAPS)     # 'elm': the skill memory (`LearnSettings.skill`)
BASELINE_FORMAT = 'psl-baseline-samples'     # the memory file of a baseline's session
# how a session continues the skill of `LearnSettings.continue_from` (module docstring):
# 'residual' learns the robot's correction on top of the loaded skill, 'samples' adds the new
# solutions to the loaded skill's samples
CONTINUATIONS = ('residual', 'samples')
# the skill of a residual continuation's correction, in the memory file beside the task's
CORRECTION_SUFFIX = '+correction'


@dataclasses.dataclass(frozen=True)
class LearnSettings:
    strategy: str = 'bootstrap'
    num_tasks: int = 30
    seed: int = 0
    num_test: int = 20
    search: SearchSettings = SearchSettings()
    skill: SkillConfig = SkillConfig()  # bayes, fixed precisions: ridge's mean + variance
    add_only_fulfilled: bool = True     # a failed search's best theta would teach the skill a miss
    # tasks with feed-forward: ILC of theta_D from the search's start first, then CMA-ES over
    # [theta_K, theta_D] with the rest of the budget (iterations=0: CMA-ES only)
    ilc: ILCSettings = ILCSettings()
    # which instance comes next: 'random' (the seeded sequence) or 'variance' (the candidate
    # with the largest predictive variance of the skill, `most_uncertain`)
    task_selection: str = 'random'
    # a new session starts from an empty skill, or ('continue_from': a memory file) from the
    # skill of this task that file holds (batch mode: a path; graph mode: a file of the memory
    # node's memory_dir); resuming from the session's own checkpoint does not look at it
    continue_from: str = ''
    selection_candidates: int = 20
    # the tau -> theta map in the skill slot (`in_process_skill`): 'elm', the skill memory of
    # `skill`; or a baseline of BASELINE_MAPS, 'library' (the k nearest solved instances,
    # inverse-distance weighted) or 'gp' (Gaussian-process regression). Baselines: batch mode,
    # no continue_from
    skill_map: str = 'elm'
    # the robot the rollouts run on differs from the task's model (batch mode, sim to real;
    # `ModelError.parse` text, '' = none): recorded here, the rollouts must have the same
    model_error: str = ''
    # how continue_from's skill is continued (CONTINUATIONS): 'residual' (the robot's
    # correction learned on top of it; the memory node's only way) or 'samples' (the new
    # solutions added to its samples, in-process only); '' = residual
    continuation: str = ''
    # a noisy robot (batch mode): `psl_optimizer.batch_rollout.MeasurementNoise.parse` text,
    # '' = none; recorded here, the rollouts must have the same (the `Learner` checks it with
    # the rollouts' own parser: the loop imports no rollout implementation)
    measurement_noise: str = ''
    # (k, n): a search's success is confirmed before its sample enters the skill: the
    # candidate is rolled out n - 1 more times and enters only if at least k of the n rollouts
    # fulfil the instance (the extra rollouts count); (1, 1): off
    confirm: tuple[int, int] = (1, 1)

    def __post_init__(self):
        if self.num_tasks < 1 or self.num_test < 1:
            raise ValueError(f'num_tasks and num_test must be at least 1, got {self.num_tasks} '
                             f'and {self.num_test}')
        if self.task_selection not in TASK_SELECTIONS:
            raise ValueError(f'unknown task selection {self.task_selection!r}; known: '
                             f'{", ".join(TASK_SELECTIONS)}')
        if self.selection_candidates < 1:
            raise ValueError('selection_candidates must be at least 1')
        if self.skill_map not in SKILL_MAPS:
            raise ValueError(f'unknown skill map {self.skill_map!r}; known: '
                             f'{", ".join(SKILL_MAPS)}')
        if self.skill_map != 'elm' and self.continue_from:
            raise ValueError(f'continue_from needs the elm skill map; the {self.skill_map!r} '
                             'baseline starts empty')
        ModelError.parse(self.model_error)          # ValueError naming what is wrong
        k, n = self.confirm
        if not (isinstance(k, int) and isinstance(n, int) and 1 <= k <= n):
            raise ValueError(f'confirm (k, n) needs whole numbers 1 <= k <= n, got '
                             f'{self.confirm}')
        if self.continuation not in ('', *CONTINUATIONS):
            raise ValueError(f'unknown continuation {self.continuation!r}; known: '
                             f'{", ".join(CONTINUATIONS)}')
        if (self.task_selection == 'variance' and self.skill_map != 'elm'
                and not BASELINE_MAPS[self.skill_map].has_variance):
            raise ValueError(f'task selection by variance needs a predictive variance, which '
                             f'the {self.skill_map!r} skill map does not have')


class ResidualComposition:
    """The skill slot's answers from named skills: the task's skill alone, or a residual
    continuation of it (`CONTINUATIONS`). Continuing a skill the 'residual' way, the loaded
    skill of the task (the base, PS_sim) stays as it is, and a correction C, a skill of the same
    ranges and reference (named task + `CORRECTION_SUFFIX`, in the same memory and file),
    learns ``theta - PS_sim(tau)`` of every new solution: ``PS(tau) = PS_sim(tau) + C(tau) -
    c0``, with c0 the correction's reference (its answer without samples: the theta reference
    it was created with), so an empty correction answers PS_sim exactly. The predictive
    variance is the correction's (where the robot has no solution yet). A memory that holds a
    correction already (a continued session's) is continued with it.

    Subclasses say where the skills live (`_query`, `_add`: this process's memory, or the
    skill_memory node's) and set ``name``, ``correction`` and ``_c0`` (None: the skill alone).
    """

    name: str
    correction: str
    _c0: np.ndarray | None = None

    def _query(self, skill: str, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(theta, variance or None) of the named skill at tau."""
        raise NotImplementedError

    def _add(self, skill: str, tau: np.ndarray, theta: np.ndarray) -> None:
        raise NotImplementedError

    def query(self, tau: np.ndarray) -> np.ndarray:
        theta = self._query(self.name, tau)[0]
        if self._c0 is None:
            return theta
        return theta + (self._query(self.correction, tau)[0] - self._c0)

    def alternatives(self, tau: np.ndarray) -> list[np.ndarray]:
        """The skill's other guesses at tau than `query`, in the order a search tries them
        when that one fails (`psl_optimizer.policy_search.try_guesses`): of a residual
        continuation, the loaded skill without the robot's correction, PS_sim(tau), and the
        answer of a skill without samples, c0 (a session from scratch's first guess); of a
        skill alone, none."""
        if self._c0 is None:
            return []
        return [self._query(self.name, tau)[0], self._c0.copy()]

    def variance(self, tau: np.ndarray) -> np.ndarray | None:
        """Predictive variance of PS(tau) per theta dimension (None without a Bayesian
        readout); of a residual continuation: the correction's."""
        return self._query(self.name if self._c0 is None else self.correction, tau)[1]

    def add(self, tau: np.ndarray, theta: np.ndarray) -> None:
        if self._c0 is None:
            self._add(self.name, tau, theta)
        else:
            base = self._query(self.name, tau)[0]
            self._add(self.correction, tau, np.asarray(theta) - base + self._c0)


class InProcessSkill(ResidualComposition):
    """The skill memory as a library, in this process (batch mode's default), continued
    either way of `CONTINUATIONS` (`ResidualComposition`)."""

    continuations = CONTINUATIONS

    def __init__(self, task: TaskDefinition, config: SkillConfig, default_theta: np.ndarray,
                 continuation: str = CONTINUATIONS[0]):
        if continuation not in CONTINUATIONS:
            raise ValueError(f'unknown continuation {continuation!r}; known: '
                             f'{", ".join(CONTINUATIONS)}')
        self.task, self.config, self.default_theta = task, config, default_theta
        self.continuation = continuation
        self.name, self.correction = task.name, task.name + CORRECTION_SUFFIX
        self.start('')

    def start(self, continue_from: str) -> None:
        """A new session: an empty skill of the task, or the memory saved at `continue_from`
        (which must hold a skill of the task's sizes), continued the `continuation` way."""
        self.memory = SkillMemory(self.config) if not continue_from else SkillMemory.read(
            continue_from)
        self.memory.create(self.task.name, self.task.tau_low, self.task.tau_high,
                           self.default_theta, exist_ok=bool(continue_from))
        if continue_from and self.continuation == 'samples' and (
                self.correction in self.memory.skills) and (
                self.memory.get(self.correction).num_samples):
            raise ValueError(f'{continue_from} holds a residual skill (its correction '
                             f'{self.correction!r}): continue it the residual way')
        if continue_from and self.continuation == 'residual':
            self.memory.create(self.correction, self.task.tau_low, self.task.tau_high,
                               self.default_theta, exist_ok=True)
        self._base()

    def restore(self, path: Path) -> None:
        """A resumed session: the memory of its checkpoint (with its correction, if any)."""
        self.memory = SkillMemory.read(path)
        self._base()

    def _base(self) -> None:
        """The residual parts: the correction's reference c0 (None: plain)."""
        self._c0 = None
        if self.correction in self.memory.skills:
            correction = self.memory.get(self.correction)
            self._c0 = correction.theta_scaler.from_unit(np.zeros(correction.theta_dim))

    def _query(self, skill: str, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        return self.memory.get(skill).query(tau)

    def _add(self, skill: str, tau: np.ndarray, theta: np.ndarray) -> None:
        self.memory.add(skill, tau, theta)

    def save(self, path: Path) -> None:
        self.memory.save(path)


class InProcessBaseline:
    """A baseline tau -> theta map of `BASELINE_MAPS` in the skill slot, in this process.

    Its state is its samples: the memory file (an npz of the format `BASELINE_FORMAT` with
    the map's and the task's name, taus (N, E) and thetas (N, F)) holds them, written
    atomically, and `restore` rebuilds the map from them (the same map: each is a function of
    its samples in their order).
    """

    def __init__(self, task: TaskDefinition, skill_map: str, default_theta: np.ndarray):
        if skill_map not in BASELINE_MAPS:
            raise ValueError(f'unknown baseline {skill_map!r}; known: '
                             f'{", ".join(BASELINE_MAPS)}')
        self.task, self.skill_map = task, skill_map
        self.default_theta = np.asarray(default_theta, dtype=float)
        self.start('')

    def _empty(self):
        return BASELINE_MAPS[self.skill_map](self.task.tau_low, self.task.tau_high,
                                             self.default_theta)

    def start(self, continue_from: str) -> None:
        """A new session: an empty map (`LearnSettings` refuses continue_from for a
        baseline)."""
        self.map = self._empty()

    def restore(self, path: Path) -> None:
        """A resumed session: the map rebuilt from the samples of its checkpoint's file.

        Raises:
            ValueError: the file is missing, too big, not a baseline's samples file, or of
                another map, task or size (another session's folder).
        """
        path = Path(path)
        if path.is_symlink() or not path.is_file():
            raise ValueError(f'{path}: no memory file to resume from (not a regular file)')
        if path.stat().st_size > MAX_FILE_BYTES:
            raise ValueError(f'{path}: more than {MAX_FILE_BYTES} bytes; not read')
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files}
        except Exception as exc:  # noqa: BLE001 - numpy/zipfile raise many kinds
            raise ValueError(f'{path}: not readable as an npz file ({exc})') from exc
        kind = (str(arrays['format']) if 'format' in arrays else
                'an elm skill memory' if '__meta__' in arrays else 'no known format')
        if kind != BASELINE_FORMAT:
            raise ValueError(f'{path}: holds {kind}, not the samples of a baseline skill map '
                             f'({self.skill_map!r}): the folder holds another session')
        found = (str(arrays.get('skill_map')), str(arrays.get('task')))
        if found != (self.skill_map, self.task.name):
            raise ValueError(f'{path}: samples of skill map {found[0]!r} on task {found[1]!r}, '
                             f'not {self.skill_map!r} on {self.task.name!r}')
        fresh = self._empty()
        taus, thetas = arrays.get('taus'), arrays.get('thetas')
        if (taus is None or thetas is None or taus.ndim != 2 or thetas.ndim != 2
                or taus.shape[1] != fresh.tau_dim or thetas.shape[1] != fresh.theta_dim):
            raise ValueError(f'{path}: taus and thetas missing or not of this task\'s sizes')
        if len(taus):
            fresh.extend(taus, thetas)       # ValueError: other counts, NaN or inf
        self.map = fresh

    def query(self, tau: np.ndarray) -> np.ndarray:
        return self.map.query(tau)

    def variance(self, tau: np.ndarray) -> np.ndarray | None:
        """Predictive variance per theta dimension (None: the map has none)."""
        return self.map.variance(tau)

    def add(self, tau: np.ndarray, theta: np.ndarray) -> None:
        self.map.add(tau, theta)

    def save(self, path: Path) -> None:
        """Write the samples atomically (`write_npz_atomically`)."""
        write_npz_atomically(path, {
            'format': np.array(BASELINE_FORMAT), 'skill_map': np.array(self.skill_map),
            'task': np.array(self.task.name), 'taus': self.map.taus,
            'thetas': self.map.thetas})


def in_process_skill(task: TaskDefinition, settings: LearnSettings,
                     default_theta: np.ndarray) -> InProcessSkill | InProcessBaseline:
    """The skill slot of batch mode for `settings.skill_map`: the skill memory
    (`InProcessSkill` with `settings.skill`) or a baseline (`InProcessBaseline`): the
    `Learner`'s default skill."""
    if settings.skill_map == 'elm':
        return InProcessSkill(task, settings.skill, default_theta,
                              settings.continuation or CONTINUATIONS[0])
    return InProcessBaseline(task, settings.skill_map, default_theta)


def search_normalisation(task: TaskDefinition, default_theta: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """CMA-ES coordinates theta = centre + scale * z: around the default theta with the
    skill's common spread (`scaler_around`); for a task with feed-forward the theta_D block
    gets its own scale, a share (`FEEDFORWARD_SCALE`) of each joint's torque limit, since
    torques and DMP weights differ in units and size by orders of magnitude; a learned goal
    (``policy.learn_goal``) is centred on its default with a scale in its own units
    (`GOAL_SCALE`: rad or m; a goal orientation's rotation vector `ORIENTATION_GOAL_SCALE`),
    and the weights' scale shrinks to `GOAL_WEIGHT_SHARE`."""
    policy = policy_for(task)
    default_theta = np.asarray(default_theta, dtype=float)
    scaler = scaler_around(default_theta[policy.kinematics])
    centre, scale = default_theta.copy(), np.empty(default_theta.shape)
    centre[policy.kinematics] = 0.5 * (scaler.high + scaler.low)
    scale[policy.kinematics] = 0.5 * (scaler.high - scaler.low)
    if task.policy.learn_goal:
        scale[policy.kinematics] *= GOAL_WEIGHT_SHARE
        centre[policy.goal] = default_theta[policy.goal]
        scale[policy.goal] = GOAL_SCALE[task.policy.space]
        centre[policy.orientation_goal] = default_theta[policy.orientation_goal]
        scale[policy.orientation_goal] = ORIENTATION_GOAL_SCALE
    if policy.has_feedforward:
        law = law_for(task)
        limit = np.maximum(np.abs(law.torque_low), np.abs(law.torque_high))   # (n_joints,)
        scale[policy.dynamics] = np.repeat(FEEDFORWARD_SCALE * limit,
                                           policy.feedforward.n_basis)
    return centre, scale


# LearnSettings fields a resumed session must share with its checkpoint besides those always
# compared (`Learner._identity`): the search's budget and steps, ILC's, the skill's readout and
# what fills the skill slot
RESUMED_SETTINGS = ('search', 'ilc', 'skill', 'skill_map', 'add_only_fulfilled')


def _plain(value):
    """A settings value as JSON gives it back (dataclasses as dicts, tuples as lists)."""
    if dataclasses.is_dataclass(value):
        value = dataclasses.asdict(value)
    return json.loads(json.dumps(value))


class SessionFolderError(ValueError):
    """A session's folder holds another session (its checkpoint's settings differ), more
    tasks than this session has, or a damaged checkpoint: it is not resumed."""


CHECKPOINT_FILE = 'checkpoint.json'


def holds_checkpoint(folder: str | Path) -> bool:
    """Whether a session's `folder` holds a checkpoint, readable or not (a damaged one, even a
    directory or a dangling link of its name, is refused by the learner, never written
    over)."""
    return os.path.lexists(Path(folder) / CHECKPOINT_FILE)


def _brief(value, width: int = 60) -> str:
    """A setting's value for a one-line message ('' as 'none'), at most `width` characters."""
    text = json.dumps(value, sort_keys=True) if not isinstance(value, str) else (value
                                                                                 or 'none')
    return text if len(text) <= width else text[:width - 3] + '...'


class Learner:
    """Runs one learning session of one task, checkpointing into `out`.

    Args:
        rollouts: how the rollouts run (`Rollouts`: batch or graph mode,
            `psl_optimizer.rollout_modes.make_rollouts`).
        instances: with task selection 'given', the source of the training instances: task
            index -> tau (it may wait for the environment; `psl_ros.instance_source`).
        skill: object with query/variance/add/save/start/restore (InProcessSkill, or the
            skill_memory node behind its services); default: InProcessSkill. Its
            ``continuations`` (default ('samples',)) say how it can continue a skill.

    Raises:
        ValueError: the rollouts' model error or measurement noise is not the settings'
            (`LearnSettings.model_error`, `measurement_noise`), or the skill cannot continue
            the way the settings ask.
    """

    def __init__(self, task: TaskDefinition, settings: LearnSettings, out: str | Path,
                 rollouts: Rollouts, skill=None,
                 instances: Callable[[int], np.ndarray] | None = None):
        if (settings.task_selection == 'given') != (instances is not None):
            raise ValueError("task selection 'given' takes the instances from a source (e.g. "
                             'a topic: psl learn --tau-topic), and only it does')
        self.instances = instances      # index -> tau, for task_selection 'given'
        error = ModelError.parse(settings.model_error)
        simulated = getattr(rollouts, 'model_error', ModelError())
        if simulated != error:
            raise ValueError(f'the rollouts run with model error {simulated}, the settings say '
                             f'{error}: give both the same (make_rollouts(model_error=...))')
        measured = getattr(rollouts, 'measurement_noise', None)
        if measured is None and settings.measurement_noise:
            raise ValueError('measurement noise is a setting of batch rollouts; these rollouts '
                             'have none')
        if measured is not None and measured != type(measured).parse(
                settings.measurement_noise):
            raise ValueError(f'the rollouts run with {measured}, the settings say '
                             f'{settings.measurement_noise!r}: give both the same '
                             '(make_rollouts(measurement_noise=...))')
        self.policy = policy_for(task)
        self.default_theta = self.policy.default_theta
        self.skill = skill or in_process_skill(task, settings, self.default_theta)
        ways = getattr(self.skill, 'continuations', ('samples',))
        if settings.continuation and settings.continuation not in ways:
            raise ValueError(f'this skill continues a skill by {", ".join(ways)}, not '
                             f'{settings.continuation!r}')
        self.task, self.settings, self.out = task, settings, Path(out)
        self.rollouts = rollouts
        self.done: list[TaskRecord] = []    # finished tasks (from the checkpoint, then run)

    # -- checkpoints --------------------------------------------------------------------------
    @property
    def checkpoint_path(self) -> Path:
        return self.out / CHECKPOINT_FILE

    @property
    def memory_path(self) -> Path:
        return self.out / 'memory.npz'

    def _identity(self) -> dict:
        """What a checkpoint must match to be resumed by this session: what decides its
        searches and its skill (another budget or readout would go on as another session)."""
        s = self.settings
        return {'task': self.task.name, 'strategy': s.strategy, 'seed': s.seed,
                'task_selection': s.task_selection, 'model_error': s.model_error,
                'measurement_noise': s.measurement_noise, 'confirm': list(s.confirm),
                'continue_from': s.continue_from, 'continuation': s.continuation,
                **{key: _plain(getattr(s, key)) for key in RESUMED_SETTINGS}}

    def _load_checkpoint(self) -> list[TaskRecord]:
        """The finished tasks of the folder's checkpoint, the skill restored to its moment; a
        folder without one starts the session (`continue_from`).

        Raises:
            SessionFolderError: the checkpoint is another session's, of more tasks, or damaged
                (not a file, not JSON, not a checkpoint's content: the file named).
        """
        if not holds_checkpoint(self.out):
            self.skill.start(self.settings.continue_from)
            return []
        state = self._read_checkpoint()
        mine = self._identity()
        state.setdefault('task_selection', 'random')      # checkpoints from before the option
        for key, value in (('model_error', ''), ('measurement_noise', ''), ('confirm', [1, 1]),
                           ('continue_from', mine['continue_from']),
                           ('continuation', mine['continuation']),
                           *((key, mine[key]) for key in RESUMED_SETTINGS)):
            state.setdefault(key, value)                   # checkpoints from before them
        differ = [key for key, value in mine.items() if state.get(key) != value]
        if differ:
            raise SessionFolderError(
                f'{self.out} holds a checkpoint of another session ('
                + '; '.join(f'{key} {_brief(state.get(key))} there, {_brief(mine[key])} here'
                            for key in differ) + '): use another folder')
        if len(state['tasks']) > self.settings.num_tasks:
            raise SessionFolderError(
                f"{self.out} holds a session of {len(state['tasks'])} tasks done, more than "
                f'the {self.settings.num_tasks} of this one: use another folder')
        # the memory of the checkpoint's moment: the file it names if a kill left it there,
        # else memory.npz, which it replaced
        named = self.out / Path(str(state.get('memory', self.memory_path.name))).name
        try:
            done = [TaskRecord.from_dict(record) for record in state['tasks']]
        except KeyError as exc:
            raise self._damaged(f'a task record without {exc}') from None
        except (TypeError, ValueError, AttributeError) as exc:
            raise self._damaged(f'a task record that is not one: {exc}') from None
        self.skill.restore(named if named.is_file() else self.memory_path)
        return done

    def _damaged(self, why: str) -> SessionFolderError:
        return SessionFolderError(f'{self.checkpoint_path}: a damaged checkpoint ({why}); '
                                  'remove it to start the session afresh, or use another '
                                  'folder')

    def _read_checkpoint(self) -> dict:
        """The checkpoint's JSON object, with a list of tasks (SessionFolderError naming the
        file otherwise)."""
        path = self.checkpoint_path
        if not path.is_file():
            raise self._damaged('not a regular file')
        try:
            state = json.loads(path.read_text())
        except OSError as exc:
            raise self._damaged(f'cannot be read: {exc.strerror or exc}') from None
        except UnicodeDecodeError:
            raise self._damaged('not text') from None
        except ValueError as exc:                       # json.JSONDecodeError
            raise self._damaged(f'not JSON: {exc}') from None
        if not isinstance(state, dict):
            raise self._damaged(f'a JSON {type(state).__name__}, not an object')
        if not isinstance(state.get('tasks'), list):
            raise self._damaged('no list of tasks')
        return state

    def _save_checkpoint(self, done: list[TaskRecord]) -> None:
        """The memory and the tasks of one moment, whenever the process is killed: the memory
        after these tasks under a name of its own first, then the checkpoint naming it
        (atomic), then it replaces memory.npz. (Before, a kill between saving memory.npz and
        the checkpoint resumed with the last task's sample in the memory and the task to do
        again: its sample was added twice.)"""
        pending = self.out / f'memory.task{len(done)}.npz'
        self.skill.save(pending)                        # atomic
        state = {**self._identity(), 'tasks': [record.to_dict() for record in done],
                 'memory': pending.name}
        tmp = self.checkpoint_path.with_suffix('.tmp')
        tmp.write_text(json.dumps(state))
        os.replace(tmp, self.checkpoint_path)
        os.replace(pending, self.memory_path)
        for stale in self.out.glob('memory.task*.npz'):    # one a kill left before its checkpoint
            stale.unlink(missing_ok=True)

    # -- the loop -----------------------------------------------------------------------------
    def run(self, progress: Callable[[TaskRecord], None] | None = None,
            should_stop: Callable[[], bool] | None = None) -> Metrics:
        """Train on the task sequence (resuming from a checkpoint), then test zero-shot.
        Returns the metrics (also written to out/metrics.json)."""
        self.out.mkdir(parents=True, exist_ok=True)
        s = self.settings
        done = self.done = self._load_checkpoint()
        centre, scale = search_normalisation(self.task, self.default_theta)
        stream = task_stream(self.task, s.seed)            # lazy: any num_tasks is cheap
        for _ in range(len(done)):
            next(stream)                                   # the instances already done
        for index in range(len(done), s.num_tasks):
            if should_stop is not None and should_stop():
                break
            drawn = next(stream)
            if s.task_selection == 'given':
                tau = np.asarray(self.instances(index), dtype=float)
                self.task.validate_tau(tau)
            else:
                tau = drawn if s.task_selection == 'random' else most_uncertain(
                    self.task, self.skill.variance, s.selection_candidates, s.seed, index)
            start, refused, failed = (time.perf_counter(), self.rollouts.refused,
                                      self.rollouts.failed)
            preempted = self.rollouts.preempted
            result = self._search(tau, index, centre, scale)
            confirmed, extra = self._confirm(tau, result)
            if confirmed or not s.add_only_fulfilled:
                self.skill.add(tau, result.theta)
            done.append(TaskRecord(index=index, tau=tau.tolist(),
                                   rollouts=result.rollouts + extra,
                                   fulfilled=result.fulfilled, best_reward=result.reward,
                                   start_reward=result.rewards[0],
                                   seconds=time.perf_counter() - start,
                                   refused=self.rollouts.refused - refused,
                                   failed=self.rollouts.failed - failed,
                                   failure=(self.rollouts.last_failure
                                            if self.rollouts.failed > failed else ''),
                                   unconfirmed=result.fulfilled and not confirmed,
                                   confirm_rollouts=extra,
                                   preempted=self.rollouts.preempted - preempted))
            self._save_checkpoint(done)
            if progress is not None:
                progress(done[-1])
        complete = len(done) == s.num_tasks
        metrics = Metrics(task=self.task.name, strategy=s.strategy, seed=s.seed,
                          settings=json.loads(json.dumps(dataclasses.asdict(s))),
                          tasks=list(done), complete=complete,
                          summary=self.summary(done) if complete else None,
                          task_path=str(self.task.path), task_yaml=self.task.path.read_text())
        metrics.write(self.out)
        return metrics

    def _confirm(self, tau: np.ndarray, result: SearchResult) -> tuple[bool, int]:
        """Whether the search's success holds (`LearnSettings.confirm`: at least k of n
        rollouts of its theta fulfil the instance, the search's own first one counted) and the
        extra rollouts it took. A failed search, or confirm off: (fulfilled, 0)."""
        k, n = self.settings.confirm
        if not result.fulfilled or n == 1:
            return result.fulfilled, 0
        _, fulfilled = self.rollouts.evaluate(np.tile(result.theta, (n - 1, 1)),
                                              np.tile(tau, (n - 1, 1)))
        return 1 + int(np.sum(fulfilled)) >= k, n - 1

    def _search(self, tau: np.ndarray, index: int, centre: np.ndarray,
                scale: np.ndarray) -> SearchResult:
        """One task instance: the strategy's CMA-ES search, preceded by ILC of theta_D for a
        task with feed-forward (`LearnSettings.ilc`)."""
        s = self.settings

        def objective(thetas):
            return self.rollouts.evaluate(thetas, np.tile(tau, (len(thetas), 1)))
        seed = s.seed * 100_003 + index
        if not (self.policy.has_feedforward and s.ilc.iterations):
            alternatives = getattr(self.skill, 'alternatives', lambda _: [])
            return search(s.strategy, objective, tau, self.default_theta, self.skill.query,
                          centre, scale, self.task.tau_low, self.task.tau_high, s.search,
                          seed=seed, alternatives=alternatives(tau))
        start = self.default_theta if s.strategy == 'scratch' else self.skill.query(tau)
        ilc = ilc_search(self.rollouts, tau, start, s.ilc, scale)
        # CMA-ES (any strategy) goes on from ILC's best theta: it is the start and the estimate
        left = s.search.max_rollouts - ilc.rollouts
        if ilc.fulfilled or left <= 0:
            return ilc
        # ILC has found the torque profile: CMA-ES refines theta_D in smaller steps
        refine = scale.copy()
        refine[self.policy.dynamics] *= ILC_REFINE_SHARE
        rest = search(s.strategy, objective, tau, ilc.theta, lambda _: ilc.theta, centre, refine,
                      self.task.tau_low, self.task.tau_high,
                      dataclasses.replace(s.search, max_rollouts=left), seed=seed)
        best = rest if (rest.fulfilled or rest.reward > ilc.reward) else ilc
        return SearchResult(theta=best.theta, reward=best.reward, fulfilled=best.fulfilled,
                            rollouts=ilc.rollouts + rest.rollouts, start_theta=ilc.start_theta,
                            rewards=ilc.rewards + rest.rewards)

    def summary(self, done: list[TaskRecord]) -> Summary:
        test = held_out_tasks(self.task, self.settings.num_test, self.settings.seed)
        thetas = np.array([self.skill.query(t) for t in test])
        results = self.rollouts.run(thetas, test)
        rewards = np.array([r.evaluation.reward for r in results])
        fulfilled = np.array([r.evaluation.fulfilled for r in results])
        # the hand's final miss of the target (a refused or aborted rollout has none: NaN);
        # the orientation where the reward scores it
        scored = [name for name in HAND_ERRORS if name == 'goal_error'
                  or self.task.reward.weights.get(name, 0.0) > 0.0]
        hand_errors = None if self.task.target is None else {
            name: [float(r.evaluation.components.get(name, np.nan)) for r in results]
            for name in scored}
        rollouts = [d.rollouts for d in done]
        tracking = (tracking_comparison(self.rollouts, test, thetas)
                    if self.policy.has_feedforward else None)
        return Summary(total_rollouts=int(sum(rollouts)), rollouts_per_task=rollouts,
                       fulfilled_tasks=int(sum(d.fulfilled for d in done)),
                       unconfirmed_tasks=int(sum(d.unconfirmed for d in done)),
                       confirm_rollouts=int(sum(d.confirm_rollouts for d in done)),
                       test_taus=test.tolist(), test_rewards=[float(r) for r in rewards],
                       zero_shot_success_rate=float(np.mean(fulfilled)),
                       zero_shot_mean_reward=float(np.mean(rewards)),
                       test_hand_errors=hand_errors,
                       tracking_rmse=tracking,
                       tracking_rmse_mean=None if tracking is None else {
                           name: float(np.nanmean(values)) if not np.all(np.isnan(values))
                           else float('nan') for name, values in tracking.items()})


def feedforward_variants(task: TaskDefinition, taus: np.ndarray, thetas: np.ndarray
                         ) -> dict[str, np.ndarray]:
    """The same commanded paths (theta_K of thetas (B, F)) with three feed-forwards:
    ``pd_only`` (theta_D = 0), ``learned`` (thetas as they are) and ``oracle`` (the
    inverse-dynamics theta_D on each task instance of taus (B, E)).

    Raises:
        ValueError: a task without feed-forward.
    """
    policy = policy_for(task)
    if not policy.has_feedforward:
        raise ValueError(f'task {task.name!r} has no feed-forward (policy.feedforward)')
    thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
    taus = np.atleast_2d(np.asarray(taus, dtype=float))
    return {
        'pd_only': np.array([policy.with_feedforward(th, np.zeros(
                             policy.feedforward.num_parameters)) for th in thetas]),
        'learned': thetas,
        'oracle': np.array([oracle_theta(task, tau, th, policy) for tau, th in zip(taus, thetas)]),
    }


def tracking_comparison(rollouts: Rollouts, taus: np.ndarray,
                        thetas: np.ndarray) -> dict[str, list[float]]:
    """RMS tracking error [rad] on each task instance taus (B, E) of its policy thetas (B, F)
    beside the same commanded path with PD only and with the oracle's feed-forward
    (`feedforward_variants`), per variant; NaN for a rollout that did not run (the safety
    check refused that variant, the controller aborted it: no tracking error)."""
    out = {}
    for name, variant in feedforward_variants(rollouts.task, taus, thetas).items():
        rmse = [r.evaluation.components.get('tracking_error', np.nan)
                for r in rollouts.run(variant, taus)]
        out[name] = [float(v) for v in rmse]
    return out


def nothing_scored(tasks: list[TaskRecord]) -> str:
    """Why a session could score none of its rollouts: every one it ran failed to be scored
    by a reward component (each got the task's penalty, so its search learned nothing; the
    candidates the safety check refused never ran), with the counts and the newest reason;
    '' when the reward scored at least one rollout, or none failed."""
    rollouts = sum(t.rollouts for t in tasks)
    failed, refused = sum(t.failed for t in tasks), sum(t.refused for t in tasks)
    if failed == 0 or failed + refused < rollouts:
        return ''
    reason = next((t.failure for t in reversed(tasks) if t.failure), '')
    refusals = f', {refused} refused by the safety check' if refused else ''
    return (f'the reward scored none of the session\'s {rollouts} rollouts ({failed} not scored'
            f'{refusals}): {reason}')
