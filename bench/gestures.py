"""SYNTHETIC everyday two-person gestures for the retargeting figures and tests.

Made up by a program from the SMPL rest pose (rigid turns of joint subtrees), not captured: a
person standing with the arms hanging 15° out who bows, hands something over (both arms
forward, leaning in), gives two high fives, shakes hands (the hand pumping at 3 Hz), leans
from side to side, and waves. The feet never move (contacts are detected). Each clip starts
and ends standing. Units: m, s; Z up; the person faces +X at the origin, 30 fps.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dualflow.motion import REST_POSE, Motion
from dualflow.motion.skeleton import JOINT_NAMES, PARENTS

FPS = 30.0
_J = {n: i for i, n in enumerate(JOINT_NAMES)}


def _below(joint: int) -> list[int]:
    """The joints of ``joint``'s subtree, itself excluded (SMPL order: parents first)."""
    out, inside = [], {joint}
    for j, p in enumerate(PARENTS):
        if p in inside:
            inside.add(j)
            out.append(j)
    return out


def _turn(pose: np.ndarray, joint: str, rotvec) -> None:
    """Turn everything below ``joint`` about it by ``rotvec`` (rad, world axes), in place."""
    j = _J[joint]
    idx = _below(j)
    pose[idx] = Rotation.from_rotvec(rotvec).apply(pose[idx] - pose[j]) + pose[j]


def _lean(pose: np.ndarray, rotvec) -> None:
    """Turn the upper body (spine1 and all above it) about the pelvis."""
    idx = [_J["spine1"], *_below(_J["spine1"])]
    c = pose[_J["pelvis"]].copy()
    pose[idx] = Rotation.from_rotvec(rotvec).apply(pose[idx] - c) + c


def _ease(t: float, a: float, b: float) -> float:
    """0 before a, 1 after b, a smoothstep between."""
    s = min(max((t - a) / (b - a), 0.0), 1.0)
    return s * s * (3 - 2 * s)


def _standing() -> np.ndarray:
    pose = REST_POSE.copy()
    _turn(pose, "left_shoulder", [-np.radians(75), 0, 0])  # from the T-pose down to 15° out
    _turn(pose, "right_shoulder", [np.radians(75), 0, 0])
    return pose


def _clip(name: str, seconds: float, move) -> Motion:
    frames = []
    for k in range(int(round(seconds * FPS))):
        pose = _standing()
        move(pose, k / FPS)
        frames.append(pose)
    return Motion(np.stack(frames), FPS, name=f"gesture_{name}")


def _bow(pose, t):
    f = _ease(t, 0.8, 2.0) - _ease(t, 3.0, 4.2)
    _lean(pose, [0, np.radians(40) * f, 0])
    pose[[_J["pelvis"], _J["left_hip"], _J["right_hip"], _J["spine1"], *_below(_J["spine1"])]] -= [0.08 * f, 0, 0]


def _hand_over(pose, t):
    f = _ease(t, 0.8, 1.8) - _ease(t, 3.3, 4.3)
    for side in ("left", "right"):
        _turn(pose, f"{side}_shoulder", [0, -np.radians(80) * f, 0])
    _lean(pose, [0, np.radians(15) * f, 0])


def _high_five(pose, t):
    f = max(_ease(t, 1.0, 1.3) - _ease(t, 1.5, 2.0), _ease(t, 2.8, 3.1) - _ease(t, 3.3, 3.8))
    _turn(pose, "right_shoulder", [0, -np.radians(150) * f, 0])
    _lean(pose, [0, np.radians(8) * f, 0])


def _handshake(pose, t):
    f = _ease(t, 0.8, 1.5) - _ease(t, 3.5, 4.2)
    pump = np.radians(10) * np.sin(6 * np.pi * t) * _ease(t, 1.5, 1.7) * (1 - _ease(t, 3.0, 3.2))
    _turn(pose, "right_shoulder", [0, -(np.radians(45) * f + pump), 0])
    _lean(pose, [0, np.radians(10) * f, 0])


def _side_lean(pose, t):
    _lean(pose, [np.radians(20) * np.sin(0.8 * np.pi * t) * _ease(t, 0.5, 1.0), 0, 0])


def _wave(pose, t):
    f = _ease(t, 0.8, 1.4) - _ease(t, 3.6, 4.2)
    _turn(pose, "right_shoulder", [-np.radians(150) * f, 0, 0])
    _turn(pose, "right_elbow", [0, np.radians(30) * np.sin(4 * np.pi * t) * f, 0])


def gestures() -> list[Motion]:
    """The six gestures, 4.5-6 s each."""
    return [
        _clip("bow", 5.0, _bow),
        _clip("hand_over", 5.0, _hand_over),
        _clip("high_five", 4.5, _high_five),
        _clip("handshake", 5.0, _handshake),
        _clip("side_lean", 6.0, _side_lean),
        _clip("wave", 5.0, _wave),
    ]
