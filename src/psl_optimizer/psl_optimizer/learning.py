"""The learning loop: for each new task instance, search theta starting from the skill, add the
solution to the memory at once, go on; then measure zero-shot success on held-out instances.

Task sequences come from a seed (`task_sequence`); the held-out test instances come from a
separate stream and are never trained on. After every task the loop writes a checkpoint
(memory file + progress JSON) into its output folder, and `Learner.run` resumes from it, so a
crash or a cancel loses no finished task. Imports no ROS; the learner node and ``psl learn``
wrap it.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from psl_controller.policy import policy_for
from psl_memory.parameterized_skill import SkillConfig, scaler_around
from psl_memory.skill_memory import SkillMemory
from psl_optimizer.batch_rollout import BatchRollout
from psl_optimizer.policy_search import SearchSettings, search
from psl_sim.task import TaskDefinition

TEST_SEED_OFFSET = 1_000_003     # held-out instances: a stream no training sequence uses


def task_sequence(task: TaskDefinition, count: int, seed: int) -> np.ndarray:
    """`count` training instances (count, E), uniform over the task's ranges."""
    rng = np.random.default_rng(seed)
    return np.array([task.sample_tau(rng) for _ in range(count)]).reshape(count, -1)


def held_out_tasks(task: TaskDefinition, count: int, seed: int) -> np.ndarray:
    return task_sequence(task, count, seed + TEST_SEED_OFFSET)


@dataclasses.dataclass(frozen=True)
class LearnSettings:
    strategy: str = 'bootstrap'
    num_tasks: int = 30
    seed: int = 0
    num_test: int = 20
    search: SearchSettings = SearchSettings()
    skill: SkillConfig = SkillConfig()  # bayes, fixed precisions: ridge's mean + variance
    add_only_fulfilled: bool = True     # a failed search's best theta would teach the skill a miss


class InProcessSkill:
    """The skill memory as a library, in this process (batch mode's default)."""

    def __init__(self, task: TaskDefinition, config: SkillConfig, default_theta: np.ndarray):
        self.task, self.config, self.default_theta = task, config, default_theta
        self.restore(None)

    def restore(self, path: Path | None) -> None:
        """A fresh skill (path None) or the one saved at path."""
        if path is None:
            self.memory = SkillMemory(self.config)
            self.memory.create(self.task.name, self.task.tau_low, self.task.tau_high,
                               self.default_theta)
        else:
            self.memory = SkillMemory.read(path)

    def query(self, tau: np.ndarray) -> np.ndarray:
        return self.memory.get(self.task.name).query(tau)[0]

    def add(self, tau: np.ndarray, theta: np.ndarray) -> None:
        self.memory.add(self.task.name, tau, theta)

    def save(self, path: Path) -> None:
        self.memory.save(path)


def batch_evaluator(evaluator: BatchRollout):
    """(thetas (B, F), taus (B, E)) -> rewards (B,), fulfilled (B,), all in one batch."""
    def evaluate(thetas: np.ndarray, taus: np.ndarray):
        results = evaluator.run(thetas, taus)
        return (np.array([r.evaluation.reward for r in results]),
                np.array([r.evaluation.fulfilled for r in results]))
    return evaluate


