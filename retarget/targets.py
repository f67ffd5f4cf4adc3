"""Human motion → robot keypoint targets at robot scale, and foot contacts.

Contract: :func:`make_targets` turns a :class:`dualflow.motion.Motion` (SMPL-22 positions
(T, 22, 3) m, Z up) into :class:`Targets`: keypoints (T, K, 3) m at the robot's bone lengths and
side contacts (T, 2) bool (the motion's labels, else detected). :class:`KeypointScaler` keeps the
person's bone directions and the robot's rest bone lengths, walking the profile's keypoint tree
from its root; a fixed base mirrors the posture in the person's heading. Scaling and contact
detection in full: docs/retargeting.md, section 1.
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
        raise RetargetError(
            f"{what}: has {motion.n_frames} frame(s); retargeting needs at least {min_frames} "
            "(velocity and acceleration need neighbours); give a longer clip"
        )


#: A person's foot joint is on the floor while it is within this height (m) of its rest height
#: and moves slower than this speed (m/s, per 30 fps frame); runs and gaps shorter than
#: CONTACT_MIN_FRAMES frames are smoothed away. sim.check counts a robot's steps by the same
#: rule, scaled to the robot's size.
CONTACT_HEIGHT = 0.05
CONTACT_SPEED = 0.4
CONTACT_MIN_FRAMES = 3
CONTACT_FPS = 30.0


#: The share of a clip's frames whose lowest foot joint may stand below its floor
#: (:func:`floor_offset`): marker noise, a foot sliding through the floor now and then
FLOOR_QUANTILE = 0.05


def floor_offset(heights: np.ndarray) -> float:
    """The height (m) of the floor a clip's feet stand on, from ``heights`` (T, 4): its foot
    joints' heights above their rest heights. The FLOOR_QUANTILE low quantile, over frames, of
    the lowest foot joint: 0 for a capture on z = 0 with SMPL's ankle and toe heights, the
    offset for one whose floor is elsewhere or whose skeleton's ankles sit higher or lower
    (CMU 18_01 +7 mm, 19_01 -16 mm). A floor 5 cm up left every frame of a clip in the air: a
    flight the robot stood through, never stepping."""
    lowest = np.min(heights, axis=1)
    return float(np.quantile(lowest, FLOOR_QUANTILE)) if lowest.size else 0.0


def detect_contacts(
    motion: Motion,
    height_tol: float = CONTACT_HEIGHT,
    speed_tol: float = CONTACT_SPEED,
    min_frames: int = CONTACT_MIN_FRAMES,
) -> np.ndarray:
    """(T, 4) bool contact of left ankle, left toe, right ankle, right toe (InterGen's order),
    heights measured above the clip's own floor (:func:`floor_offset`)."""
    pos = motion.positions[:, list(FOOT_JOINTS), :]
    rest_h = REST_POSE[list(FOOT_JOINTS), 2]
    height = pos[..., 2] - rest_h[None]
    height -= floor_offset(height)
    vel = np.zeros(pos.shape[:2])
    if motion.n_frames > 1:
        v = np.linalg.norm(np.diff(pos, axis=0), axis=-1) * motion.fps
        vel[1:] = v
        vel[0] = v[0]
    c = (height < height_tol) & (vel < speed_tol)
    return np.stack([debounce(c[:, i], min_frames) for i in range(4)], axis=1)


def debounce(c: np.ndarray, n: int) -> np.ndarray:
    """Fill False gaps shorter than n between True runs, then drop True runs shorter than n."""
    c = c.copy()
    for value in (False, True):
        runs = bool_runs(c)
        for start, stop, v in runs:
            if v == value and stop - start < n and (value or (start > 0 and stop < len(c))):
                c[start:stop] = not value
    return c


def bool_runs(c: np.ndarray) -> list[tuple[int, int, bool]]:
    """(start, stop, value) of the runs of a bool array (T,)."""
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


class KeypointScaler:
    """Per-bone scales for one human: s_k = robot rest length / this human's length.

    The human's bone lengths are the medians over a clip (robust to marker noise), or the
    SMPL REST_POSE when no clip is given (e.g. a live stream's start). The root scale is the
    robot's standing root height over the human's, the human's being REST_POSE's pelvis height
    times the ratio of this human's leg length (hip→knee→ankle) to REST_POSE's. Profile
    overrides (``scale:``) win over both.
    """

    def __init__(self, robot, human_positions: np.ndarray | None = None):
        self.robot = robot
        ref = REST_POSE[None] if human_positions is None else np.asarray(human_positions, dtype=np.float64)
        hidx, par = robot.human_index, robot.keypoint_parent
        scales = np.ones(robot.n_keypoints)
        for k, p in enumerate(par):
            if p < 0:
                continue
            name = robot.keypoint_names[k]
            if name in robot.profile.scale_overrides:
                scales[k] = robot.profile.scale_overrides[name]
                continue
            hl = float(np.median(np.linalg.norm(ref[:, hidx[k]] - ref[:, hidx[p]], axis=-1)))
            if hl < 1e-4:
                raise RetargetError(
                    f"motion: the human bone {robot.keypoint_names[p]} -> {name} has zero length; "
                    "check the joint positions"
                )
            scales[k] = robot.bone_lengths[k] / hl
        self.bone_scales = scales
        if robot.profile.root_scale is not None:
            self.root_scale = robot.profile.root_scale
        else:
            legs = [(1, 4), (4, 7), (2, 5), (5, 8)]  # SMPL hip→knee→ankle, both sides
            rest = sum(np.linalg.norm(REST_POSE[a] - REST_POSE[b]) for a, b in legs)
            this = sum(float(np.median(np.linalg.norm(ref[:, a] - ref[:, b], axis=-1))) for a, b in legs)
            human_h = REST_POSE[hidx[robot.root_keypoint], 2] * this / rest
            self.root_scale = float(robot.standing_root_height / human_h)

    def targets(self, positions: np.ndarray) -> np.ndarray:
        """Human positions (T, 22, 3) → robot keypoint targets (T, K, 3) (see the module docstring)."""
        rb = self.robot
        h = np.asarray(positions, dtype=np.float64)[:, rb.human_index, :]
        T = h.shape[0]
        out = np.zeros_like(h)
        r = rb.root_keypoint
        rot = None
        if rb.floating:
            out[:, r] = self.root_scale * h[:, r]
        else:
            stand = rb.evaluate(rb.x_stand[None])["keypoints"][0]
            out[:, r] = stand[r]
            yaw = _heading(np.asarray(positions))
            c, s = np.cos(-yaw), np.sin(-yaw)
            rot = np.zeros((T, 3, 3))
            rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
        frames = {}
        for k in _topological(rb.keypoint_parent):
            p = rb.keypoint_parent[k]
            if p < 0:
                continue
            name = rb.keypoint_names[k]
            frame_of = _FRAME_BONES.get(name) if name in rb.profile.rigid_offsets else None
            if frame_of is not None:
                if frame_of not in frames:
                    frames[frame_of] = _body_frame(np.asarray(positions, dtype=np.float64), frame_of)
                bone = np.einsum("tij,j->ti", frames[frame_of], rb.rest_offsets[k])
                scale = 1.0
            else:
                bone = h[:, k] - h[:, p]
                scale = self.bone_scales[k]
            if rot is not None:
                bone = np.einsum("tij,tj->ti", rot, bone)
            out[:, k] = out[:, p] + scale * bone
        return out


#: The frame each ``rigid_offsets`` keypoint of a profile turns with. These short bones across
#: the pelvis and the chest point differently on a person and on most robots (human hips sit
#: lower and wider), so their targets are the robot's own rest offset turned by the human's
#: pelvis / chest frame instead of the scaled human bone.
_FRAME_BONES = {"left_hip": "pelvis", "right_hip": "pelvis", "left_shoulder": "chest", "right_shoulder": "chest"}


def _body_frame(positions: np.ndarray, which: str) -> np.ndarray:
    """(T, 3, 3) rotation of the human's pelvis or chest: columns forward, left, up.

    left = unit(left − right joint) (hips, or shoulders), up = the spine direction
    (pelvis→spine1, or spine3→neck) made orthogonal to left, forward = left × up.
    In the rest pose both are the identity (DESIGN.md: facing +X, left +Y, Z up)."""
    if which == "pelvis":
        across, up = positions[:, 1] - positions[:, 2], positions[:, 3] - positions[:, 0]
    else:
        across, up = positions[:, 16] - positions[:, 17], positions[:, 12] - positions[:, 9]
    y = across / np.maximum(np.linalg.norm(across, axis=-1, keepdims=True), 1e-9)
    z = up - np.sum(up * y, axis=-1, keepdims=True) * y
    z /= np.maximum(np.linalg.norm(z, axis=-1, keepdims=True), 1e-9)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


def make_targets(
    robot, motion: Motion, contacts: np.ndarray | None = None, scaler: KeypointScaler | None = None
) -> Targets:
    """Scaled keypoint targets (T, K, 3) and side contacts (T, 2) for ``robot`` (a RetargetRobot).

    The scaler defaults to one fitted on this clip's own bone lengths."""
    check_motion(motion, min_frames=1)
    scaler = scaler or KeypointScaler(robot, motion.positions)
    out = scaler.targets(motion.positions)
    T = out.shape[0]
    if contacts is None:
        contacts = motion.contacts if motion.contacts is not None else detect_contacts(motion)
    contacts = np.asarray(contacts, dtype=bool)
    if contacts.shape == (T, 4):
        contacts = side_contacts(contacts)
    if contacts.shape != (T, 2):
        raise RetargetError(f"contacts: expected shape ({T}, 4) or ({T}, 2), got {contacts.shape}")
    if not robot.has_feet or not robot.floating:
        contacts = np.zeros((T, 2), dtype=bool)
    else:
        out = out + np.array([0.0, 0.0, ground_offset(robot, out, contacts)])
    return Targets(out, contacts, motion.fps)


def ground_offset(robot, keypoints: np.ndarray, contacts: np.ndarray) -> float:
    """Vertical shift (m) that puts the scaled ankles, while their foot is in contact, at the
    robot's own standing ankle height (median over contact frames). Scaling a real person's
    feet rarely lands them exactly on the ground; this is the clip-level correction."""
    shifts = []
    for side, joint in ((0, "left_ankle"), (1, "right_ankle")):
        if joint in robot.keypoint_names and contacts[:, side].any():
            k = robot.keypoint_names.index(joint)
            shifts.append(robot.standing_heights[k] - np.median(keypoints[contacts[:, side], k, 2]))
    return float(np.median(shifts)) if shifts else 0.0


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
    """The inverse of :meth:`KeypointScaler.targets` with the REST_POSE scaler (free base): a
    human Motion whose scaled targets are ``keypoints`` (T, K, 3). Human joints that are not
    keypoints sit at their rest offset from their parent. Because only bone *directions* of
    the result matter, re-fitting the scaler on it gives back REST_POSE's scales only if its
    bone lengths are constant, which they are for a rigid robot. Used for round-trip checks."""
    from dualflow.motion.skeleton import N_JOINTS, PARENTS

    sc = KeypointScaler(robot)
    kp = np.asarray(keypoints, dtype=np.float64)
    T = kp.shape[0]
    h = np.zeros((T, N_JOINTS, 3))
    done = np.zeros(N_JOINTS, dtype=bool)
    for k in _topological(robot.keypoint_parent):
        j, p = robot.human_index[k], robot.keypoint_parent[k]
        if p < 0:
            h[:, j] = kp[:, k] / sc.root_scale
        elif robot.keypoint_names[k] in robot.profile.rigid_offsets:
            h[:, j] = h[:, robot.human_index[p]] + (kp[:, k] - kp[:, p]) * (
                np.linalg.norm(REST_POSE[j] - REST_POSE[robot.human_index[p]]) / max(robot.bone_lengths[k], 1e-9)
            )
        else:
            h[:, j] = h[:, robot.human_index[p]] + (kp[:, k] - kp[:, p]) / sc.bone_scales[k]
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
