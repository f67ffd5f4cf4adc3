"""A robot is one name resolving to three files (DESIGN.md): its MJCF, its retarget
profile and its hardware config; and, derived from them, the limits the bridge enforces.

``resolve_robot("op3")`` finds the bundled files; ``resolve_robot("my_robot.yaml")`` takes
a hardware config, whose ``mjcf`` key names the model and whose ``robot`` key names the
retarget profile (bundled, or ``<robot>.profile.yaml`` beside the config).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_cfg.config import RobotConfig, load_config, robot_config_path
from firmware_cfg.servo_models import load_servo_model
from retarget.robot import resolve_paths
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.safety import JointLimits

#: Fraction of a servo's no-load speed the bridge may command (the rest is headroom
#: for the position loop to catch up under load).
VELOCITY_SCALE = 0.8
#: Joint acceleration limit (rad/s²) when the hardware config sets no profile acceleration:
#: about what brisk human arm motion scaled to a 0.5 m robot asks for, and well within what
#: an XM430 (4 N·m) gives a small robot's light links.
DEFAULT_MAX_ACCELERATION = 80.0


@dataclass(frozen=True)
class RobotFiles:
    name: str
    mjcf: Path
    profile: Path
    hardware: Path | None  #: None for a model with no hardware config (simulation only)

    def hardware_config(self) -> RobotConfig:
        if self.hardware is None:
            raise BridgeError(f"robot {self.name!r} has no hardware config; write one (see firmware_cfg/robots/op3.yaml)")
        return load_config(self.hardware, self.mjcf)


def resolve_robot(robot: str | Path) -> RobotFiles:
    text = str(robot)
    if text.endswith((".yaml", ".yml")):
        path = Path(text)
        cfg = load_config(path)
        if cfg.mjcf is None:
            raise BridgeError(f"{path}: the hardware config needs an 'mjcf' key naming the robot model")
        local_profile = path.with_name(f"{cfg.robot}.profile.yaml")
        profile = local_profile if local_profile.is_file() else resolve_paths(cfg.robot)[1]
        return RobotFiles(cfg.robot, Path(cfg.mjcf), Path(profile), path)
    mjcf, profile = resolve_paths(text)
    name = Path(mjcf).stem
    hardware = Path(robot_config_path(name))
    return RobotFiles(name, Path(mjcf), Path(profile), hardware if hardware.is_file() else None)


def bridge_limits(config: RobotConfig, velocity_scale: float = VELOCITY_SCALE,
                  default_acceleration: float = DEFAULT_MAX_ACCELERATION) -> JointLimits:
    """Position limits from the hardware config (already checked against the MJCF by
    ``load_config``), velocity from each servo model's no-load speed (or the profile
    velocity when set and lower), acceleration from the profile or the default."""
    lower, upper, vmax, amax = [], [], [], []
    for s in config.servos:
        lower.append(s.lower)
        upper.append(s.upper)
        v = np.inf
        if s.model is not None:
            v = load_servo_model(s.model).no_load_speed_rad_s * velocity_scale
        if s.profile_velocity:
            v = min(v, s.profile_velocity)
        if not np.isfinite(v):
            raise BridgeError(f"{config.source}: joint {s.joint!r} has neither a servo model nor a profile_velocity; "
                              "the bridge needs one to limit its speed")
        vmax.append(v)
        amax.append(s.profile_acceleration or default_acceleration)
    return JointLimits(config.joint_names, lower, upper, vmax, amax)
