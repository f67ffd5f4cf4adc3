"""Reading and writing human motion files (numpy only; never imports torch).

BVH (any hierarchy, with joint maps to SMPL-22, unit and up-axis detection) lives
in :mod:`.bvh` (the format) and :mod:`.bvh_motion` (to and from SMPL-22 motion).
"""

from dualflow.motion.io.bvh import BvhClip, BvhJoint, read_bvh, write_bvh
from dualflow.motion.io.bvh_motion import (
    BvhImport,
    BvhImportOptions,
    bvh_to_motion,
    motion_to_bvh,
    read_bvh_motion,
    write_bvh_motion,
)
from dualflow.motion.io.formats import (
    DUET_FORMAT,
    MOTION_FORMAT,
    load_any,
    load_motion,
    load_pair,
    put_on_ground,
    save_motion,
)
from dualflow.motion.io.joint_maps import BUILTIN_MAPS, JointMap, load_joint_map, resolve_joint_map
from dualflow.motion.io.units import HEIGHT_RANGE, KNOWN_UNITS, estimate_height

__all__ = [
    "BUILTIN_MAPS",
    "DUET_FORMAT",
    "HEIGHT_RANGE",
    "KNOWN_UNITS",
    "MOTION_FORMAT",
    "BvhClip",
    "BvhImport",
    "BvhImportOptions",
    "BvhJoint",
    "JointMap",
    "bvh_to_motion",
    "estimate_height",
    "load_any",
    "load_joint_map",
    "load_motion",
    "load_pair",
    "motion_to_bvh",
    "put_on_ground",
    "read_bvh",
    "read_bvh_motion",
    "resolve_joint_map",
    "save_motion",
    "write_bvh",
    "write_bvh_motion",
]
