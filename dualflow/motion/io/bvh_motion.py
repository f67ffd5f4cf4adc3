"""BVH <-> :class:`~dualflow.motion.Motion`: joint maps, units, axes, and an SMPL-22 BVH writer.

Contract: :func:`bvh_to_motion` picks the SMPL-22 joints with a joint map
(:mod:`.joint_maps`), converts units and axes (detected or given) and never moves the data, so
two files of one capture stay in one world frame. :func:`motion_to_bvh` writes an SMPL-22
skeleton in metres, Y up, ``Zrotation Yrotation Xrotation`` channels, rotations from bone
alignment and median bone lengths; ``translations="all"`` makes the round trip exact.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from dualflow.errors import DualFlowError
from dualflow.motion.container import Motion
from dualflow.motion.io.bvh import BvhClip, BvhJoint, read_bvh, write_bvh
from dualflow.motion.io.joint_maps import JointMap, resolve_joint_map, strip_namespace
from dualflow.motion.io.units import (
    HEIGHT_RANGE,
    Y_UP,
    axes_from_rest,
    axes_matrix,
    check_height,
    check_positions,
    detect_scale,
    estimate_height,
)
from dualflow.motion.rotations import align_vector_sets, swing_rotation
from dualflow.motion.skeleton import JOINT_NAMES, N_JOINTS, PARENTS, REST_POSE


@dataclass(frozen=True)
class BvhImportOptions:
    """How to turn a BVH file into SMPL-22 motion.

    scale: metres per file unit, or None to detect it from the person's height.
    up: 'auto' (from the rest pose), 'y' (Y up, facing +Z) or 'z' (Z up, facing +X).
    joint_map: None (detect), a built-in name ('cmu', 'mixamo', 'mixamo_spine3',
        'smpl'), a .yaml/.json path, a mapping, or a JointMap.
    drop_first: 'auto' drops a reference first frame (see :func:`is_reference_frame`),
        True always drops frame 0, False keeps it.
    height_range: allowed standing height in metres, None to skip the check.
    axes: an explicit file->world rotation (3, 3) overriding ``up`` (used to give two
        files of one capture the same frame).
    """

    scale: float | None = None
    up: str = "auto"
    joint_map: object = None
    drop_first: object = "auto"
    height_range: tuple[float, float] | None = HEIGHT_RANGE
    axes: np.ndarray | None = None


@dataclass(frozen=True)
class BvhImport:
    """The result of an import and the decisions taken on the way."""

    motion: Motion
    scale: float
    axes: np.ndarray
    joint_map: str
    dropped_first_frame: bool
    height: float
    notes: list[str] = field(default_factory=list)


def is_reference_frame(positions: np.ndarray, min_jump: float = 0.05, factor: float = 5.0) -> bool:
    """Whether frame 0 of (T, J, 3) positions in metres is a reference pose rather than capture.

    Reference poses (a T-pose, CMU's all-zero pose) jump to the first captured
    frame: the largest joint displacement from frame 0 to 1 exceeds ``min_jump`` m
    and ``factor`` times the 99th percentile of the per-frame largest
    displacements over the rest of the clip. Needs at least 3 frames.
    """
    if positions.shape[0] < 3:
        return False
    step = np.linalg.norm(np.diff(positions, axis=0), axis=-1).max(axis=-1)  # (T-1,)
    typical = float(np.percentile(step[1:], 99))
    return bool(step[0] > min_jump and step[0] > factor * typical)


def _rest_axes(clip: BvhClip, names, jm: JointMap) -> np.ndarray:
    rest = jm.apply(clip.rest_positions()[None], names, clip.source)[0]
    up = rest[JOINT_NAMES.index("head")] - rest[0]
    left = rest[JOINT_NAMES.index("left_hip")] - rest[JOINT_NAMES.index("right_hip")]
    return axes_from_rest(up, left, clip.source)


def bvh_to_motion(clip: BvhClip, options: BvhImportOptions = BvhImportOptions(), fps: float | None = None) -> BvhImport:
    """SMPL-22 motion (metres, Z up) from a parsed BVH clip; see the module docstring."""
    source = clip.source
    names = [strip_namespace(n) for n in clip.names]
    if len(set(names)) != len(names):
        names = list(clip.names)
    jm = resolve_joint_map(names, options.joint_map, source)
    file_pos = jm.apply(clip.global_positions(), names, source)  # (T, 22, 3) file units

    if options.axes is not None:
        axes = np.asarray(options.axes, dtype=np.float64)
    elif str(options.up).lower() == "auto":
        axes = _rest_axes(clip, names, jm)
    else:
        axes = axes_matrix(options.up)

    size = estimate_height(file_pos)
    if options.scale is None:
        scale = detect_scale(size, source)
    else:
        scale = float(options.scale)
        if not np.isfinite(scale) or scale <= 0:
            raise DualFlowError(
                f"{source}: --scale must be a positive number of metres per unit, got {options.scale!r}"
            )
    height = size * scale
    check_height(height, scale, source, options.height_range)

    pos = scale * np.einsum("ab,tjb->tja", axes, file_pos)
    notes = []
    if options.drop_first == "auto":
        drop = is_reference_frame(pos)
    elif isinstance(options.drop_first, bool):
        drop = options.drop_first
    else:
        raise DualFlowError(f"drop_first must be 'auto', True or False, got {options.drop_first!r}")
    if drop:
        if pos.shape[0] < 2:
            raise DualFlowError(
                f"{source}: cannot drop the first frame of a one-frame file; keep it (--keep-first-frame)"
            )
        pos = pos[1:]
        notes.append("dropped the first frame (a reference pose, not capture)")
    check_positions(pos, source)
    up = pos[:, JOINT_NAMES.index("head"), 2] - pos[:, 0, 2]
    if np.median(up) < 0:
        raise DualFlowError(
            f"{source}: after axis conversion the head is below the pelvis in most frames; "
            "the up axis is wrong, pass --up y or --up z"
        )
    motion = Motion(pos, fps=clip.fps, name=os.path.basename(source))
    if fps is not None:
        motion = motion.resample(fps)
    return BvhImport(motion, scale, axes, jm.name, drop, height, notes)


def read_bvh_motion(path, options: BvhImportOptions = BvhImportOptions(), fps: float | None = None) -> BvhImport:
    """Read a BVH file as SMPL-22 motion; see :func:`bvh_to_motion`."""
    return bvh_to_motion(read_bvh(path), options, fps)


# ---------------------------------------------------------------------------
# Export
# ---------------------------------------------------------------------------
#: World (Z up, facing +X) -> BVH file (Y up, facing +Z): yup = zup[..., [1, 2, 0]].
_TO_FILE = Y_UP.T
#: Cosmetic End Sites so leaf bones have a length in viewers: (joint, world rest offset m).
_END_SITES = {
    "head": (0.0, 0.0, 0.10),
    "left_wrist": (0.0, 0.08, 0.0),
    "right_wrist": (0.0, -0.08, 0.0),
    "left_foot": (0.05, 0.0, 0.0),
    "right_foot": (0.05, 0.0, 0.0),
}
_CHILDREN = {j: [c for c in range(N_JOINTS) if PARENTS[c] == j] for j in range(N_JOINTS)}


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 1e-12, n, 1.0)


def motion_to_bvh(motion: Motion, translations: str = "root") -> BvhClip:
    """An SMPL-22 BVH clip (metres, Y up) reproducing ``motion``'s positions.

    translations: 'root' (position channels on the pelvis only, the usual layout)
    or 'all' (every joint, exact round trip for any input). See the module docstring.
    """
    if translations not in ("root", "all"):
        raise DualFlowError(f"translations must be 'root' or 'all', got {translations!r}")
    p = np.einsum("ab,tjb->tja", _TO_FILE, motion.positions)  # (T, 22, 3) file frame
    T = p.shape[0]
    rest = REST_POSE @ _TO_FILE.T
    bones = p[:, 1:] - p[:, list(PARENTS[1:])]
    length = np.median(np.linalg.norm(bones, axis=-1), axis=0)  # (21,)
    offsets = np.zeros((N_JOINTS, 3))
    offsets[0] = rest[0]
    for j in range(1, N_JOINTS):
        offsets[j] = _unit(rest[j] - rest[PARENTS[j]]) * length[j - 1]

    glob = np.empty((T, N_JOINTS, 3, 3))
    for j in range(N_JOINTS):
        parent = PARENTS[j]
        g_parent = np.broadcast_to(np.eye(3), (T, 3, 3)) if parent < 0 else glob[:, parent]
        kids = _CHILDREN[j]
        if len(kids) > 1:
            dst = p[:, kids] - p[:, j : j + 1]  # (T, C, 3)
            g = align_vector_sets(np.broadcast_to(offsets[kids], dst.shape), dst)
            # replace the rest-layout offsets by the clip's mean body-frame vectors
            offsets[kids] = np.einsum("tba,tcb->tca", g, dst).mean(axis=0)
            glob[:, j] = align_vector_sets(np.broadcast_to(offsets[kids], dst.shape), dst)
        elif len(kids) == 1:
            c = kids[0]
            carried = _unit(np.einsum("tab,b->ta", g_parent, offsets[c]))
            observed = p[:, c] - p[:, j]
            ok = np.linalg.norm(observed, axis=-1) > 1e-9
            target = np.where(ok[:, None], _unit(observed), carried)
            glob[:, j] = swing_rotation(carried, target) @ g_parent
        else:
            glob[:, j] = g_parent

    local = np.empty_like(glob)
    local[:, 0] = glob[:, 0]
    par = list(PARENTS[1:])
    local[:, 1:] = np.swapaxes(glob[:, par], -1, -2) @ glob[:, 1:]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gimbal-lock notices: the angles are still exact
        euler = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_euler("ZYX", degrees=True).reshape(T, N_JOINTS, 3)

    rot_channels = ("Zrotation", "Yrotation", "Xrotation")
    pos_channels = ("Xposition", "Yposition", "Zposition")
    joints: list[BvhJoint] = []
    columns: list[np.ndarray] = []
    index: dict[int, int] = {}

    def add(j: int) -> None:
        parent = PARENTS[j]
        with_pos = parent < 0 or translations == "all"
        channels = (pos_channels if with_pos else ()) + rot_channels
        index[j] = len(joints)
        joints.append(BvhJoint(JOINT_NAMES[j], -1 if parent < 0 else index[parent], tuple(offsets[j]), channels))
        if with_pos:
            if parent < 0:
                columns.append(p[:, 0])
            else:
                rel = p[:, j] - p[:, parent]
                columns.append(np.einsum("tba,tb->ta", glob[:, parent], rel))
        columns.append(euler[:, j])
        if JOINT_NAMES[j] in _END_SITES:
            end = np.asarray(_END_SITES[JOINT_NAMES[j]]) @ _TO_FILE.T
            joints.append(BvhJoint(f"{JOINT_NAMES[j]}_end", index[j], tuple(end), (), True))
        for c in _CHILDREN[j]:
            add(c)

    add(0)
    return BvhClip(tuple(joints), 1.0 / motion.fps, np.concatenate(columns, axis=1), motion.name or "<motion>")


def write_bvh_motion(motion: Motion, path, translations: str = "root", precision: int = 6) -> None:
    """Write ``motion`` as an SMPL-22 BVH file (metres, Y up), atomically."""
    write_bvh(motion_to_bvh(motion, translations), path, precision)
