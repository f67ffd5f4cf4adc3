"""The SMPL 22-joint body skeleton: names, parents, chains, symmetry and a rest pose.

All positions are in the project's world frame: metres, Z up, the person facing
+X with their left towards +Y (so a left joint has y > 0 in the rest pose).
"""

from __future__ import annotations

import numpy as np

from dualflow.errors import DualFlowError

JOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
)
N_JOINTS = len(JOINT_NAMES)

#: Parent index of each joint (-1 for the root), SMPL order.
PARENTS: tuple[int, ...] = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)

#: Kinematic chains from the root outwards (right leg, left leg, spine+head,
#: right arm, left arm), the order HumanML3D and InterGen use for drawing.
KINEMATIC_CHAINS: tuple[tuple[int, ...], ...] = (
    (0, 2, 5, 8, 11),
    (0, 1, 4, 7, 10),
    (0, 3, 6, 9, 12, 15),
    (9, 14, 17, 19, 21),
    (9, 13, 16, 18, 20),
)

#: (left, right) joint index pairs.
LEFT_RIGHT_PAIRS: tuple[tuple[int, int], ...] = (
    (1, 2),
    (4, 5),
    (7, 8),
    (10, 11),
    (13, 14),
    (16, 17),
    (18, 19),
    (20, 21),
)


def _mirror_index() -> tuple[int, ...]:
    idx = list(range(N_JOINTS))
    for left, right in LEFT_RIGHT_PAIRS:
        idx[left], idx[right] = right, left
    return tuple(idx)


#: For each joint, the index of its mirror twin (itself on the midline).
MIRROR_INDEX: tuple[int, ...] = _mirror_index()

#: Foot joints in the column order of the contact labels (InterGen's order):
#: left ankle, left foot, right ankle, right foot.
FOOT_JOINTS: tuple[int, int, int, int] = (7, 10, 8, 11)
#: Ankle and toe ("foot") joints per side.
LEFT_FOOT_JOINTS: tuple[int, int] = (7, 10)
RIGHT_FOOT_JOINTS: tuple[int, int] = (8, 11)

#: Joints that define the facing direction, InterGen's ``face_joint_indx``:
#: right hip, left hip, right shoulder, left shoulder.
FACE_JOINTS: tuple[int, int, int, int] = (2, 1, 17, 16)

#: Rest pose (T-pose) of an adult about 1.72 m tall, metres, Z up, facing +X,
#: feet on the ground plane. Bone lengths follow common anthropometric tables
#: (thigh 0.39 m, shin 0.40 m, upper arm 0.26 m, forearm 0.25 m).
REST_POSE: np.ndarray = np.array(
    [
        [0.000, 0.000, 0.950],  # pelvis
        [0.000, 0.090, 0.870],  # left_hip
        [0.000, -0.090, 0.870],  # right_hip
        [-0.005, 0.000, 1.060],  # spine1
        [0.000, 0.100, 0.480],  # left_knee
        [0.000, -0.100, 0.480],  # right_knee
        [-0.005, 0.000, 1.190],  # spine2
        [-0.020, 0.100, 0.080],  # left_ankle
        [-0.020, -0.100, 0.080],  # right_ankle
        [0.000, 0.000, 1.250],  # spine3
        [0.110, 0.110, 0.020],  # left_foot
        [0.110, -0.110, 0.020],  # right_foot
        [0.000, 0.000, 1.470],  # neck
        [0.000, 0.080, 1.380],  # left_collar
        [0.000, -0.080, 1.380],  # right_collar
        [0.030, 0.000, 1.580],  # head
        [0.000, 0.180, 1.400],  # left_shoulder
        [0.000, -0.180, 1.400],  # right_shoulder
        [0.000, 0.440, 1.400],  # left_elbow
        [0.000, -0.440, 1.400],  # right_elbow
        [0.000, 0.690, 1.400],  # left_wrist
        [0.000, -0.690, 1.400],  # right_wrist
    ],
    dtype=np.float64,
)
REST_POSE.setflags(write=False)


def bone_lengths(positions: np.ndarray) -> np.ndarray:
    """Length of each bone (joint to its parent) in metres.

    positions: (..., 22, 3). Returns (..., 21): entry j-1 is the bone ending at joint j.
    """
    positions = np.asarray(positions)
    parents = np.asarray(PARENTS[1:])
    return np.linalg.norm(positions[..., 1:, :] - positions[..., parents, :], axis=-1)


def joint_index(name: str) -> int:
    """Index of an SMPL-22 joint by name; raises DualFlowError naming the valid names."""
    try:
        return JOINT_NAMES.index(name)
    except ValueError:
        raise DualFlowError(f"unknown SMPL joint name {name!r}; expected one of: {', '.join(JOINT_NAMES)}") from None
