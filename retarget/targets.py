"""Human motion → robot keypoint targets at robot scale, and foot contacts.

Scaling walks the keypoint tree from the root (the profile's ``root``, normally the pelvis):

    target_root(t) = s_root · h_root(t)                                   (free base)
    target_k(t)    = target_parent(k)(t) + s_k · (h_k(t) − h_parent(k)(t))

where h are human joint positions (m), parent(k) the nearest ancestor keypoint and
s_k, s_root the robot/human rest-pose length ratios of :class:`retarget.robot.RetargetRobot`.
Directions are the human's, lengths the robot's; nothing depends on joint frames.

For a fixed base the root is the robot's (fixed) root keypoint, and the human's bone
vectors are first turned by the inverse of the human's heading (yaw from the hips), so
an upper-body partner mirrors the person's posture, not their walking.

Contacts: the motion's labels (T, 4) when present, else detected: a foot joint is in
contact when it is within ``height_tol`` of its rest height above the ground and moves
slower than ``speed_tol``. A side is in contact when its ankle or toe is. Flickers
shorter than ``min_frames`` are removed and gaps as short are filled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualflow.motion import Motion
from dualflow.motion.skeleton import FOOT_JOINTS, REST_POSE
from retarget.errors import RetargetError


@dataclass(frozen=True)
class Targets:
    """keypoints (T, K, 3) m at robot scale; contacts (T, 2) bool (left, right); fps."""

    keypoints: np.ndarray
    contacts: np.ndarray
    fps: float


def check_motion(motion: Motion, min_frames: int = 2) -> None:
    """Raise RetargetError for input the solvers cannot use (NaN, too short)."""
    if not isinstance(motion, Motion):
        raise RetargetError(f"motion: expected a dualflow.motion.Motion, got {type(motion).__name__}")
    what = motion.name or "motion"
    pos = motion.positions
    if not np.all(np.isfinite(pos)):
        frame = int(np.argwhere(~np.isfinite(pos))[0][0])
        raise RetargetError(f"{what}: positions contain NaN or inf at frame {frame}; clean or drop those frames")
    if motion.n_frames < min_frames:
        raise RetargetError(f"{what}: has {motion.n_frames} frame(s); retargeting needs at least {min_frames} "
                            "(velocity and acceleration need neighbours); give a longer clip")


def detect_contacts(motion: Motion, height_tol: float = 0.05, speed_tol: float = 0.4, min_frames: int = 3) -> np.ndarray:
    """(T, 4) bool contact of left ankle, left toe, right ankle, right toe (InterGen's order)."""
    pos = motion.positions[:, list(FOOT_JOINTS), :]
    rest_h = REST_POSE[list(FOOT_JOINTS), 2]
    height = pos[..., 2] - rest_h[None]
    vel = np.zeros(pos.shape[:2])
    if motion.n_frames > 1:
        v = np.linalg.norm(np.diff(pos, axis=0), axis=-1) * motion.fps
        vel[1:] = v
        vel[0] = v[0]
    c = (height < height_tol) & (vel < speed_tol)
    return np.stack([_debounce(c[:, i], min_frames) for i in range(4)], axis=1)


def _debounce(c: np.ndarray, n: int) -> np.ndarray:
    """Fill False gaps shorter than n between True runs, then drop True runs shorter than n."""
    c = c.copy()
    for value in (False, True):
        runs = _runs(c)
        for start, stop, v in runs:
            if v == value and stop - start < n and (value or (start > 0 and stop < len(c))):
                c[start:stop] = not value
    return c


def _runs(c: np.ndarray):
    out, start = [], 0
    for i in range(1, len(c) + 1):
        if i == len(c) or c[i] != c[start]:
            out.append((start, i, bool(c[start])))
            start = i
    return out


def side_contacts(contacts4: np.ndarray) -> np.ndarray:
    """(T, 4) foot-joint contacts → (T, 2) left, right foot contact."""
    c = np.asarray(contacts4, dtype=bool)
    return np.stack([c[:, 0] | c[:, 1], c[:, 2] | c[:, 3]], axis=1)


def _heading(positions: np.ndarray) -> np.ndarray:
    """(T,) yaw of the person's facing direction (+X at yaw 0) from the hip line."""
    left, right = positions[:, 1], positions[:, 2]
    across = left - right
    return np.arctan2(-across[:, 0], across[:, 1])


def make_targets(robot, motion: Motion, contacts: np.ndarray | None = None) -> Targets:
    """Scaled keypoint targets (T, K, 3) and side contacts (T, 2) for ``robot`` (a RetargetRobot)."""
    check_motion(motion, min_frames=1)
    h = motion.positions[:, robot.human_index, :]
    T, K = h.shape[:2]
    out = np.zeros_like(h)
    r = robot.root_keypoint
    if robot.floating:
        out[:, r] = robot.root_scale * h[:, r]
        rot = None
    else:
        stand = robot.evaluate(robot.x_stand[None])["keypoints"][0]
        out[:, r] = stand[r]
        yaw = _heading(motion.positions)
        c, s = np.cos(-yaw), np.sin(-yaw)
        rot = np.zeros((T, 3, 3))
        rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
    order = _topological(robot.keypoint_parent)
    for k in order:
        p = robot.keypoint_parent[k]
        if p < 0:
            continue
        bone = h[:, k] - h[:, p]
        if rot is not None:
            bone = np.einsum("tij,tj->ti", rot, bone)
        out[:, k] = out[:, p] + robot.bone_scales[k] * bone
    if contacts is None:
        contacts = motion.contacts if motion.contacts is not None else detect_contacts(motion)
    contacts = np.asarray(contacts, dtype=bool)
    if contacts.shape == (T, 4):
        contacts = side_contacts(contacts)
    if contacts.shape != (T, 2):
        raise RetargetError(f"contacts: expected shape ({T}, 4) or ({T}, 2), got {contacts.shape}")
    if not robot.has_feet or not robot.floating:
        contacts = np.zeros((T, 2), dtype=bool)
    return Targets(out, contacts, motion.fps)


def _topological(parent: np.ndarray) -> list[int]:
    order, seen = [], set()

    def visit(k):
        if k in seen:
            return
        if parent[k] >= 0:
            visit(int(parent[k]))
        seen.add(k)
        order.append(k)

    for k in range(len(parent)):
        visit(k)
    return order


def human_from_keypoints(robot, keypoints: np.ndarray, fps: float, name: str = "from robot keypoints") -> Motion:
    """The inverse of :func:`make_targets` (free base): a human Motion whose scaled targets are
    exactly ``keypoints`` (T, K, 3). Human joints that are not keypoints are placed at their
    rest offset from their parent. Used for round-trip checks and for replaying robot clips."""
    from dualflow.motion.skeleton import N_JOINTS, PARENTS

    kp = np.asarray(keypoints, dtype=np.float64)
    T = kp.shape[0]
    h = np.zeros((T, N_JOINTS, 3))
    done = np.zeros(N_JOINTS, dtype=bool)
    for k in _topological(robot.keypoint_parent):
        j, p = robot.human_index[k], robot.keypoint_parent[k]
        if p < 0:
            h[:, j] = kp[:, k] / robot.root_scale
        else:
            h[:, j] = h[:, robot.human_index[p]] + (kp[:, k] - kp[:, p]) / robot.bone_scales[k]
        done[j] = True
    for j in range(N_JOINTS):
        if not done[j]:
            chain = [j]
            while not done[chain[-1]]:
                chain.append(PARENTS[chain[-1]])
            for c in reversed(chain[:-1]):
                h[:, c] = h[:, PARENTS[c]] + (REST_POSE[c] - REST_POSE[PARENTS[c]])
                done[c] = True
    return Motion(h, fps=fps, name=name)
