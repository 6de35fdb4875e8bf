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

Within the joint ranges (``low``, ``high``: the safety check's, with its margin), one law
(`psl_task.safety_check`): no joint's distance to its range grows along the homing, and every
joint ends inside. The quintic from rest is monotone in every joint (its velocity
30 d s^2 (1 - s)^2 / T never changes sign), so from q0 to q1 inside a joint inside stays inside
and a joint outside only comes closer. The braking is monotone too, and stops short of the
range's bound ahead of each joint: its velocity is cut to ``2 room / Tb`` (`braking_velocity`),
room the distance from q0 to that bound, none for a joint outside moving away from its range
(the reference then starts at rest there, and the controller brakes the arm). Sent to the
controller, a homing from outside starts at its first point inside every range
(`psl_task.safety_check.inside_from`): the points of the goal are all inside, and the segment
from the measured state to that point is the controller's own (JTC's: a first point later than
the start).

Its feed-forward is the model's inverse dynamics along the quintic when one is given
(``feed_forward(q, qd, qdd)``, e.g. `psl_task.arm_model.ArmModel.inverse_dynamics` with the
instance applied): the torque that carries the arm and holds it against gravity at the start
posture, so that PD corrects only the model's error (a payload arm under PD alone sags by
``g(q) / kp``). On a robot the model does not match, the arm still comes to rest off the start,
by about ``(g_robot - g_model) / kp``: a hold with the held torque raised by
``(kp + dg/dq) (q1 - q)`` measured cancels that to first order (a Newton step on the held
torque, `corrected_hold`). Sent to the controller, every homing goal's feed-forward is clipped
into the torque limits (`psl_controller.episode.Episode`): the PD law clips the total torque
there anyway, and a controller rejects a goal whose effort passes them, while the model's
inverse dynamics may ask for more (ball_throw's shoulder held at 3 rad needs 192 N m of its 80;
a reference touching a joint's stop adds the stop's force). Imports no ROS.
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


ROOM_SHARE = 1.0 - 1e-9     # of the room ahead the braking may use: its last point, rounded,
                            # stays inside


def braking_velocity(q0: np.ndarray, qd0: np.ndarray, duration: float, low: np.ndarray,
                     high: np.ndarray) -> np.ndarray:
    """The velocity (n,) the braking quintic starts from: qd0, cut where braking over
    `duration` would carry a joint past the bound ahead of it (braking distance
    qd0 duration / 2, module doc): to 2 room / duration, room the distance from q0 to that
    bound; 0 for a joint outside its range moving away from it."""
    q0, qd0 = np.asarray(q0, dtype=float), np.asarray(qd0, dtype=float)
    if duration <= 0.0:
        return qd0
    room = np.maximum(np.where(qd0 > 0.0, high - q0, q0 - low), 0.0)    # inf: unlimited
    cap = 2.0 * ROOM_SHARE * room / duration
    return np.sign(qd0) * np.minimum(np.abs(qd0), cap)


def homing_reference(q0: np.ndarray, qd0: np.ndarray, q1: np.ndarray, spec: HomingSpec,
                     dt: float, feed_forward: FeedForward | None = None,
                     low: np.ndarray | None = None, high: np.ndarray | None = None
                     ) -> Reference:
    """The homing motion sampled every control period dt: a moving arm braked to rest, the
    quintic from rest to q1, then ``settle_time`` held at q1 (module doc); feed-forward
    ``feed_forward(q, qd, qdd)`` on those samples (T, n), else zero. `low`, `high`: the joint
    ranges (n,) the braking keeps to (`braking_velocity`; None: unlimited)."""
    q0, qd0, q1 = (np.asarray(a, dtype=float) for a in (q0, qd0, q1))
    low = np.full_like(q0, -np.inf) if low is None else np.asarray(low, dtype=float)
    high = np.full_like(q0, np.inf) if high is None else np.asarray(high, dtype=float)
    Tb = braking_duration(qd0, spec, dt)
    qd0 = braking_velocity(q0, qd0, Tb, low, high)    # a cut joint brakes more gently
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
