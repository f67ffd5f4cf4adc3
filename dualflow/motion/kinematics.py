"""Forward and inverse kinematics of the SMPL-22 skeleton (numpy, vectorised over frames).

Rotation convention (the one SMPL uses): every joint ``j`` has a *global*
rotation ``G_j`` (3, 3) that maps rest-pose vectors to posed world vectors, and a
*local* rotation ``L_j = G_parent(j)^T G_j`` relative to its parent. For the
root, ``L_0 = G_0`` is its global orientation. A bone offset ``o_j`` is the
rest-pose vector from ``parent(j)`` to ``j``, and forward kinematics is

    G_0 = L_0,                     p_0 = root_pos
    G_j = G_parent(j) L_j,         p_j = p_parent(j) + G_parent(j) o_j

i.e. a joint's rotation moves the bones leaving it (its children), not itself.

The functions are frame-agnostic: positions, offsets and the rest pose only have
to be expressed in the same frame. The defaults come from
:data:`dualflow.motion.skeleton.REST_POSE` (Z-up, facing +X); to work in another
frame (e.g. the Y-up feature frame) pass the rest pose expressed in that frame.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from dualflow.errors import DualFlowError
from dualflow.motion.rotations import align_vector_sets, swing_between_units
from dualflow.motion.skeleton import N_JOINTS, PARENTS, REST_POSE

_PARENTS = np.asarray(PARENTS)

#: Children of each joint, SMPL order.
CHILDREN: tuple[tuple[int, ...], ...] = tuple(
    tuple(c for c in range(N_JOINTS) if PARENTS[c] == j) for j in range(N_JOINTS)
)
#: Joints without children (feet, head, wrists): positions do not determine
#: their rotation, so inverse kinematics gives them the identity local rotation.
LEAF_JOINTS: tuple[int, ...] = tuple(j for j in range(N_JOINTS) if not CHILDREN[j])
#: A posed bone shorter than this (m) has no direction: its joint keeps the identity rotation.
_MIN_BONE = 1e-9
_I3 = np.eye(3)
_I3.flags.writeable = False


@dataclass(frozen=True)
class _Level:
    """The joints at one depth of the tree, split for :func:`inverse_kinematics`."""

    joints: np.ndarray  #: every joint at this depth
    parents: np.ndarray  #: their parents
    multi: tuple[int, ...]  #: joints with several children (Kabsch)
    single: np.ndarray  #: joints with exactly one child (swing)
    single_parents: np.ndarray
    single_kids: np.ndarray  #: the child of each ``single`` joint


def _levels() -> tuple[_Level, ...]:
    depth = [0] * N_JOINTS
    for j in range(1, N_JOINTS):
        depth[j] = depth[PARENTS[j]] + 1
    out = []
    for d in range(max(depth) + 1):
        joints = [j for j in range(N_JOINTS) if depth[j] == d]
        single = [j for j in joints if len(CHILDREN[j]) == 1]
        out.append(
            _Level(
                joints=np.array(joints),
                parents=_PARENTS[joints],
                multi=tuple(j for j in joints if len(CHILDREN[j]) > 1),
                single=np.array(single, dtype=int),
                single_parents=_PARENTS[single].astype(int),
                single_kids=np.array([CHILDREN[j][0] for j in single], dtype=int),
            )
        )
    return tuple(out)


_LEVELS = _levels()


@dataclass(frozen=True)
class _RestDirections:
    """Unit rest-pose child directions of one rest pose, per :data:`_LEVELS` entry."""

    single: tuple[np.ndarray, ...]  #: (k, 3) for each level's single-child joints
    multi: dict  #: joint -> (children, 3) for the multi-child joints


@functools.lru_cache(maxsize=8)
def _rest_directions(rest_bytes: bytes) -> _RestDirections:
    off = rest_offsets(np.frombuffer(rest_bytes).reshape(N_JOINTS, 3))

    def unit(v):
        u = v / np.linalg.norm(v, axis=-1, keepdims=True)
        u.flags.writeable = False  # shared by every later call with this rest pose
        return u

    return _RestDirections(
        single=tuple(unit(off[lv.single_kids]) for lv in _LEVELS),
        multi={j: unit(off[list(CHILDREN[j])]) for lv in _LEVELS for j in lv.multi},
    )


def _check_rest(rest, what: str = "rest pose") -> np.ndarray:
    rest = np.asarray(rest, dtype=np.float64)
    if rest.shape != (N_JOINTS, 3) or not np.isfinite(rest).all():
        raise DualFlowError(f"{what}: must be finite with shape ({N_JOINTS}, 3), got {tuple(rest.shape)}")
    return rest


def rest_offsets(rest=REST_POSE) -> np.ndarray:
    """Bone offsets (22, 3) in metres: ``o_j = rest_j - rest_parent(j)``; ``o_0 = 0``."""
    rest = _check_rest(rest)
    off = rest - rest[np.maximum(_PARENTS, 0)]
    off[0] = 0.0
    return off


def scaled_offsets(lengths, rest=REST_POSE) -> np.ndarray:
    """Rest-pose bone directions scaled to other bone lengths.

    lengths: (..., 21) metres, entry ``j-1`` for the bone ending at joint ``j``
    (the layout of :func:`dualflow.motion.skeleton.bone_lengths`). Returns
    (..., 22, 3) offsets with ``o_0 = 0``: the rest pose of a person with these
    proportions, for :func:`forward_kinematics`.
    """
    lengths = np.asarray(lengths, dtype=np.float64)
    if lengths.ndim < 1 or lengths.shape[-1] != N_JOINTS - 1:
        raise DualFlowError(f"bone lengths: expected shape (..., {N_JOINTS - 1}), got {tuple(lengths.shape)}")
    off = rest_offsets(rest)
    dirs = off[1:] / np.linalg.norm(off[1:], axis=-1, keepdims=True)
    out = np.zeros(lengths.shape[:-1] + (N_JOINTS, 3))
    out[..., 1:, :] = dirs * lengths[..., None]
    return out


def global_rotations(local_rot) -> np.ndarray:
    """Local rotations (T, 22, 3, 3) -> global rotations (T, 22, 3, 3): ``G_j = G_parent L_j``."""
    local_rot = np.asarray(local_rot, dtype=np.float64)
    if local_rot.ndim != 4 or local_rot.shape[1:] != (N_JOINTS, 3, 3):
        raise DualFlowError(f"local_rot: expected shape (T, {N_JOINTS}, 3, 3), got {tuple(local_rot.shape)}")
    G = np.empty_like(local_rot)
    G[:, 0] = local_rot[:, 0]
    for j in range(1, N_JOINTS):
        G[:, j] = G[:, PARENTS[j]] @ local_rot[:, j]
    return G


def fit_offsets(positions, local_rot) -> np.ndarray:
    """Bone offsets (22, 3) for which FK of ``local_rot`` best reproduces ``positions``.

    positions (T, 22, 3), local_rot (T, 22, 3, 3) (``[:, 0]`` the root's global
    orientation), one frame. With the global rotations ``G`` of ``local_rot``
    fixed, each bone is fitted on its own by least squares,

        o_j = argmin_o sum_t |G_parent(j)[t] o - (p_j[t] - p_parent(j)[t])|^2
            = mean_t G_parent(j)[t]^T (p_j[t] - p_parent(j)[t]),

    i.e. the person's own rest skeleton (proportions *and* pelvis / chest shape)
    in the rest pose's frame. ``o_0 = 0``. For a rigid skeleton whose rotations
    came from :func:`inverse_kinematics`, FK with these offsets is exact.
    """
    positions = _check_positions(positions)
    G = global_rotations(local_rot)
    if G.shape[0] != positions.shape[0]:
        raise DualFlowError(
            f"local_rot: {G.shape[0]} frames but positions has {positions.shape[0]}; give one rotation set per frame"
        )
    bones = positions[:, 1:] - positions[:, _PARENTS[1:]]  # (T, 21, 3)
    local_bones = np.einsum("tjba,tjb->tja", G[:, _PARENTS[1:]], bones)
    off = np.zeros((N_JOINTS, 3))
    off[1:] = local_bones.mean(axis=0)
    return off


def forward_kinematics(root_pos, local_rot, offsets=None) -> np.ndarray:
    """Joint positions from a root trajectory and local joint rotations.

    root_pos: (T, 3) metres, position of the pelvis.
    local_rot: (T, 22, 3, 3) rotation matrices; ``[:, 0]`` is the pelvis's global
        orientation, ``[:, j]`` the rotation of joint j relative to its parent.
        Identity everywhere gives the rest pose.
    offsets: bone offsets (22, 3) or per frame (T, 22, 3) in metres (``o_j`` from
        the parent to joint j in the rest pose; ``o_0`` is ignored). Default:
        :func:`rest_offsets` of ``REST_POSE``, i.e. Z-up, rest pose facing +X.
    Returns (T, 22, 3) positions in metres, in the frame of ``root_pos``.
    """
    root_pos = np.asarray(root_pos, dtype=np.float64)
    local_rot = np.asarray(local_rot, dtype=np.float64)
    if root_pos.ndim != 2 or root_pos.shape[1] != 3:
        raise DualFlowError(f"root_pos: expected shape (T, 3), got {tuple(root_pos.shape)}")
    T = root_pos.shape[0]
    if local_rot.shape != (T, N_JOINTS, 3, 3):
        raise DualFlowError(
            f"local_rot: expected shape ({T}, {N_JOINTS}, 3, 3) to match root_pos, got {tuple(local_rot.shape)}"
        )
    off = rest_offsets() if offsets is None else np.asarray(offsets, dtype=np.float64)
    if off.shape not in ((N_JOINTS, 3), (T, N_JOINTS, 3)):
        raise DualFlowError(f"offsets: expected shape ({N_JOINTS}, 3) or ({T}, {N_JOINTS}, 3), got {tuple(off.shape)}")
    off = np.broadcast_to(off, (T, N_JOINTS, 3))
    G = global_rotations(local_rot)
    pos = np.empty((T, N_JOINTS, 3))
    pos[:, 0] = root_pos
    for j in range(1, N_JOINTS):
        p = PARENTS[j]
        pos[:, j] = pos[:, p] + np.einsum("tab,tb->ta", G[:, p], off[:, j])
    return pos


def inverse_kinematics(positions, rest=REST_POSE) -> tuple[np.ndarray, np.ndarray]:
    """Local joint rotations that pose ``rest`` like ``positions`` (one IK step, no iteration).

    positions: (T, 22, 3) metres; rest: (22, 3), same frame. Returns
    ``(root_pos (T, 3), local_rot (T, 22, 3, 3))`` for :func:`forward_kinematics`.

    Walking the tree from the root, each joint's global rotation ``G_j`` is chosen
    so that its rest-pose child bones point like the posed ones:

    * several children (pelvis: hips + spine1; spine3: neck + collars): the
      least-squares rotation (Kabsch, :func:`align_vector_sets`) taking the rest
      child directions, scaled to the posed bone lengths, onto the posed child
      offsets. The spread of the children fixes the twist; for a rigid,
      rest-shaped pelvis/chest it is exact.
    * one child: ``L_j`` is the *swing-only* rotation (:func:`~dualflow.motion.rotations.swing_rotation`)
      taking the rest bone direction onto the posed bone direction expressed in
      the parent's frame, ``G_parent^T (p_child - p_j)``. The twist about the
      bone is therefore zero relative to the parent (positions carry no twist).
    * no children (feet, head, wrists, see :data:`LEAF_JOINTS`): identity.

    Consequence: FK of the result with offsets of the posed bone lengths lands
    every single-child joint's child exactly on its posed direction; residual
    error comes only from a pelvis/chest whose triangle shape differs from the
    rest pose's, and it is passed down the chain as a translation, not amplified.
    """
    positions = _check_positions(positions)
    dirs = _rest_directions(_check_rest(rest).tobytes())
    T = positions.shape[0]
    local = np.empty((T, N_JOINTS, 3, 3))
    local[:] = _I3
    G = local.copy()
    # one tree depth at a time (a joint's rotation needs only its ancestors'): the
    # single-child joints of a depth in one batched swing, the two multi-child joints
    # (pelvis, spine3) on their own; the same equations as joint by joint
    for level, rest_dirs in zip(_LEVELS, dirs.single):
        for j in level.multi:
            local[:, j] = _joint_rotation(positions, j, G[:, PARENTS[j]] if j else _I3, dirs.multi[j])
        if level.single.size:
            posed = positions[:, level.single_kids] - positions[:, level.single]  # (T, k, 3)
            # G_parent^T posed, as the row vector posed^T G_parent
            posed_in_parent = (posed[..., None, :] @ G[:, level.single_parents])[..., 0, :]
            length = np.sqrt(np.einsum("tki,tki->tk", posed_in_parent, posed_in_parent))[..., None]
            posed_dirs = posed_in_parent / np.maximum(length, _MIN_BONE)
            if (length < _MIN_BONE).any():  # a zero-length bone keeps the identity, as swing_rotation does
                posed_dirs = np.where(length < _MIN_BONE, rest_dirs, posed_dirs)
            local[:, level.single] = swing_between_units(rest_dirs, posed_dirs)
        if level.joints[0] == 0:
            G[:, 0] = local[:, 0]
        else:
            G[:, level.joints] = G[:, level.parents] @ local[:, level.joints]
    return positions[:, 0].copy(), local


def _check_positions(positions) -> np.ndarray:
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[1:] != (N_JOINTS, 3):
        raise DualFlowError(f"positions: expected shape (T, {N_JOINTS}, 3), got {tuple(positions.shape)}")
    if not np.isfinite(positions).all():
        raise DualFlowError("positions: contain NaN or inf; clean or drop those frames before inverse kinematics")
    return positions


def _joint_rotation(positions: np.ndarray, j: int, parent_G: np.ndarray, rest_dirs: np.ndarray) -> np.ndarray:
    """Local rotation (T, 3, 3) of joint j with several children (pelvis, spine3) given its
    parent's global rotation and its children's unit rest directions (children, 3);
    single-child joints take the batched swing in :func:`inverse_kinematics`."""
    posed = positions[:, list(CHILDREN[j])] - positions[:, j : j + 1]  # (T, k, 3) world
    posed_in_parent = posed @ parent_G  # rows d^T G_parent, i.e. G_parent^T d
    lengths = np.sqrt(np.einsum("tki,tki->tk", posed_in_parent, posed_in_parent))[..., None]  # (T, k, 1)
    return align_vector_sets(rest_dirs[None] * lengths, posed_in_parent)


def root_orientation(positions, rest=REST_POSE) -> np.ndarray:
    """Global pelvis rotation (T, 3, 3) from the pelvis and its children (hips, spine1).

    The same least-squares step :func:`inverse_kinematics` uses for the root;
    positions (T, 22, 3) and rest (22, 3) in one frame.
    """
    positions = _check_positions(positions)
    T = positions.shape[0]
    return _joint_rotation(
        positions, 0, np.broadcast_to(np.eye(3), (T, 3, 3)), _rest_directions(_check_rest(rest).tobytes()).multi[0]
    )
