"""Unit quaternions for orientations, the one module of psl's quaternion math: product,
conjugate, log and exp maps, geodesic resampling (the pose DMP's, Ude et al. 2014); and, over
any leading shape for the vectorised kinematics (`psl_task.site_chain`, the IK's errors), the
quaternion of a rotation matrix (Bar-Itzhack 2000), the rotation vector and the angle between
orientations.

A quaternion is a numpy array ``[w, x, y, z]`` (scalar first; scipy's ``Rotation`` takes
``[x, y, z, w]``); the functions take any leading shape ``(..., 4)``. A unit quaternion ``q``
and ``-q`` are the same rotation. The maps follow Ude et al. (2014), Sec. III, in the
rotation-vector convention: :func:`log_map` returns the rotation vector ``theta u`` (angle
times unit axis), which is twice the quaternion logarithm of the paper,

    2 log(q) = 2 arccos(w) v / |v|   (v != 0),   0   (v = 0),

and :func:`exp_map` is its inverse, the paper's ``exp(r / 2)``,

    exp_map(r) = [cos(|r| / 2), sin(|r| / 2) r / |r|]   (r != 0),   [1, 0, 0, 0]   (r = 0).

Unlike the paper's arccos form, :func:`log_map` takes the shorter way: it maps ``q`` and ``-q``
to the same rotation vector, of angle in [0, pi], and it is accurate near the identity (it uses
``atan2(|v|, |w|)``, not ``arccos(w)``). Pure numpy; no ROS.

References
----------
Bar-Itzhack, I. Y. (2000). New method for extracting the quaternion from a rotation matrix.
Journal of Guidance, Control, and Dynamics, 23(6), 1085-1087.

Ude, A., Nemec, B., Petric, T., Morimoto, J. (2014). Orientation in Cartesian space dynamic
movement primitives. IEEE International Conference on Robotics and Automation (ICRA),
2997-3004. doi:10.1109/ICRA.2014.6907291
"""

import numpy as np

# Named slices of a quaternion [w, x, y, z].
W = 0
VEC = slice(1, 4)

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
IDENTITY.setflags(write=False)
UNIT_TOLERANCE = 1e-6  # | |q| - 1 | accepted by as_unit_quaternion (then normalised)


def _quaternions(q, name: str = 'q') -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.ndim < 1 or q.shape[-1] != 4:
        raise ValueError(f'{name} must have shape (..., 4) as [w, x, y, z], got {q.shape}')
    return q


def _rotation_vectors(r, name: str = 'r') -> np.ndarray:
    r = np.asarray(r, dtype=float)
    if r.ndim < 1 or r.shape[-1] != 3:
        raise ValueError(f'{name} must have shape (..., 3), got {r.shape}')
    return r


def as_unit_quaternion(value, name: str = 'q') -> np.ndarray:
    """A validated unit quaternion, shape (4,), normalised.

    Args:
        value: ``[w, x, y, z]``.
        name: what the value is, for the error message.

    Raises:
        ValueError: not of shape (4,), not finite, or a norm further than ``UNIT_TOLERANCE``
        from 1.
    """
    q = np.asarray(value, dtype=float)
    if q.shape != (4,):
        raise ValueError(f'{name} must be a quaternion [w, x, y, z] of shape (4,), got {q.shape}')
    if not np.all(np.isfinite(q)):
        raise ValueError(f'{name} must be finite, got {q}')
    norm = np.linalg.norm(q)
    if abs(norm - 1.0) > UNIT_TOLERANCE:
        raise ValueError(f'{name} must be a unit quaternion (|{name}| within {UNIT_TOLERANCE:g} '
                         f'of 1), got |{name}| = {norm:.9g}')
    return q / norm


