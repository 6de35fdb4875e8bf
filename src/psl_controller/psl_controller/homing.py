"""The homing motion of a ``drive`` reset: from where the arm is to the start posture.

A real arm cannot be teleported: before each episode the executor drives it from its measured
posture q0 (velocity qd0) to the task's start posture q1 along a quintic per joint, the
polynomial with the given position and velocity and zero acceleration at the start and rest at
the end (position q1, zero velocity and acceleration)::

    q(s) = q0 + qd0 T s + (10 d - 6 qd0 T) s^3 + (-15 d + 8 qd0 T) s^4 + (6 d - 3 qd0 T) s^5,

s = t / T, d = q1 - q0, then holds q1 for the settle time. From rest its peak velocity is
15 d / (8 T) and its peak acceleration 10 d / (sqrt(3) T^2): the duration is the shortest that
keeps every joint within ``max_velocity`` and ``max_acceleration`` (and at least
``min_duration``).

An arm that still moves is first braked to rest: the same quintic from (q0, qd0) to
qb = q0 + qd0 Tb / 2, whose velocity qd0 (1 - 3 s^2 + 2 s^3) falls to zero without reversing
and whose deceleration peaks at 1.5 |qd0| / Tb, so Tb = 1.5 max|qd0| / ``max_acceleration``
(braking distance 0.75 qd0^2 / max_acceleration); then the quintic from rest at qb to q1.
(Carrying qd0 through the whole homing instead moves a joint about 0.19 qd0 T beyond its
start: 34 rad for an oscillating arm homed over 4.5 s, which the safety check refused.)

Its feed-forward is the model's inverse dynamics along the quintic when one is given
(``feed_forward(q, qd, qdd)``, e.g. `psl_task.arm_model.ArmModel.inverse_dynamics` with the
instance applied): the torque that carries the arm and holds it against gravity at the start
posture, so that PD corrects only the model's error (a payload arm under PD alone sags by
``g(q) / kp``). On a robot the model does not match, the arm still comes to rest off the start,
by about ``(g_robot - g_model) / kp``: a hold with the held torque raised by
``(kp + dg/dq) (q1 - q)`` measured cancels that to first order (a Newton step on the held
torque, `corrected_hold`). Imports no ROS.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from psl_controller.policy import Reference
from psl_task.task import HomingSpec

PEAK_VELOCITY = 15.0 / 8.0              # x d / T, from rest
PEAK_ACCELERATION = 10.0 / np.sqrt(3.0)  # x d / T^2, from rest


def quintic(q0: np.ndarray, qd0: np.ndarray, q1: np.ndarray, duration: float,
            t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity and acceleration (len(t), n) of the quintic of the module doc at
    times t (clipped to [0, duration]: before, q0; after, q1 at rest)."""
    T = float(duration)
    s = np.clip(np.asarray(t, dtype=float) / T, 0.0, 1.0)[:, None]
    d, v = q1 - q0, qd0 * T
    c3, c4, c5 = 10 * d - 6 * v, -15 * d + 8 * v, 6 * d - 3 * v
    q = q0 + v * s + c3 * s**3 + c4 * s**4 + c5 * s**5
    qd = (v + 3 * c3 * s**2 + 4 * c4 * s**3 + 5 * c5 * s**4) / T
    qdd = (6 * c3 * s + 12 * c4 * s**2 + 20 * c5 * s**3) / T**2
    after = (np.asarray(t, dtype=float) > T)[:, None]
    return (np.where(after, q1, q), np.where(after, 0.0, qd), np.where(after, 0.0, qdd))


def homing_duration(q0: np.ndarray, q1: np.ndarray, spec: HomingSpec, dt: float) -> float:
    """The shortest duration, a whole number of control periods dt, whose quintic from rest
    at q0 to rest at q1 keeps every joint within the spec's velocity and acceleration limits
    (its peaks 15 d / (8 T) and 10 d / (sqrt(3) T^2): module doc), at least
    ``min_duration``."""
    d = np.abs(np.asarray(q1, dtype=float) - np.asarray(q0, dtype=float)).max(initial=0.0)
    T = max(spec.min_duration, PEAK_VELOCITY * d / spec.max_velocity,
            np.sqrt(PEAK_ACCELERATION * d / spec.max_acceleration))
    return float(dt * np.ceil(T / dt - 1e-9))


