"""Reward components: functions of a population of rollouts (psl_task.reward_components).

Each takes a `psl_optimizer.reward.RolloutData` (arrays rollout first, (B, ...)) and
returns one finite cost per rollout, (B,): lower is better. psl weights it with the task's
``reward.weights`` entry of the same name and calls the same function in batch and graph mode.
"""
import numpy as np


def hand_path_length(rollouts) -> np.ndarray:
    """Length [m] of the end effector's path over each rollout: the sum of the distances
    between the hand positions of consecutive states (a detour costs, a straight line is the
    least). rollouts.measured.end_effector is (B, T, 3)."""
    hand = rollouts.measured.end_effector
    return np.linalg.norm(np.diff(hand, axis=1), axis=2).sum(axis=1)