def product(p, q) -> np.ndarray:
    """Hamilton product ``p * q``, shape (..., 4) (broadcast): the rotation q, then p.

    ``p * q = [p_w q_w - p_v . q_v,  p_w q_v + q_w p_v + p_v x q_v]``.
    """
    p = _quaternions(p, 'p')
    q = _quaternions(q, 'q')
    pw, pv = p[..., W], p[..., VEC]
    qw, qv = q[..., W], q[..., VEC]
    w = pw * qw - np.sum(pv * qv, axis=-1)
    v = pw[..., None] * qv + qw[..., None] * pv + np.cross(pv, qv)
    return np.concatenate([w[..., None], v], axis=-1)


def conjugate(q) -> np.ndarray:
    """Conjugate ``[w, -x, -y, -z]``, shape (..., 4); the inverse of a unit quaternion."""
    q = _quaternions(q)
    return np.concatenate([q[..., :1], -q[..., VEC]], axis=-1)


def log_map(q) -> np.ndarray:
    """Rotation vector ``theta u`` of the unit quaternion q, shape (..., 3), theta in [0, pi].

    Ude et al. (2014)'s ``2 log(q)`` taken the shorter way: ``log_map(q) == log_map(-q)``.
    With ``s = |v|`` and the sign of w folded into v, ``theta = 2 atan2(s, |w|)`` and the
    vector is ``(theta / s) v``; atan2 of a small s keeps its relative precision, so there is
    no loss of precision near the identity (at s = 0 exactly, v = 0 and so is the result;
    below about 1e-154 rad the square in |v| underflows and the result is 0).
    """
    q = _quaternions(q)
    sign = np.where(q[..., W] < 0.0, -1.0, 1.0)  # take the shorter way: w >= 0
    w = sign * q[..., W]
    v = sign[..., None] * q[..., VEC]
    s = np.linalg.norm(v, axis=-1)
    factor = 2.0 * np.arctan2(s, w) / np.where(s > 0.0, s, 1.0)
    return factor[..., None] * v


def exp_map(r) -> np.ndarray:
    """Unit quaternion of the rotation vector r (angle |r| about r / |r|), shape (..., 4).

    Ude et al. (2014)'s ``exp(r / 2) = [cos(|r|/2), sin(|r|/2) r / |r|]``, with
    ``sin(|r|/2) / |r| = sinc(|r| / (2 pi)) / 2`` (numpy's normalised sinc), exact at r = 0.
    The inverse of :func:`log_map` for |r| < pi.
    """
    r = _rotation_vectors(r)
    angle = np.linalg.norm(r, axis=-1)
    half_sinc = 0.5 * np.sinc(angle / (2.0 * np.pi))
    return np.concatenate([np.cos(0.5 * angle)[..., None], half_sinc[..., None] * r], axis=-1)


def interpolate(t, q, t_new) -> np.ndarray:
    """Piecewise geodesic (slerp) interpolation of samples q (T, 4) at times t (T,).

    Between samples i and i+1, ``q(t) = exp_map(s log_map(q_{i+1} * conj(q_i))) * q_i`` with
    ``s = (t - t_i) / (t_{i+1} - t_i)``: the shorter great-circle arc, whatever the signs of
    the samples. Times outside [t_0, t_{T-1}] take the end samples.

    Args:
        t: sample times, shape (T,), strictly increasing, T >= 2.
        q: unit quaternions, shape (T, 4).
        t_new: query times, shape (M,).

    Returns:
        unit quaternions, shape (M, 4).

    Raises:
        ValueError: t not (T,) with T >= 2 and strictly increasing, or q not (T, 4).
    """
    t = np.asarray(t, dtype=float)
    q = _quaternions(q)
    if t.ndim != 1 or t.size < 2 or q.shape != (t.size, 4):
        raise ValueError(f'need t (T,) with T >= 2 and q (T, 4); got {t.shape} and {q.shape}')
    if np.any(np.diff(t) <= 0.0):
        raise ValueError('sample times must be strictly increasing')
    t_new = np.atleast_1d(np.asarray(t_new, dtype=float))
    index = np.clip(np.searchsorted(t, t_new, side='right') - 1, 0, len(t) - 2)  # (M,)
    s = np.clip((t_new - t[index]) / (t[index + 1] - t[index]), 0.0, 1.0)  # (M,)
    arc = log_map(product(q[index + 1], conjugate(q[index])))  # (M, 3)
    return product(exp_map(s[:, None] * arc), q[index])