class Learner:
    """Runs one learning session of one task, checkpointing into `out`.

    Args:
        evaluate: (thetas, taus) -> (rewards, fulfilled); default: batch mode in-process.
        skill: object with query/add/save/restore (InProcessSkill, or the skill_memory node
            behind its services); default: InProcessSkill.
    """

    def __init__(self, task: TaskDefinition, settings: LearnSettings, out: str | Path,
                 evaluator: BatchRollout | None = None, evaluate=None, skill=None):
        self.task, self.settings, self.out = task, settings, Path(out)
        self.default_theta = policy_for(task).default_theta
        if evaluate is None:
            evaluate = batch_evaluator(evaluator or BatchRollout(task))
        self.evaluate = evaluate
        self.skill = skill or InProcessSkill(task, settings.skill, self.default_theta)
        self.done: list[dict] = []      # finished tasks' records (from the checkpoint, then run)

    # -- checkpoints --------------------------------------------------------------------------
    @property
    def checkpoint_path(self) -> Path:
        return self.out / 'checkpoint.json'

    @property
    def memory_path(self) -> Path:
        return self.out / 'memory.npz'

    def _load_checkpoint(self) -> list[dict]:
        if not self.checkpoint_path.is_file():
            self.skill.restore(None)
            return []
        state = json.loads(self.checkpoint_path.read_text())
        mine = {'task': self.task.name, 'strategy': self.settings.strategy,
                'seed': self.settings.seed}
        if any(state.get(k) != v for k, v in mine.items()):
            raise ValueError(f'{self.out} holds a checkpoint of another session '
                             f'({ {k: state.get(k) for k in mine} }); use another folder')
        self.skill.restore(self.memory_path)
        return state['tasks']

    def _save_checkpoint(self, done: list[dict]) -> None:
        self.skill.save(self.memory_path)             # atomic
        state = {'task': self.task.name, 'strategy': self.settings.strategy,
                 'seed': self.settings.seed, 'tasks': done}
        tmp = self.checkpoint_path.with_suffix('.tmp')
        tmp.write_text(json.dumps(state))
        os.replace(tmp, self.checkpoint_path)

    # -- the loop -----------------------------------------------------------------------------
    def run(self, progress: Callable[[dict], None] | None = None,
            should_stop: Callable[[], bool] | None = None) -> dict:
        """Train on the task sequence (resuming from a checkpoint), then test zero-shot.
        Returns the metrics (also written to out/metrics.json)."""
        self.out.mkdir(parents=True, exist_ok=True)
        s = self.settings
        done = self.done = self._load_checkpoint()
        scaler = scaler_around(self.default_theta)      # the skill's own theta scaling
        centre, scale = 0.5 * (scaler.high + scaler.low), 0.5 * (scaler.high - scaler.low)
        taus = task_sequence(self.task, s.num_tasks, s.seed)
        for index in range(len(done), s.num_tasks):
            if should_stop is not None and should_stop():
                break
            tau = taus[index]
            start = time.perf_counter()
            result = search(s.strategy, lambda thetas: self.evaluate(thetas, np.tile(
                                tau, (len(thetas), 1))),
                            tau, self.default_theta, self.skill.query, centre, scale,
                            self.task.tau_low, self.task.tau_high, s.search,
                            seed=s.seed * 100_003 + index)
            if result.fulfilled or not s.add_only_fulfilled:
                self.skill.add(tau, result.theta)
            done.append({'index': index, 'tau': tau.tolist(), 'rollouts': result.rollouts,
                         'fulfilled': result.fulfilled, 'best_reward': result.reward,
                         'start_reward': result.rewards[0],
                         'seconds': time.perf_counter() - start})
            self._save_checkpoint(done)
            if progress is not None:
                progress(done[-1])
        metrics = {'task': self.task.name, 'strategy': s.strategy, 'seed': s.seed,
                   'settings': dataclasses.asdict(s), 'tasks': done,
                   'complete': len(done) == s.num_tasks}
        if metrics['complete']:
            metrics['summary'] = self.summary(done)
        (self.out / 'metrics.json').write_text(json.dumps(metrics, indent=1))
        return metrics

    def summary(self, done: list[dict]) -> dict:
        test = held_out_tasks(self.task, self.settings.num_test, self.settings.seed)
        thetas = np.array([self.skill.query(t) for t in test])
        rewards, fulfilled = self.evaluate(thetas, test)
        rollouts = [d['rollouts'] for d in done]
        return {
            'total_rollouts': int(sum(rollouts)),
            'rollouts_per_task': rollouts,
            'fulfilled_tasks': int(sum(d['fulfilled'] for d in done)),
            'test_taus': test.tolist(),
            'test_rewards': [float(r) for r in rewards],
            'zero_shot_success_rate': float(np.mean(fulfilled)),
            'zero_shot_mean_reward': float(np.mean(rewards)),
        }