FeedForward = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def braking_duration(qd0: np.ndarray, spec: HomingSpec, dt: float) -> float:
    """The shortest whole number of control periods in which the braking quintic (module
    doc) stops every joint within ``max_acceleration``; 0 for an arm at rest."""
    peak = np.abs(np.asarray(qd0, dtype=float)).max(initial=0.0)
    return 0.0 if peak == 0.0 else float(dt * np.ceil(1.5 * peak / spec.max_acceleration
                                                       / dt - 1e-9))


def homing_reference(q0: np.ndarray, qd0: np.ndarray, q1: np.ndarray, spec: HomingSpec,
                     dt: float, feed_forward: FeedForward | None = None) -> Reference:
    """The homing motion sampled every control period dt: a moving arm braked to rest, the
    quintic from rest to q1, then ``settle_time`` held at q1 (module doc); feed-forward
    ``feed_forward(q, qd, qdd)`` on those samples (T, n), else zero."""
    q0, qd0, q1 = (np.asarray(a, dtype=float) for a in (q0, qd0, q1))
    Tb = braking_duration(qd0, spec, dt)
    qb = q0 + 0.5 * qd0 * Tb                    # where braking brings the arm to rest
    rest = np.zeros_like(q0)
    T = homing_duration(qb, q1, spec, dt)
    t = np.arange(int(round((Tb + T + spec.settle_time) / dt)) + 1) * dt
    braking = t < Tb - 0.5 * dt
    parts = [quintic(qb, rest, q1, T, t[~braking] - Tb)]
    if braking.any():
        parts.insert(0, quintic(q0, qd0, qb, Tb, t[braking]))
    q, qd, qdd = (np.concatenate([part[k] for part in parts]) for k in range(3))
    u = np.zeros_like(q) if feed_forward is None else np.asarray(feed_forward(q, qd, qdd),
                                                                  dtype=float)
    return Reference(t=t, q=q, qd=qd, u_ffwd=u)


def hold_stiffness(kp: np.ndarray, feed_forward: FeedForward, q1: np.ndarray,
                   step: float = 1e-4) -> np.ndarray:
    """The stiffness (n, n) of the arm held at q1 under PD with its gravity: kp + dg/dq, the
    gravity torque's Jacobian by central differences of the model's inverse dynamics at
    rest, ``feed_forward`` (with None: kp alone)."""
    K = np.diag(np.asarray(kp, dtype=float))
    if feed_forward is None:
        return K
    q1 = np.asarray(q1, dtype=float)
    n = len(q1)
    probes = np.concatenate([q1 + step * np.eye(n), q1 - step * np.eye(n)])
    g = np.asarray(feed_forward(probes, np.zeros_like(probes), np.zeros_like(probes)))
    return K + (g[:n] - g[n:]).T / (2 * step)


def corrected_hold(q1: np.ndarray, u_held: np.ndarray, stiffness: np.ndarray, q: np.ndarray,
                   duration: float, dt: float) -> Reference:
    """Hold q1 at rest for duration with the held torque u_held + K (q1 - q), q the posture
    the arm came to rest at under u_held and K its `hold_stiffness`: at rest the PD law
    balances the robot's gravity, kp (q1 - q) + u_held = g_robot(q), and g_robot(q1) is
    g_robot(q) + dg/dq (q1 - q) to first order, so the raised torque holds the arm at q1 (one
    Newton step; the model's dg/dq stands for the robot's, friction aside)."""
    q1 = np.asarray(q1, dtype=float)
    u = np.asarray(u_held, dtype=float) + np.asarray(stiffness, dtype=float) @ (
        q1 - np.asarray(q, dtype=float))
    t = np.arange(int(round(duration / dt)) + 1) * dt
    return Reference(t=t, q=np.tile(q1, (len(t), 1)), qd=np.zeros((len(t), len(q1))),
                     u_ffwd=np.tile(u, (len(t), 1)))