# 4 q q^T (Bar-Itzhack 2000) as an affine function of a rotation matrix's 9 entries r
# (row-major): r @ _QUAT_LINEAR + _QUAT_CONSTANT, flattened to 16 (on the diagonal
# 4 w^2 = 1 + r00 + r11 + r22, ..., off it 4 w x = r21 - r12, ...)
def _quaternion_map() -> tuple[np.ndarray, np.ndarray]:
    rows = {(0, 0): {0: 1, 4: 1, 8: 1}, (1, 1): {0: 1, 4: -1, 8: -1},
            (2, 2): {0: -1, 4: 1, 8: -1}, (3, 3): {0: -1, 4: -1, 8: 1},
            (0, 1): {7: 1, 5: -1}, (0, 2): {2: 1, 6: -1}, (0, 3): {3: 1, 1: -1},
            (1, 2): {1: 1, 3: 1}, (1, 3): {2: 1, 6: 1}, (2, 3): {5: 1, 7: 1}}
    linear, constant = np.zeros((9, 16)), np.zeros(16)
    for (i, j), terms in rows.items():
        for entry, sign in terms.items():
            linear[entry, 4 * i + j] = linear[entry, 4 * j + i] = sign
        if i == j:
            constant[4 * i + i] = 1.0
    return linear, constant


_QUAT_LINEAR, _QUAT_CONSTANT = _quaternion_map()


def quaternion_of(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) [w, x, y, z] of rotation matrices (..., 3, 3): the column of
    4 q q^T (Bar-Itzhack 2000) with the largest diagonal entry, so no division by a small
    component; the sign is that of the largest component (positive)."""
    rot = np.asarray(rot, dtype=float)
    k4 = (rot.reshape(rot.shape[:-2] + (9,)) @ _QUAT_LINEAR + _QUAT_CONSTANT)
    k4 = k4.reshape(rot.shape[:-2] + (4, 4))
    diagonal = np.diagonal(k4, axis1=-2, axis2=-1)
    best = np.argmax(diagonal, axis=-1)[..., None, None]
    column = np.take_along_axis(k4, best, axis=-1)[..., 0]       # 4 q q_best
    return column / np.sqrt(np.sum(column * column, axis=-1, keepdims=True))


def _left_conjugate(q: np.ndarray) -> np.ndarray:
    """M (..., 4, 4) with M p = q (x) conj(p) for quaternions [w, x, y, z]."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    left = np.stack([np.stack([w, -x, -y, -z], -1), np.stack([x, w, -z, y], -1),
                     np.stack([y, z, w, -x], -1), np.stack([z, -y, x, w], -1)], -2)
    return left * np.array([1.0, -1.0, -1.0, -1.0])           # conj(p) = p * (1, -1, -1, -1)


def rotation_vector(q: np.ndarray) -> np.ndarray:
    """log of unit quaternions (..., 4) [w, x, y, z]: the rotation vector (..., 3) [rad] of
    the shortest rotation (angle in [0, pi]; q and -q give the same)."""
    w, v = q[..., 0], q[..., 1:]
    norm = np.sqrt(np.sum(v * v, axis=-1))
    angle = 2.0 * np.arctan2(norm, np.abs(w))
    scale = np.copysign(angle / np.maximum(norm, 1e-300), w)    # 0 / tiny = 0 at norm 0
    return scale[..., None] * v


def orientation_error(quat: np.ndarray, quat_ref: np.ndarray) -> np.ndarray:
    """|log(quat_ref (x) conj(quat))| (...,) [rad]: the angle between orientations (..., 4)."""
    err = (_left_conjugate(np.asarray(quat_ref, dtype=float))
           @ np.asarray(quat, dtype=float)[..., None])[..., 0]
    return np.sqrt(np.sum(rotation_vector(err) ** 2, axis=-1))
