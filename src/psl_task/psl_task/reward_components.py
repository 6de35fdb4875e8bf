"""The registry of reward components: every component, psl's own and a user's, is a Python
entry point of the group ``psl.reward_components``.

A reward component is a cost of each rollout of a population (lower is better, zero is
perfect), written once as a vectorised function with this signature:

    def my_component(rollouts: RolloutData) -> numpy.ndarray:   # (B,) finite floats

`psl_optimizer.reward.RolloutData` holds what both rollout modes measured, rollout first
(``(B, ...)``): the joint angles, torques and reference per control period, the reward's
geometry along the rollouts (end-effector position and orientation, arm-obstacle distance),
the task instances, their goals, and the poses of the bodies of the world the task observes.
Batch mode and graph mode build the same `RolloutData` and call the same function. The task YAML
names a component in ``reward.weights``; the reward is ``-sum(weight * cost)``
(`psl_optimizer.reward.Reward`). This module holds the registry and how a component is
called; it imports nothing of psl's (the task schema checks names with it).

A component cannot hurt the others or the session: it gets read-only views of its inputs
(`read_only`: a write raises), runs on a worker thread within the task's
``reward.component_timeout`` (`BoundedCalls`), and must return one finite real number per
rollout (`costs`, `failures`). A component that raises (a write into its inputs too), returns
anything else or does not return in time fails the rollouts it could not score, with the
reason; the others are scored (`psl_optimizer.reward.Reward`).

A package registers a component in its packaging metadata, e.g. in ``pyproject.toml``:

    [project.entry-points."psl.reward_components"]
    hand_path_length = "my_package.costs:hand_path_length"

and is found once it is installed (or on the Python path) — psl's sources are not touched. The
seven built-ins (`psl_optimizer.reward`) are registered the same way by psl_optimizer. Names
are read from the packages' metadata without importing them (`registered`), so a task file is
checked against them (`check_names`, the nearest names for a typo) before any plugin code
runs; a component's function is imported when a reward first needs it (`load`). A name
registered by two packages is refused (which one would run is not up to psl). Imports no ROS.
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import os
import queue
import sys
import threading
import time
import types
from importlib import metadata
from typing import Any, Callable, Mapping

import numpy as np

GROUP = 'psl.reward_components'


Function = Callable[[Any], np.ndarray]    # RolloutData -> (B,)


@dataclasses.dataclass(frozen=True)
class Registration:
    """Where a component comes from: its entry point and the package that registers it."""

    name: str
    target: str             # 'module:function'
    package: str            # the distribution's name and version, e.g. 'psl_optimizer 0.1.0'

    def __str__(self) -> str:
        return f'{self.name}: {self.target} ({self.package})'


def _entry_points() -> dict[str, list[metadata.EntryPoint]]:
    return _scan(tuple(sys.path))


@functools.lru_cache(maxsize=8)
def _scan(path: tuple[str, ...]) -> dict[str, list[metadata.EntryPoint]]:
    """The group's entry points on the Python path `path` (a scan of every installed
    package's metadata: tens of milliseconds, so kept per path)."""
    found: dict[str, list[metadata.EntryPoint]] = {}
    for entry in metadata.entry_points(group=GROUP):
        if all(e.value != entry.value for e in found.get(entry.name, [])):
            found.setdefault(entry.name, []).append(entry)
    return found


def registered() -> dict[str, Registration]:
    """Every registered component by name, read from the installed packages' metadata (no
    plugin is imported); read once per Python path (a package put on the path counts).

    Raises:
        ValueError: a name registered by two packages, naming both.
    """
    out = {}
    for name, entries in sorted(_entry_points().items()):
        registrations = [Registration(name, e.value, _package(e)) for e in entries]
        if len(registrations) > 1:
            raise ValueError(f'reward component {name!r} is registered twice: '
                             + ' and '.join(f'{r.target} ({r.package})' for r in registrations))
        out[name] = registrations[0]
    return out


def _package(entry: metadata.EntryPoint) -> str:
    dist = getattr(entry, 'dist', None)
    return f'{dist.metadata["Name"]} {dist.version}' if dist is not None else 'unknown package'


def check_names(names, where: str = 'reward.weights') -> None:
    """ValueError for a name no package registers, with the nearest registered name."""
    known = registered()
    for name in names:
        if name not in known:
            close = difflib.get_close_matches(str(name), list(known), n=1, cutoff=0.6)
            hint = f' (did you mean {close[0]}?)' if close else ''
            raise ValueError(f'{where} has unknown reward component {name!r}{hint}; '
                             f'registered: {", ".join(known)} (psl check lists where from)')


_loaded: dict[tuple[str, str], Function] = {}


def load(name: str) -> Function:
    """The function of the component `name`, imported on first use.

    Raises:
        ValueError: an unregistered name, or an entry point that is not a function.
    """
    check_names([name], 'a reward')
    registration = registered()[name]
    key = (name, registration.target)
    if key not in _loaded:
        entry = _entry_points()[name][0]
        try:
            function = entry.load()
        except Exception as exc:    # a plugin's import error: said with its name
            raise ValueError(f'reward component {name!r} ({registration.target}) could not be '
                             f'imported: {type(exc).__name__}: {exc}') from exc
        if not callable(function):
            raise ValueError(f'reward component {name!r} ({registration.target}) is not a '
                             'function of RolloutData')
        _loaded[key] = function
    return _loaded[key]


