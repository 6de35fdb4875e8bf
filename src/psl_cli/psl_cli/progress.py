"""The progress of a learning session on stderr (``psl learn``).

On a terminal: one `tqdm` bar over the session's tasks, its postfix the task at hand (in graph
mode redrawn after every CMA-ES batch, from the learner's feedback). Anywhere else (a pipe, a
file, a CI log): one plain line per finished task and nothing in between, so a log holds no
carriage-return redraws.
"""
from __future__ import annotations

import sys
import threading
from typing import TextIO


class LearnProgress:
    """What ``psl learn`` shows while a session runs. `bar`: draw the tqdm bar (default: when
    `stream` is a terminal), else write one line per finished task.

    Tasks are numbered from 0 here and shown from 1. Rollout counts: `rollouts` is the task's
    own, `in_all` the session's so far (the tasks of a resumed checkpoint included)."""

    def __init__(self, num_tasks: int, stream: TextIO | None = None, bar: bool | None = None):
        self.num_tasks = num_tasks
        self.stream = stream if stream is not None else sys.stderr
        if bar is None:
            bar = self.stream.isatty()
        self._lock = threading.Lock()
        self._bar = None
        if bar:
            from tqdm import tqdm
            self._bar = tqdm(total=num_tasks, unit='task', desc='learning', file=self.stream,
                             dynamic_ncols=True, leave=True)
        self._current = None        # graph mode: (index, in_all, best, fulfilled) of the task
        self._ended_at = {}         # graph mode: index -> rollouts in all when it ended

    # -- what happened ----------------------------------------------------------------------
    def finished(self, index: int, best_reward: float, fulfilled: bool, in_all: int,
                 rollouts: int | None = None) -> None:
        """Task `index` is finished (`rollouts`: its own count, if known)."""
        with self._lock:
            self._finished(index, best_reward, fulfilled, in_all, rollouts)

    def batch(self, index: int, in_all: int, best_reward: float, fulfilled: bool) -> None:
        """Graph mode: a batch of task `index` was rolled out (the learn_skill feedback: task
        index, rollouts in all so far, the task's best reward, fulfilled yet). A feedback of a
        later task means the one before it finished with its last feedback."""
        with self._lock:
            if self._current is not None and self._current[0] != index:
                self._finish_current()
            self._current = (index, in_all, best_reward, fulfilled)
            if self._bar is not None:
                state = 'fulfilled' if fulfilled else 'searching'
                self._bar.set_postfix_str(f'task {index + 1} {state}, best {best_reward:.3f}, '
                                          f'{in_all} rollouts in all')

    def close(self, complete: bool = False) -> None:
        """End the display. `complete`: the session finished all its tasks (graph mode: the
        task of the last feedback is then finished too; after a cancel it is not)."""
        with self._lock:
            if complete and self._current is not None:
                self._finish_current()
            self._current = None
            if self._bar is not None:
                self._bar.close()
                self._bar = None

    # -- drawing -----------------------------------------------------------------------------
    def _finish_current(self) -> None:
        index, in_all, best, fulfilled = self._current
        self._current = None
        before = self._ended_at.get(index - 1, 0 if index == 0 else None)
        self._finished(index, best, fulfilled, in_all,
                       None if before is None else in_all - before)

    def _finished(self, index: int, best: float, fulfilled: bool, in_all: int,
                  rollouts: int | None) -> None:
        self._ended_at[index] = in_all
        state = 'fulfilled' if fulfilled else 'NOT fulfilled'
        if self._bar is None:
            count = (f'{in_all} rollouts in all' if rollouts is None
                     else f'{rollouts} rollouts ({in_all} in all)')
            print(f'task {index + 1}/{self.num_tasks} {state}: best reward {best:.3f}, '
                  f'{count}', file=self.stream, flush=True)
            return
        count = f'{in_all} rollouts in all' if rollouts is None else f'{rollouts} rollouts'
        self._bar.n = index + 1
        self._bar.set_postfix_str(f'task {index + 1} {state}, best {best:.3f}, {count}')
