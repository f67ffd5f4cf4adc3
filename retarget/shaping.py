"""Keypoint targets reshaped to what a small robot's feet can balance: the person's horizontal
travel followed with a bounded acceleration, from rest at the clip's start.

A body's horizontal acceleration a moves its zero-moment point by (c_z / g) a from the centre of
mass (the cart-table model). A person walking off from frame 0 of a clip (a clip that starts
mid-step) or swaying on the beat accelerates their pelvis by 1-2 m/s²; at the robot's scale that
is a ZMP shift of 3-5 cm, more than half the OP3's 12.7 cm foot, and the robot, brought to the
first frame at rest, would have to lunge after the person. :func:`ease_travel` moves every
keypoint target of a frame by the same horizontal offset so that the pelvis target follows the
person's from rest with a bounded-acceleration PD tracker (natural frequency ``omega``):

    a_t = clip(ω² (p_t − q_t) + 2ω (ṗ_t − q̇_t), |a| ≤ a_max),  q̇_{t+1} = q̇_t + a_t / fps,
    q_{t+1} = q_t + q̇_{t+1} / fps,  q_0 = p_0, q̇_0 = 0,

with p the person's pelvis xy (T, 2) and q the robot's; the offset is q − p. Where the person's
pelvis accelerates less than a_max the robot catches up and then follows exactly.
"""

from __future__ import annotations

import math

import numpy as np


def ease_travel(
    keypoints: np.ndarray, root: int, fps: float, a_max: float, omega: float = 2 * math.pi
) -> tuple[np.ndarray, np.ndarray]:
    """keypoints (T, K, 3) m, root: the index of the pelvis keypoint, a_max m/s², omega rad/s →
    (targets (T, K, 3) shifted horizontally, the shift (T, 2) m)."""
    kp = np.asarray(keypoints, dtype=np.float64)
    T = kp.shape[0]
    p = kp[:, root, 0:2]
    v = np.zeros_like(p)
    v[1:] = np.diff(p, axis=0) * fps
    q = np.empty_like(p)
    q[0] = p[0]
    qd = np.zeros(2)
    dt = 1.0 / fps
    for t in range(T - 1):
        a = omega**2 * (p[t] - q[t]) + 2 * omega * (v[t] - qd)
        n = math.hypot(a[0], a[1])
        if n > a_max:
            a *= a_max / n
        qd = qd + a * dt
        q[t + 1] = q[t] + qd * dt
    shift = q - p
    out = kp.copy()
    out[:, :, 0:2] += shift[:, None, :]
    return out, shift