class ComponentFailed(Exception):
    """A component raised, returned what is not a finite real cost per rollout, or did not
    return in time."""


class ComponentTimedOut(ComponentFailed):
    """A component's call did not return within its bound (the population's rollouts not
    failed yet fail with it), or its earlier call that did not still runs (its rollouts fail
    with it)."""


# -- what a component sees: read-only views ---------------------------------------------------
def read_only(value: Any) -> Any:
    """`value` as a component sees it, so that nothing it does to its inputs changes what the
    other components (and psl) see: an array as a read-only view (a write raises ValueError:
    assignment destination is read-only; psl's array itself stays writeable), a mapping as a
    read-only mapping (`types.MappingProxyType`; an assignment raises TypeError) of such
    values, a list or tuple as a tuple of them (a named tuple as its own type), a set as a frozenset, a frozen dataclass as a
    copy whose fields (and anything cached beside them) are such (an assignment raises
    FrozenInstanceError). Numbers, strings, paths, frozen pydantic models and other values
    are returned as they are. A component runs in psl's process: this stops writes through
    what it is given, not code that sets out to get around it.

    Raises:
        TypeError: a dataclass that is not frozen (its copy could be assigned to).
    """
    if isinstance(value, np.ndarray):
        if not value.flags.writeable:
            return value
        view = value.view()
        view.flags.writeable = False
        return view
    if isinstance(value, Mapping):
        return types.MappingProxyType({key: read_only(item) for key, item in value.items()})
    if isinstance(value, (list, tuple)):
        items = (read_only(item) for item in value)
        return type(value)(*items) if hasattr(value, '_fields') else tuple(items)   # namedtuple
    if isinstance(value, (set, frozenset)):
        return frozenset(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        if not type(value).__dataclass_params__.frozen:
            raise TypeError(f'{type(value).__qualname__} is not a frozen dataclass: a reward '
                            'component could assign to it')
        view = copy.copy(value)
        attributes = (vars(value) if hasattr(value, '__dict__')
                      else {f.name: getattr(value, f.name) for f in dataclasses.fields(value)})
        for key, item in attributes.items():
            object.__setattr__(view, key, read_only(item))
        return view
    return value


# -- a component's call, bounded in time ------------------------------------------------------
KEPT_WORKERS = 2        # idle worker threads kept for the next populations (more end)
Call = Callable[[str, Function, Any], tuple[np.ndarray | None, BaseException | None]]


class _Abandoned(Exception):
    """Ends the work of a population whose caller has given up on it."""


class _Job:
    """The work of one population, handed to a worker thread."""

    __slots__ = ('work', 'lock', 'done', 'value', 'error', 'running', 'abandoned')

    def __init__(self, work: Callable[[Call], Any]):
        self.work = work
        self.lock = threading.Lock()     # the caller's giving up against the worker's progress
        self.done = threading.Event()
        self.value: Any = None
        self.error: BaseException | None = None
        self.running: tuple[str, float] | None = None   # the component called, since when
        self.abandoned = False           # the caller gave up: the work's results are dropped


class _Worker(threading.Thread):
    """A daemon thread that runs the jobs put in its inbox (a component that never returns
    keeps it, and the process can still end)."""

    def __init__(self, calls: 'BoundedCalls'):
        super().__init__(name='psl reward component', daemon=True)
        self.calls = calls
        self.inbox: queue.SimpleQueue[_Job] = queue.SimpleQueue()

    def run(self) -> None:
        while True:
            job = self.inbox.get()
            try:
                job.value = job.work(functools.partial(self.calls.call_in, job))
            except _Abandoned:
                pass
            except BaseException as exc:    # psl's own error: raised again to the caller
                job.error = exc
            if not self.calls.finished(self, job):
                return


class BoundedCalls:
    """The components' calls on a population, on a worker thread, each call bounded in time.

    The caller hands the whole work of a population (every component, and each rollout alone
    where a component fails on the population) to a waiting worker thread in one hand-over
    and waits for it; the worker calls each component through `call_in`, which notes the call
    and its start. When a call passes its bound, the caller gives up on the population
    (`ComponentTimedOut`) while the worker is inside that call. Python cannot stop a thread,
    so the call is left to run; when it returns, its result and the rest of the population's
    work are dropped. Until then, further calls of that component fail at once with the reason
    instead of piling up threads, and other populations run on another worker. Idle workers
    are kept (at most `KEPT_WORKERS`): no new thread per population.
    """

    def __init__(self):
        self._reset()

    def _reset(self) -> None:
        self._lock = threading.Lock()
        self._idle: list[_Worker] = []
        self._late: dict[str, float] = {}   # component -> the bound its running call passed

    def run(self, work: Callable[[Call], Any], timeout: float) -> Any:
        """``work(call)`` on a worker thread, where ``call(name, function, argument)`` is
        `call_in`: each component's call bounded by `timeout` s. Returns what `work` returns.

        Raises:
            ComponentTimedOut: a component's call did not return within `timeout` s (the work
                is left to end on its own; what it did so far stays as it was when the call
                began, what it would do after is dropped).
            BaseException: what `work` itself raised.
        """
        with self._lock:
            worker = self._idle.pop() if self._idle else None
        if worker is None:
            worker = _Worker(self)
            worker.start()
        job = _Job(work)
        worker.inbox.put(job)
        wait = timeout
        while not job.done.wait(wait):
            with job.lock:
                if job.done.is_set():
                    break
                now = time.monotonic()
                if job.running is None:             # between two calls: psl's own work
                    wait = timeout
                    continue
                name, started = job.running
                if now - started < timeout:
                    wait = started + timeout - now
                    continue
                job.abandoned = True
                with self._lock:
                    self._late[name] = timeout
                raise ComponentTimedOut(f'reward component {name!r} did not return within '
                                        f'{timeout:g} s (reward.component_timeout)')
        if job.error is not None:
            raise job.error
        return job.value

    def call_in(self, job: _Job, name: str, function: Function,
                argument) -> tuple[np.ndarray | None, BaseException | None]:
        """On the worker: `function(argument)` as an array (its value) or what it raised
        (its error; SystemExit too), its start noted for the caller's bound.

        Raises:
            ComponentTimedOut: an earlier call of the component `name` that passed its bound
                still runs.
            _Abandoned: the caller gave up on the job while the call ran.
        """
        with job.lock, self._lock:
            if name in self._late:
                raise ComponentTimedOut(
                    f'reward component {name!r} has not returned from a call that passed its '
                    f'{self._late[name]:g} s (reward.component_timeout): its rollouts fail '
                    'until it does')
            job.running = (name, time.monotonic())
        value = error = None
        try:         # converted here, within the call's time (an __array__ of its own too)
            value = np.asarray(function(argument))
        except BaseException as exc:    # SystemExit of a plugin too: its call's failure
            error = exc
        with job.lock:
            job.running = None
            if job.abandoned:
                with self._lock:
                    self._late.pop(name, None)
                raise _Abandoned
        return value, error

    def finished(self, worker: _Worker, job: _Job) -> bool:
        """`worker` has ended `job`: hand it to its caller; True when the worker is kept for
        the next job."""
        with job.lock:
            with self._lock:
                keep = len(self._idle) < KEPT_WORKERS
                if keep:
                    self._idle.append(worker)
            job.done.set()
        return keep


CALLS = BoundedCalls()      # the process's (a child forked from it starts with none)
os.register_at_fork(after_in_child=CALLS._reset)


# -- what a component may return -----------------------------------------------------------
KINDS = {'c': 'complex numbers', 'U': 'text', 'S': 'bytes', 'O': 'Python objects',
         'M': 'dates', 'm': 'time spans', 'V': 'records'}    # numpy dtype kinds, not reals


def costs(name: str, returned: np.ndarray, count: int) -> np.ndarray:
    """The costs (count,) a component returned, as floats (a copy: nothing the component
    keeps can change them later); NaN and inf are left to `failures`.

    Raises:
        ComponentFailed: not real numbers (complex, text, objects, ...; booleans count as 0
            and 1), or not one per rollout.
    """
    if returned.dtype.kind not in 'biuf':
        first = f' ({_brief(returned.ravel()[:1].tolist()[0])}, ...)' if returned.size else ''
        raise ComponentFailed(f'reward component {name!r} returned '
                              f'{KINDS.get(returned.dtype.kind, str(returned.dtype))}{first}, '
                              'not real costs')
    if returned.shape != (count,):
        raise ComponentFailed(f'reward component {name!r} returned shape {returned.shape}, '
                              f'not one cost per rollout ({count},)')
    return returned.astype(float)


def _brief(value, width: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= width else text[:width - 3] + '...'


def evaluate(name: str, function: Function, rollouts, call: Call) -> np.ndarray:
    """The costs (B,) of `function` on the population `rollouts` (as a reward gives it:
    `read_only`), called through `call` (the bounded call of `BoundedCalls.run`), checked: one
    real number per rollout (a NaN or inf fails its rollout alone: `failures`).

    Raises:
        ComponentTimedOut: its earlier call that did not return in time still runs.
        ComponentFailed: it raised (a write into its inputs too), or returned what is not one
            real number per rollout (`costs`); the message names the component.
    """
    returned, error = call(name, function, rollouts)
    if error is not None:   # a plugin's bug: the rollout fails with the reason, no more
        raise ComponentFailed(f'reward component {name!r} raised {type(error).__name__}: '
                              f'{error}') from error
    return costs(name, returned, len(rollouts))


def failures(name: str, values: np.ndarray) -> dict[int, str]:
    """The rollouts whose cost is not finite, with the reason."""
    return {int(b): f'reward component {name!r} returned {values[b]} (not finite)'
            for b in np.flatnonzero(~np.isfinite(values))}
