"""The bundled robot models (MJCF), looked up by name without importing mujoco.

A robot name resolves to ``sim/robots/<name>/<name>.xml``. Each model declares one
position actuator per joint, named like its joint; the ACTUATOR order is the robot's
joint order (for op3, the ROBOTIS servo-ID order), which trajectories, the hardware
config and the bridge use. MuJoCo's qpos order follows the body tree instead, so
look joints up by name, never by qpos index.

Each model has a keyframe named ``"stand"`` (its rest/standing pose) and named sites
for the retargeting keypoints (see each model's header comment and
:data:`KEYPOINT_SITES`).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from sim.errors import SimError

ROBOTS_DIR = Path(__file__).resolve().parent


@dataclass(frozen=True)
class RobotInfo:
    """What a bundled robot is, in one line, and whether its base is bolted down."""

    name: str
    description: str
    fixed_base: bool


#: Bundled robots by name.
ROBOTS: dict[str, RobotInfo] = {
    "op3": RobotInfo(
        "op3",
        "OP3-class 20-DOF Dynamixel humanoid (XM430-W350 servos), 0.51 m, 3.37 kg, free-standing",
        fixed_base=False,
    ),
    "ub14": RobotInfo(
        "ub14",
        "fixed-base adult-sized upper-body partner, 14 DOF (waist yaw/pitch, neck, 5 per arm), XM540-W270 servos",
        fixed_base=True,
    ),
}

#: Retarget keypoint sites every bundled humanoid with legs has (op3). Fixed-base
#: robots have the upper-body subset (see their MJCF header).
KEYPOINT_SITES: tuple[str, ...] = (
    "pelvis", "torso", "head",
    "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand",
    "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle", "r_ankle",
    "l_foot", "r_foot", "l_toe", "r_toe",
)


def mjcf_path(name: str) -> Path:
    """Path of robot ``name``'s MJCF; a path to an existing .xml file is accepted as is.

    Raises SimError naming the bundled robots when ``name`` is unknown.
    """
    name = str(name)
    candidate = Path(name)
    if candidate.suffix == ".xml":
        if not candidate.is_file():
            raise SimError(f"robot model {candidate}: file not found; give an existing MJCF file or one of {sorted(ROBOTS)}")
        return candidate
    path = ROBOTS_DIR / name / f"{name}.xml"
    if name not in ROBOTS or not path.is_file():
        raise SimError(f"unknown robot {name!r}; bundled robots are: {', '.join(sorted(ROBOTS))}")
    return path


@lru_cache(maxsize=None)
def _parse(path: Path) -> ET.Element:
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SimError(f"robot model {path}: not valid XML ({exc})") from None


def joint_names(name: str) -> tuple[str, ...]:
    """The robot's joint names in actuator order (for op3: servo IDs 1..20)."""
    root = _parse(mjcf_path(name))
    names = tuple(el.get("joint") for el in root.iter() if el.tag in ("position", "general", "motor") and el.get("joint"))
    if not names:
        raise SimError(f"robot model {mjcf_path(name)}: no joint actuators found; each joint needs a <position> actuator")
    return names


def joint_limits(name: str) -> dict[str, tuple[float, float]]:
    """Joint limits (lower, upper) in radians, read from the MJCF ``range`` attributes."""
    root = _parse(mjcf_path(name))
    limits = {}
    for el in root.iter("joint"):
        if el.get("name") and el.get("range"):
            lo, hi = (float(v) for v in el.get("range").split())
            limits[el.get("name")] = (lo, hi)
    return {j: limits[j] for j in joint_names(name)}


__all__ = ["ROBOTS", "ROBOTS_DIR", "RobotInfo", "KEYPOINT_SITES", "mjcf_path", "joint_names", "joint_limits"]
