"""What the check needs that a published MJCF may not say, from the rest of the robot's folder.

A model as published (MuJoCo Menagerie's, a vendor's) often leaves joints unranged (MuJoCo
then treats them as unlimited and stores a range of [0, 0]) and never names its servo's
no-load speed. A robot folder (:mod:`firmware_cfg.registry`) holds what is known besides:

- joint limits (rad) for the joints the MJCF leaves unranged: the retarget profile's
  ``joint_limits``, else the hardware config's per-servo ``limits``;
- each joint's servo no-load speed (rad/s): the rated no-load speed of the servo model the
  hardware config names (:mod:`firmware_cfg.servo_models`; serial-link channels name none).

Values given explicitly (``SceneConfig.joint_limits`` / ``no_load_speed``) come first. Where
nothing is known, :class:`sim.robot_index.RobotIndex` records it and the check reports the
test as not run for those joints instead of passing it silently. A profile or hardware
config that cannot be read (a skeleton still to be filled in, say) is left out with a note
(``RobotFacts.notes``), not an error: the check does not need it to run.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from sim.errors import SimError


@dataclass(frozen=True)
class RobotFacts:
    """Per joint name: ``joint_limits`` (lower, upper) rad with ``limit_source`` ("given",
    "profile" or "hardware"), and ``no_load_speed`` rad/s with ``speed_source`` ("given" or
    "hardware"); ``notes``: files of the robot's folder that were left out, and why."""

    joint_limits: dict = field(default_factory=dict)
    limit_source: dict = field(default_factory=dict)
    no_load_speed: dict = field(default_factory=dict)
    speed_source: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    #: {joint: rad}: the profile's ``stand_pose``, where the MJCF has no stand keyframe
    stand_pose: dict = field(default_factory=dict)


def robot_facts(robot, joint_limits: Mapping | None = None, no_load_speed=None) -> RobotFacts:
    """The facts for robot reference ``robot`` (as the registry resolves it; None or an
    unresolvable reference gives only the explicit values). ``joint_limits`` maps joint ->
    (lower, upper) rad; ``no_load_speed`` maps joint -> rad/s, or is one number for all."""
    facts = RobotFacts()
    for name, lim in _limits(joint_limits or {}, "joint_limits").items():
        facts.joint_limits[name], facts.limit_source[name] = lim, "given"
    if isinstance(no_load_speed, Mapping):
        for name, v in no_load_speed.items():
            facts.no_load_speed[str(name)], facts.speed_source[str(name)] = _speed(v, f"no_load_speed.{name}"), "given"
    elif no_load_speed is not None:
        facts.no_load_speed["*"], facts.speed_source["*"] = _speed(no_load_speed, "no_load_speed"), "given"

    files = _robot_files(robot)
    if files is None:
        return facts
    profile, hardware = files
    if profile is not None:
        try:
            limits, stand = _profile_facts(profile)
            facts.stand_pose.update(stand)
        except SimError as exc:
            facts.notes.append(f"retarget profile left out: {exc}")
            limits = {}
        for name, lim in limits.items():
            if name not in facts.joint_limits:
                facts.joint_limits[name], facts.limit_source[name] = lim, "profile"
    if hardware is not None:
        try:
            servos = _hardware_servos(hardware)
        except SimError as exc:
            facts.notes.append(f"hardware config left out: {exc}")
            servos = ()
        for servo in servos:
            if servo.joint not in facts.joint_limits:
                facts.joint_limits[servo.joint] = (float(servo.lower), float(servo.upper))
                facts.limit_source[servo.joint] = "hardware"
            speed = _servo_speed(servo.model)
            if speed is not None and servo.joint not in facts.no_load_speed:
                facts.no_load_speed[servo.joint], facts.speed_source[servo.joint] = speed, "hardware"
    return facts


def _robot_files(robot) -> tuple[Path | None, Path | None] | None:
    if robot is None:
        return None
    from firmware_cfg.errors import ConfigError
    from firmware_cfg.registry import resolve

    try:
        r = resolve(robot)
    except ConfigError:
        return None  # the scene reports an unknown robot itself
    return r.profile, r.hardware


def _profile_facts(path: Path) -> tuple[dict, dict]:
    """The profile's ``joint_limits`` and ``stand_pose`` ({joint: rad})."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise SimError(f"{path}: cannot read the retarget profile ({str(exc).splitlines()[0]}); fix the file") from None
    data = data if isinstance(data, dict) else {}
    stand = data.get("stand_pose") or {}
    if not isinstance(stand, dict) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in stand.values()
    ):
        raise SimError(f"{path}: field stand_pose: must map joint names to finite angles in rad; fix the file")
    limits = _limits(data.get("joint_limits") or {}, f"{path}: joint_limits")
    return limits, {str(k): float(v) for k, v in stand.items()}


def _hardware_servos(path: Path):
    from firmware_cfg.config import load_config
    from firmware_cfg.errors import ConfigError

    try:
        return load_config(path, check_mjcf=False).servos
    except ConfigError as exc:
        raise SimError(str(exc)) from None


def _servo_speed(model: str | None) -> float | None:
    if not model:
        return None
    from firmware_cfg.errors import ConfigError
    from firmware_cfg.servo_models import load_servo_model

    try:
        speed = float(load_servo_model(model).no_load_speed_rad_s)
    except (ConfigError, KeyError, ValueError):
        return None
    return speed if math.isfinite(speed) and speed > 0 else None


def _limits(raw, where: str) -> dict:
    if not isinstance(raw, Mapping):
        raise SimError(f"{where}: give a mapping joint -> [lower, upper] in rad")
    out = {}
    for name, v in raw.items():
        try:
            lo, hi = (float(x) for x in v)
        except (TypeError, ValueError):
            raise SimError(f"{where}.{name}: give [lower, upper] in rad, got {v!r}") from None
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise SimError(f"{where}.{name}: need finite lower < upper (rad), got [{lo}, {hi}]")
        out[str(name)] = (lo, hi)
    return out


def _speed(v, where: str) -> float:
    try:
        s = float(v)
    except (TypeError, ValueError):
        raise SimError(f"{where}: give a speed in rad/s, got {v!r}") from None
    if not (math.isfinite(s) and s > 0):
        raise SimError(f"{where}: give a speed > 0 rad/s, got {v!r}")
    return s
