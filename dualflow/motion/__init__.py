"""The human-motion contract (numpy only; never imports torch).

Frames and units (see DESIGN.md): metres, seconds, right-handed world with Z up,
ground plane at z = 0. A person standing in the rest pose faces +X with their
left hand towards +Y. InterGen's 262-d features are Y-up; the conversion between
the two happens once, in :mod:`dualflow.motion.features`.
"""

from dualflow.errors import DualFlowError
from dualflow.motion.container import Motion, TwoPersonMotion
from dualflow.motion.skeleton import (
    FACE_JOINTS,
    FOOT_JOINTS,
    JOINT_NAMES,
    KINEMATIC_CHAINS,
    LEFT_RIGHT_PAIRS,
    MIRROR_INDEX,
    N_JOINTS,
    PARENTS,
    REST_POSE,
    bone_lengths,
    joint_index,
)

__all__ = [
    "DualFlowError",
    "Motion",
    "TwoPersonMotion",
    "JOINT_NAMES",
    "PARENTS",
    "N_JOINTS",
    "KINEMATIC_CHAINS",
    "LEFT_RIGHT_PAIRS",
    "MIRROR_INDEX",
    "FOOT_JOINTS",
    "FACE_JOINTS",
    "REST_POSE",
    "bone_lengths",
    "joint_index",
]
