"""Forward kinematics and Jacobians of one site over a chain of hinge and slide joints, for
any number of postures at once, in a few numpy calls.

`SiteChain`: from the world to the site's body
the chain is a product of fixed transforms (``body_pos``, ``body_quat``; the site's
``site_pos``, ``site_quat``) and one transform per arm joint, a rotation by
theta = q - qpos0 about the unit axis a (``jnt_axis``) through the anchor p (``jnt_pos``) of
a hinge, a translation theta a of a slide. In homogeneous form (Rodrigues' formula,
K = [a]_x the cross-product matrix of a)

    H(theta) = I + sin(theta) G + (1 - cos(theta)) G2 + theta S
    G = [K, -K p; 0, 0],  G2 = [K^2, -K^2 p; 0, 0],  S = 0     (hinge)
    G = G2 = 0,           S = [0, a; 0, 0]                     (slide)

so that with the fixed transform F_j before joint j the link F_j H_j(theta) is a linear
combination of constant matrices with the coefficients [1, sin, cos(, theta)], and the
transform of a pair of consecutive joints one of constant products with the products of
their coefficients: the links of all pairs and candidates are one matrix product, the chain
ceil(n / 2) - 1 batched 3 x 4 products. A joint's own motion keeps its axis and (hinge) its
anchor, so the frames before and after each pair give every joint's axis a_w and anchor o_w
in the world, and the site's position x and orientation, in one more product; the position
Jacobian's column is a_w x (x - o_w) for a hinge and a_w for a slide, the rotational one
a_w for a hinge and 0 for a slide (as ``mj_jacSite``; they agree with MuJoCo's to ~1e-15).
A passive hinge or slide on the chain stays at its qpos0 (as in `DifferentialIK`'s own
MjData), where its transform is the identity: it is left out. Ball and free joints on the
chain, and arm joints off it (their column of J would be zero), are refused with an
`IKError`: use `DifferentialIK` for such a model.

Used by `psl_task.inverse_kinematics` (to check interpolated samples along a whole path) and
the tests' `PopulationIK` (src/psl_task/test/test_population_ik.py: the kinematics of a
population's step). Imports no ROS; calls MuJoCo only to build the chain.

References
----------
Bar-Itzhack, I. Y. (2000). New method for extracting the quaternion from a rotation matrix.
Journal of Guidance, Control, and Dynamics, 23(6), 1085-1087.
"""
from __future__ import annotations

import mujoco
import numpy as np

from psl_task.quaternion import quaternion_of


class IKError(ValueError):
    """Input the inverse kinematics or its kinematic chain refuses: wrong shapes, non-finite
    numbers, bad settings, a chain it cannot follow."""


_HINGE, _SLIDE = mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE
_JOINT_TYPES = {int(t): name[len('mjJNT_'):].lower()
                for name, t in mujoco.mjtJoint.__members__.items()}
