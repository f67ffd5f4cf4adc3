"""Rotation utilities for the human-motion contract (numpy + scipy, batched).

Contract: arrays with any leading batch dimensions, float64. Matrices act on column vectors;
quaternions are w-x-y-z (scipy's x-y-z-w is converted here); the 6D form is the first two
*columns* of R, column after column, recovered by Gram-Schmidt (PyTorch3D stores rows: convert
through the transpose). scipy does the standard conversions; this module adds batched 6D,
swing rotations between directions and least-squares alignment of vector sets.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dualflow.errors import DualFlowError

#: Norm below which a direction is treated as undefined (metres or unitless).
_EPS = 1e-9
_I3 = np.eye(3)
_I3.flags.writeable = False


def _as_array(x, last: tuple[int, ...], what: str) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim < len(last) or arr.shape[arr.ndim - len(last) :] != last:
        shape = ", ".join(["..."] + [str(n) for n in last])
        raise DualFlowError(f"{what}: expected shape ({shape}), got {tuple(arr.shape)}")
    return arr


def _scipy(fn, arr: np.ndarray, n_tail: int) -> np.ndarray:
    """Apply a scipy Rotation conversion to an array with leading batch dims."""
    batch = arr.shape[: arr.ndim - n_tail]
    flat = arr.reshape((-1,) + arr.shape[arr.ndim - n_tail :])
    out = fn(flat)
    return out.reshape(batch + out.shape[1:])


# -- 6D ----------------------------------------------------------------------
def matrix_to_6d(R) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 6): first column, then second column."""
    R = _as_array(R, (3, 3), "rotation matrix")
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def sixd_to_matrix(d6) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt (see module docstring).

    Any pair of non-parallel 3-vectors maps to a proper rotation; a zero or
    parallel pair has no defined rotation and raises DualFlowError.
    """
    d6 = _as_array(d6, (6,), "rotation 6D")
    a1, a2 = d6[..., 0:3], d6[..., 3:6]
    n1 = np.linalg.norm(a1, axis=-1, keepdims=True)
    b1 = a1 / np.maximum(n1, _EPS)
    u2 = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    n2 = np.linalg.norm(u2, axis=-1, keepdims=True)
    bad = (n1[..., 0] < _EPS) | (n2[..., 0] < _EPS) | ~np.isfinite(d6).all(axis=-1)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise DualFlowError(
            f"rotation 6D: entry {where} has a zero or parallel column pair (or NaN), "
            "so it defines no rotation; check the generator output or the file"
        )
    b2 = u2 / n2
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-1)


# -- scipy-backed conversions -----------------------------------------------
def quat_wxyz_to_matrix(q) -> np.ndarray:
    """(..., 4) unit quaternions wxyz -> (..., 3, 3). Non-unit input is normalised."""
    q = _as_array(q, (4,), "quaternion")
    return _scipy(lambda f: Rotation.from_quat(f[:, [1, 2, 3, 0]]).as_matrix(), q, 1)


def matrix_to_quat_wxyz(R) -> np.ndarray:
    """(..., 3, 3) -> (..., 4) wxyz with w >= 0 (canonical sign)."""
    R = _as_array(R, (3, 3), "rotation matrix")
    q = _scipy(lambda f: Rotation.from_matrix(f).as_quat()[:, [3, 0, 1, 2]], R, 2)
    return np.where(q[..., :1] < 0, -q, q)


def rotvec_to_matrix(rv) -> np.ndarray:
    """(..., 3) rotation vectors (axis * angle, rad) -> (..., 3, 3)."""
    rv = _as_array(rv, (3,), "rotation vector")
    return _scipy(lambda f: Rotation.from_rotvec(f).as_matrix(), rv, 1)


def matrix_to_rotvec(R) -> np.ndarray:
    """(..., 3, 3) -> (..., 3) rotation vectors, angle in [0, pi]."""
    R = _as_array(R, (3, 3), "rotation matrix")
    return _scipy(lambda f: Rotation.from_matrix(f).as_rotvec(), R, 2)


def euler_to_matrix(angles, order: str) -> np.ndarray:
    """(..., 3) Euler angles in radians -> (..., 3, 3).

    ``order`` follows scipy: upper case (e.g. ``"ZXY"``) is intrinsic, lower case
    extrinsic. BVH channel orders are intrinsic in the order the channels appear.
    """
    angles = _as_array(angles, (3,), "euler angles")
    return _scipy(lambda f: Rotation.from_euler(order, f).as_matrix(), angles, 1)


def axis_angle_matrix(axis, angle) -> np.ndarray:
    """Rotation by ``angle`` (...,) rad about the fixed unit ``axis`` (3,) -> (..., 3, 3)."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    angle = np.asarray(angle, dtype=np.float64)
    return rotvec_to_matrix(angle[..., None] * axis)


# -- constructions used by inverse kinematics --------------------------------
def _unit(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, _EPS), n[..., 0]


def any_perpendicular(v) -> np.ndarray:
    """(..., 3) -> (..., 3) a unit vector perpendicular to ``v`` (deterministic)."""
    v = _as_array(v, (3,), "vector")
    u, _ = _unit(v)
    # Cross with the world axis least aligned with v: never degenerate.
    axes = np.eye(3)[np.argmin(np.abs(u), axis=-1)]
    p, _ = _unit(np.cross(u, axes))
    return p


