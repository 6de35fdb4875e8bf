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
(`psl_optimizer.reward.Reward`). This module holds only the registry: it imports nothing of
psl's (the task schema checks names with it).

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

import dataclasses
import difflib
import functools
import sys
from importlib import metadata
from typing import Any, Callable

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
    """A component raised or returned what is not a finite cost per rollout."""


def evaluate(name: str, function: Function, rollouts) -> np.ndarray:
    """The costs (B,) of `function` on the population, checked: one finite number per rollout.

    Raises:
        ComponentFailed: it raised, or returned a wrong shape or a value that is not finite
            (the message names the component and the rollouts).
    """
    try:
        values = np.asarray(function(rollouts), dtype=float)
    except Exception as exc:    # a plugin's bug: the rollout fails with the reason, no more
        raise ComponentFailed(f'reward component {name!r} raised {type(exc).__name__}: '
                              f'{exc}') from exc
    if values.shape != (len(rollouts),):
        raise ComponentFailed(f'reward component {name!r} returned shape {values.shape}, not '
                              f'one cost per rollout ({len(rollouts)},)')
    return values


def failures(name: str, values: np.ndarray) -> dict[int, str]:
    """The rollouts whose cost is not finite, with the reason."""
    return {int(b): f'reward component {name!r} returned {values[b]} (not finite)'
            for b in np.flatnonzero(~np.isfinite(values))}
