"""PD + feed-forward joint torque law with torque limits (DESIGN.md section 4). Pure numpy; no ROS.

``u = Kp (q_ref - q) + Kd (qd_ref - qd) + u_ffwd``, clipped elementwise to ``[-u_limit, u_limit]``.
"""

import numpy as np


def _joint_array(value, n_joints: int, name: str) -> np.ndarray:
    """Scalar or (n_joints,) array -> finite (n_joints,) array."""
    array = np.asarray(value, dtype=float)
    if array.ndim == 0:
        array = np.full(n_joints, float(array))
    if array.shape != (n_joints,):
        raise ValueError(f'{name} must be a scalar or have shape ({n_joints},), got {array.shape}')
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{name} must be finite, got {array}')
    return array


def pd_feedforward(q, qd, q_ref, qd_ref, u_ffwd, kp, kd, u_limit) -> np.ndarray:
    """Joint torques of the PD + feed-forward law, clipped to the torque limits.

    Args:
        q, qd: measured joint positions and velocities, shape (n,).
        q_ref, qd_ref: reference positions and velocities, shape (n,).
        u_ffwd: feed-forward torques, shape (n,).
        kp, kd: proportional and derivative gains (>= 0), scalars or shape (n,).
        u_limit: torque limits (>= 0), scalar or shape (n,).

    Returns:
        u: torques, shape (n,), each in [-u_limit, u_limit].

    Raises:
        ValueError: mismatched shapes, non-finite inputs, negative gains or torque limits.
    """
    q = np.atleast_1d(np.asarray(q, dtype=float))
    if q.ndim != 1:
        raise ValueError(f'q must have shape (n,), got {q.shape}')
    n_joints = q.shape[0]
    q = _joint_array(q, n_joints, 'q')
    qd = _joint_array(np.atleast_1d(qd), n_joints, 'qd')
    q_ref = _joint_array(np.atleast_1d(q_ref), n_joints, 'q_ref')
    qd_ref = _joint_array(np.atleast_1d(qd_ref), n_joints, 'qd_ref')
    u_ffwd = _joint_array(np.atleast_1d(u_ffwd), n_joints, 'u_ffwd')
    kp = _joint_array(kp, n_joints, 'kp')
    kd = _joint_array(kd, n_joints, 'kd')
    u_limit = _joint_array(u_limit, n_joints, 'u_limit')
    for name, value in (('kp', kp), ('kd', kd), ('u_limit', u_limit)):
        if np.any(value < 0.0):
            raise ValueError(f'{name} must be >= 0, got {value}')
    u = kp * (q_ref - q) + kd * (qd_ref - qd) + u_ffwd
    return np.clip(u, -u_limit, u_limit)