def swing_rotation(a, b) -> np.ndarray:
    """The minimal rotation taking direction ``a`` onto direction ``b``.

    a, b: (..., 3), any non-zero length (only directions matter), broadcast against each
    other. Returns (..., 3, 3) ``R`` with ``R @ a/|a| = b/|b|`` and no twist about ``a``
    (it turns about ``a x b``). A zero vector gives the identity; for opposite directions the
    axis is :func:`any_perpendicular` of ``a``.
    """
    a = _as_array(a, (3,), "swing source direction")
    b = _as_array(b, (3,), "swing target direction")
    ua, na = _unit(a)
    ub, nb = _unit(b)
    R = swing_between_units(ua, ub)
    zero = (na < _EPS) | (nb < _EPS)
    if zero.any():
        R = np.where(np.broadcast_to(zero, R.shape[:-2])[..., None, None], np.eye(3), R)
    return R


def swing_between_units(ua: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """:func:`swing_rotation` of unit vectors ``ua``, ``ub`` (..., 3), broadcast, unchecked.

    With ``c = a . b`` and ``v = a x b``, Rodrigues' formula ``R = c I + [v]x + v v^T / (1 + c)``
    needs no angle; writing ``[v]x = b a^T - a b^T`` and
    ``v v^T = (1 - c^2) I - a a^T - b b^T + c (a b^T + b a^T)`` makes it a few outer products:

        R = I + b a^T - a b^T + (c (a b^T + b a^T) - a a^T - b b^T) / (1 + c)

    (the inverse kinematics calls this per tree depth for every frame, where array calls,
    not arithmetic, are the cost). Within ~2.6 degrees of opposite (``1 + c < 1e-3``) the
    division loses digits, and those rows take the angle form instead.
    """
    c = np.einsum("...i,...i->...", ua, ub)
    ab = ua[..., :, None] * ub[..., None, :]
    ba = np.swapaxes(ab, -1, -2)
    near = (c + 1.0) < 1e-3
    quad = c[..., None, None] * (ab + ba) - ua[..., :, None] * ua[..., None, :] - ub[..., :, None] * ub[..., None, :]
    R = _I3 + ba - ab + quad / np.where(near, 1.0, 1.0 + c)[..., None, None]
    if near.any():
        ua, ub = np.broadcast_arrays(ua, ub)
        R[near] = _swing_by_angle(ua[near], ub[near])
    return R


def _swing_by_angle(ua: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Unit (n, 3) -> (n, 3, 3) by the axis-angle form of Rodrigues' formula: axis
    ``u = a x b / |a x b|`` (:func:`any_perpendicular` of ``a`` when the directions are
    opposite), angle ``atan2(|a x b|, a . b)``; exact also next to opposite directions."""
    cross = np.cross(ua, ub)
    sin = np.linalg.norm(cross, axis=-1)
    cos = np.einsum("...i,...i->...", ua, ub)
    axis = cross / np.maximum(sin, 1e-300)[..., None]
    flip = (sin <= 1e-12) & (cos < 0.0)
    if flip.any():
        axis = np.where(flip[..., None], any_perpendicular(ua), axis)
    angle = np.arctan2(sin, cos)
    return rotvec_to_matrix(axis * angle[..., None])


def align_vector_sets(src, dst, weights=None) -> np.ndarray:
    """Least-squares rotation taking vector set ``src`` onto ``dst`` (Kabsch / Wahba).

    src, dst: (..., N, 3); weights (N,) or None. Returns (..., 3, 3) ``R``
    minimising ``sum_i w_i |R src_i - dst_i|^2`` over proper rotations:

        H = sum_i w_i dst_i src_i^T = U S V^T,
        R = U diag(1, 1, det(U V^T)) V^T.

    Two or more non-parallel vectors determine ``R`` uniquely; with collinear
    vectors the twist about their common line is whatever the SVD returns.
    """
    src = _as_array(src, (3,), "alignment source vectors")
    dst = _as_array(dst, (3,), "alignment target vectors")
    if src.ndim < 2 or dst.ndim < 2 or src.shape[-2] != dst.shape[-2]:
        raise DualFlowError(
            f"alignment: source and target need the same number of vectors, got "
            f"{tuple(src.shape)} and {tuple(dst.shape)}"
        )
    w = np.ones(src.shape[-2]) if weights is None else np.asarray(weights, dtype=np.float64)
    H = np.einsum("n,...ni,...nj->...ij", w, dst, src)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    D = np.broadcast_to(np.eye(3), d.shape + (3, 3)).copy()
    D[..., 2, 2] = d
    return U @ D @ Vt


def is_rotation_matrix(R, atol: float = 1e-6) -> np.ndarray:
    """(..., 3, 3) -> (...,) bool: orthonormal with determinant +1 within ``atol``."""
    R = _as_array(R, (3, 3), "rotation matrix")
    orth = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(axis=(-1, -2)) <= atol
    return orth & (np.abs(np.linalg.det(R) - 1.0) <= atol)
