"""Where a thrown object lands: the reward component ``landing_error``, written as a plugin is
(a function of `psl_optimizer.reward.RolloutData`, registered under the entry point group
``psl.reward_components`` in this package's setup.cfg; `psl_task.reward_components`).

The object is the first body the task observes (``reward.observe``), its poses per state
``RolloutData.world[body]`` (B, T, 7). It lands where its centre first comes down through the
target's height (the target's z: for a ball on the floor, its radius), between the two states
around that crossing by linear interpolation; an object that never comes down through it (still
in the hand, or still flying) is taken where it is at the episode's end. The cost is the
horizontal (x-y) distance of that point to the target. Imports no ROS.
"""
from __future__ import annotations

import numpy as np


def landing_points(poses: np.ndarray, height: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The landing point (B, 3) of each path of positions poses[..., :3] (B, T, 3+) through
    the heights height (B,), and whether it came down through it (B,) (else: the last
    position)."""
    z = poses[:, :, 2] - height[:, None]
    down = (z[:, :-1] > 0.0) & (z[:, 1:] <= 0.0)                   # (B, T-1)
    landed = down.any(axis=1)
    k = np.where(landed, down.argmax(axis=1), poses.shape[1] - 2)   # the state before
    rows = np.arange(len(poses))
    before, after = poses[rows, k, :3], poses[rows, k + 1, :3]
    share = np.where(landed, z[rows, k] / np.where(landed, z[rows, k] - z[rows, k + 1], 1.0),
                     1.0)
    return before + share[:, None] * (after - before), landed


def landing_error(rollouts) -> np.ndarray:
    """Horizontal distance [m] of each rollout's landing point to its target (B,)."""
    observe = rollouts.task.reward.observe
    if not observe:
        raise ValueError('landing_error needs an observed body (reward.observe: [ball])')
    poses = rollouts.world.get(observe[0])
    if poses is None:
        raise ValueError(f'no poses of {observe[0]!r} were measured')
    point, _ = landing_points(poses, rollouts.goal_position[:, 2])
    return np.linalg.norm(point[:, :2] - rollouts.goal_position[:, :2], axis=1)