# the cross product a x d = (a_i d_j) (9,) @ _LEVI_CIVITA: entry (3 i + j, k) = epsilon_ijk
_LEVI_CIVITA = np.zeros((9, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI_CIVITA[3 * _i + _j, _k], _LEVI_CIVITA[3 * _j + _i, _k] = 1.0, -1.0


def _homogeneous(pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """The 4 x 4 transform of a position (3,) and unit quaternion (4,) [w, x, y, z]."""
    out = np.eye(4)
    rot = np.empty(9)
    mujoco.mju_quat2Mat(rot, np.asarray(quat, dtype=float))
    out[:3, :3] = rot.reshape(3, 3)
    out[:3, 3] = pos
    return out


def _skew(a: np.ndarray) -> np.ndarray:
    """[a]_x (3, 3): [a]_x v = a x v."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


class SiteChain:
    """Forward kinematics and Jacobians of one site over n hinge or slide joints, for any
    number of postures at once (module docstring).

    Args:
        model: the model (only read, at construction).
        site: the site's id.
        joints: (n,) joint ids in q order, each a hinge or slide.

    Raises:
        IKError: a ball or free joint on the chain from the world to the site's body, or a
            joint of ``joints`` that is not on that chain.
    """

    def __init__(self, model: mujoco.MjModel, site: int, joints):
        joints = [int(j) for j in joints]
        self.n = len(joints)
        site_name = model.site(site).name or f'#{site}'
        path, body = [], int(model.site_bodyid[site])
        while body != 0:
            path.append(body)
            body = int(model.body_parentid[body])
        index = {joint: i for i, joint in enumerate(joints)}
        fixed = np.eye(4)                 # fixed transform since the last arm joint
        order, frames, axes, anchors, hinge, qpos0 = [], [], [], [], [], []
        for body in reversed(path):
            fixed = fixed @ _homogeneous(model.body_pos[body], model.body_quat[body])
            first = int(model.body_jntadr[body])
            for joint in range(first, first + int(model.body_jntnum[body])):
                kind = int(model.jnt_type[joint])
                if kind not in (_HINGE, _SLIDE):
                    raise IKError(f'the {_JOINT_TYPES[kind]} joint '
                                  f'{model.joint(joint).name or joint!r} lies on the chain '
                                  f'from the world to site {site_name!r}: the population IK '
                                  'handles hinge and slide joints only (use DifferentialIK)')
                if joint not in index:    # passive, held at qpos0: the identity
                    continue
                order.append(index[joint])
                frames.append(fixed)
                fixed = np.eye(4)
                axes.append(model.jnt_axis[joint].copy())
                anchors.append(model.jnt_pos[joint].copy())
                hinge.append(kind == _HINGE)
                qpos0.append(model.qpos0[model.jnt_qposadr[joint]])
        off = [joints[i] for i in range(self.n) if i not in set(order)]
        if off:
            names = [model.joint(j).name or f'#{j}' for j in off]
            raise IKError(f'joints {names} are not on the chain from the world to site '
                          f'{site_name!r}: they do not move it (use DifferentialIK)')
        site_frame = fixed @ _homogeneous(model.site_pos[site], model.site_quat[site])
        # chain order: joint i of the chain is q[order[i]]; q order: column j is chain[rank[j]]
        self.order = np.array(order)
        self.rank = np.argsort(self.order)
        self.hinge = np.array(hinge)
        self.qpos0 = np.array(qpos0)
        self._offset = bool(np.any(self.qpos0 != 0.0))
        self._slides = not bool(np.all(self.hinge))
        # F_j H_j(theta) = (F_j + F_j G2) + sin F_j G - cos F_j G2 + theta F_j S: per joint k
        # constant 4 x 4 matrices, weighed by the coefficients c = [1, sin, cos(, theta)]
        k = 4 if self._slides else 3
        bases = []
        for frame, a, p, is_hinge in zip(frames, axes, anchors, hinge):
            skew = _skew(a) if is_hinge else np.zeros((3, 3))
            g, g2, s = np.zeros((4, 4)), np.zeros((4, 4)), np.zeros((4, 4))
            g[:3, :3], g[:3, 3] = skew, -skew @ p
            g2[:3, :3], g2[:3, 3] = skew @ skew, -(skew @ skew) @ p
            if not is_hinge:
                s[:3, 3] = a
            bases.append(np.stack([frame + frame @ g2, frame @ g, -(frame @ g2), frame @ s][:k]))
        if self.n % 2:       # a last dummy joint: the identity (its coefficient of 1 is 1)
            bases.append(np.stack([np.eye(4)] + [np.zeros((4, 4))] * (k - 1)))
        # the joints go in pairs: the pair's transform sum_ab c_a c'_b (B_a B'_b) is one product
        # of the k^2 coefficient products with a block-diagonal (G k^2, 16 G) matrix for all G
        # pairs at once, and the chain is G - 1 batched products instead of n - 1
        self._pairs = len(bases) // 2
        self._pair_links = np.zeros((self._pairs * k * k, 16 * self._pairs))
        for pair in range(self._pairs):
            first, second = bases[2 * pair], bases[2 * pair + 1]
            block = np.array([(first[i] @ second[j]).reshape(16)
                              for i in range(k) for j in range(k)])
            self._pair_links[pair * k * k:(pair + 1) * k * k, 16 * pair:16 * (pair + 1)] = block
        # the readout of the pair frames S (R, 12 G) by one product with a (12 G, 6 n + 12)
        # matrix plus a constant: per joint its axis and anchor in the world (6 n; the first
        # joint of a pair from the frame before the pair and its fixed transform, F_j [a, 0] and
        # F_j [p, 1], the second from the frame after the pair, [a, 0] and [p, 1]: a joint's
        # own motion keeps its axis and a hinge's anchor), then the site's position (3: S_G f)
        # and rotation matrix (9: R_G R_f, row-major)
        n = self.n
        self._readout = np.zeros((12 * self._pairs, 6 * n + 12))
        self._readout_constant = np.zeros(6 * n + 12)
        for j, (frame, a, p) in enumerate(zip(frames, axes, anchors)):
            axis, anchor = np.append(a, 0.0), np.append(p, 1.0)
            if j % 2 == 0:
                axis, anchor = frame @ axis, frame @ anchor
            before = j // 2 - 1 if j % 2 == 0 else j // 2       # the frame the points are in
            if before < 0:                                      # the world
                self._readout_constant[6 * j:6 * j + 6] = [*axis[:3], *anchor[:3]]
                continue
            for i in range(3):
                row = 12 * before + 4 * i
                self._readout[row:row + 4, 6 * j + i] = axis
                self._readout[row:row + 4, 6 * j + 3 + i] = anchor
        for i in range(3):
            row = 12 * (self._pairs - 1) + 4 * i
            self._readout[row:row + 4, 6 * n + i] = site_frame[:, 3]
            self._readout[row:row + 3, 6 * n + 3 + 3 * i:6 * n + 6 + 3 * i] = site_frame[:3, :3]
        self._rotation_rows = self.hinge.astype(float)[:, None]     # (n, 1): hinges 1, slides 0
        self._slide_rows = np.flatnonzero(~self.hinge)

    # -- batched, chain order (the solver's internal layout) ---------------------------
    def frames(self, q: np.ndarray) -> np.ndarray:
        """S (R, G, 3, 4): the frame after each pair of joints (G = ceil(n / 2)), for
        postures q (R, n) in chain order."""
        rows, n = q.shape
        theta = q - self.qpos0 if self._offset else q
        k = 4 if self._slides else 3
        coefficients = np.ones((rows, 2 * self._pairs, k))      # the dummy's stay 1
        np.sin(theta, out=coefficients[:, :n, 1])
        np.cos(theta, out=coefficients[:, :n, 2])
        if self._slides:
            coefficients[:, :n, 3] = theta
        products = coefficients[:, 0::2, :, None] * coefficients[:, 1::2, None, :]
        links = (products.reshape(rows, -1) @ self._pair_links).reshape(rows, self._pairs, 4, 4)
        frames = np.empty((rows, self._pairs, 3, 4))
        frames[:, 0] = links[:, 0, :3]
        for pair in range(1, self._pairs):
            np.matmul(frames[:, pair - 1], links[:, pair], out=frames[:, pair])
        return frames

    def readout(self, frames: np.ndarray) -> np.ndarray:
        """(R, 6 n + 12) of pair frames (R, G, 3, 4): per joint [a_w, o_w], then the site's
        position (3) and rotation matrix (9)."""
        return frames.reshape(len(frames), -1) @ self._readout + self._readout_constant

    def site(self, readout: np.ndarray) -> np.ndarray:
        """The site positions (R, 3) of a readout."""
        return readout[:, 6 * self.n:6 * self.n + 3]

    def site_quaternion(self, readout: np.ndarray) -> np.ndarray:
        """The site orientations (R, 4) [w, x, y, z] of a readout."""
        return quaternion_of(readout[:, 6 * self.n + 3:].reshape(-1, 3, 3))

    def jacobian(self, readout: np.ndarray, orientation_weight: float | None = None
                 ) -> np.ndarray:
        """The transposed Jacobian jt (R, n, m) of a readout: row i the column of chain joint
        i, a_w x (x - o_w) of a hinge, a_w of a slide; m = 3, or 6 with the rotational part
        (a_w of a hinge, 0 of a slide) times orientation_weight."""
        rows, n = len(readout), self.n
        points = readout[:, :6 * n].reshape(rows, n, 2, 3)         # axis, anchor
        arm = self.site(readout)[:, None, :] - points[:, :, 1]     # (R, n, 3) anchor -> site
        outer = points[:, :, 0, :, None] * arm[:, :, None, :]      # (R, n, 3, 3) a_i arm_j
        jt = (outer.reshape(rows * n, 9) @ _LEVI_CIVITA).reshape(rows, n, 3)   # a x arm
        if self._slides:
            jt[:, self._slide_rows] = points[:, self._slide_rows, 0]
        if orientation_weight is None:
            return jt
        return np.concatenate([jt, points[:, :, 0] * (orientation_weight * self._rotation_rows)],
                              axis=2)

    def evaluate(self, q: np.ndarray, orientation_weight: float | None = None):
        """For postures q (R, n) in chain order: the site positions x (R, 3), the transposed
        Jacobian jt (R, n, m) (`jacobian`) and the site's quaternions (R, 4) (None without
        orientation_weight)."""
        readout = self.readout(self.frames(q))
        quat = None if orientation_weight is None else self.site_quaternion(readout)
        return self.site(readout), self.jacobian(readout, orientation_weight), quat

    # -- public, q order -----------------------------------------------------------------
    def _chain_order(self, q) -> tuple[np.ndarray, tuple]:
        q = np.asarray(q, dtype=float)
        if q.ndim < 1 or q.shape[-1] != self.n:
            raise IKError(f'q must have shape (..., {self.n}), got {q.shape}')
        return q.reshape(-1, self.n)[:, self.order], q.shape[:-1]

    def forward(self, q) -> np.ndarray:
        """Site positions (..., 3) [m] at joint angles q (..., n)."""
        q, shape = self._chain_order(q)
        return self.site(self.readout(self.frames(q))).reshape(shape + (3,))

    def pose(self, q) -> tuple[np.ndarray, np.ndarray]:
        """Site positions (..., 3) [m] and orientations (..., 4) (unit quaternions
        [w, x, y, z], the largest component positive) at joint angles q (..., n)."""
        q, shape = self._chain_order(q)
        readout = self.readout(self.frames(q))
        return (self.site(readout).reshape(shape + (3,)),
                self.site_quaternion(readout).reshape(shape + (4,)))

    def jacobians(self, q) -> tuple[np.ndarray, np.ndarray]:
        """The site's position and rotational Jacobians (..., 3, n) at joint angles
        q (..., n), columns in q order (``mj_jacSite``'s jacp, jacr of the joints' dofs)."""
        q, shape = self._chain_order(q)
        readout = self.readout(self.frames(q))
        jac = self.jacobian(readout, 1.0)[:, self.rank].swapaxes(1, 2)
        return jac[:, :3].reshape(shape + (3, self.n)), jac[:, 3:].reshape(shape + (3, self.n))


