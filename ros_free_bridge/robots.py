"""The bridge's view of a robot: its files from the robot registry
(:mod:`firmware_cfg.registry`: a bundled name, a robot folder, an MJCF or a hardware config)
and, derived from them, the limits the bridge enforces.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from firmware_cfg.config import RobotConfig, load_config
from firmware_cfg.errors import ConfigError
from firmware_cfg.registry import Robot, reference, resolve
from firmware_cfg.servo_models import load_servo_model
from retarget.actuation import DEFAULT_ACCELERATION
from ros_free_bridge.control.safety import JointLimits
from ros_free_bridge.errors import BridgeError

#: Fraction of a servo's no-load speed the bridge may command (the rest is headroom
#: for the position loop to catch up under load).
VELOCITY_SCALE = 0.8


@dataclass(frozen=True)
class RobotFiles:
    """A resolved robot as the bridge uses it. ``ref`` is how to name it again (a bundled
    name, or the folder / file path), which the generator process and telemetry carry."""

    name: str
    mjcf: Path
    profile: Path
    hardware: Path | None  #: None for a model with no hardware config (simulation only)
    ref: str
    fixed_base: bool

    def hardware_config(self) -> RobotConfig:
        if self.hardware is None:
            raise BridgeError(
                f"robot {self.ref}: no hardware config (hardware.yaml in the robot's folder); "
                "`dualflow-bridge robot init MODEL.xml -o DIR` writes a skeleton to fill in"
            )
        return load_config(self.hardware, self.mjcf)


def resolve_robot(robot: str | Path | Robot) -> RobotFiles:
    """The files of a robot reference; BridgeError naming the reference and the fix."""
    try:
        found = resolve(robot)
        profile = found.require_profile()
    except ConfigError as exc:
        raise BridgeError(str(exc)) from None
    return RobotFiles(found.name, found.mjcf, profile, found.hardware, reference(robot), found.fixed_base)


def bridge_limits(config: RobotConfig, velocity_scale: float = VELOCITY_SCALE) -> JointLimits:
    """Position limits from the hardware config (already checked against the MJCF by
    ``load_config``), velocity from each servo model's no-load speed (or the profile
    velocity when set and lower), acceleration from the servo's profile acceleration, else
    what the MJCF's actuator can give the joint's links, at least
    :data:`retarget.actuation.DEFAULT_ACCELERATION` (:func:`retarget.actuation.acceleration_limits`,
    as the retargeter plans with)."""
    model_acc = dict(zip(config.joint_names, _model_accelerations(config.mjcf, config.joint_names)))
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
            raise BridgeError(
                f"{config.source}: joint {s.joint!r} has neither a servo model nor a profile_velocity; "
                "the bridge needs one to limit its speed"
            )
        vmax.append(v)
        amax.append(s.profile_acceleration or model_acc[s.joint])
    return JointLimits(config.joint_names, lower, upper, vmax, amax)


def _model_accelerations(mjcf, names) -> np.ndarray:
    """:func:`retarget.actuation.acceleration_limits` of the MJCF at ``mjcf`` for joints
    ``names`` (:data:`retarget.actuation.DEFAULT_ACCELERATION` each without one)."""
    if mjcf is None:
        return np.full(len(names), DEFAULT_ACCELERATION)
    import mujoco

    from retarget.actuation import acceleration_limits

    try:
        return acceleration_limits(mujoco.MjModel.from_xml_path(str(mjcf)), names)
    except ValueError as exc:
        raise BridgeError(f"{mjcf}: MuJoCo cannot load it ({exc})") from None


def model_limits(robot) -> JointLimits:
    """Limits of a robot known only by its model (no hardware config: simulation or recording):
    the joint ranges, speeds and accelerations its retargeter keeps (MJCF ranges narrowed by the
    profile; the profile's velocity limits, never above the MJCF's servo speed; what the
    actuators can give the links). ``robot`` is a :class:`retarget.robot.RetargetRobot`."""
    n = robot.n_root
    return JointLimits(
        tuple(robot.joint_names), robot.x_lower[n:], robot.x_upper[n:], robot.velocity_limits, robot.acceleration_limits
    )


def planning_robot(robot, profile=None, fixed_base: bool = False, limits: JointLimits | None = None):
    """The :class:`retarget.robot.RetargetRobot` the bridge retargets for ``robot`` (a reference
    as :func:`retarget.robot.load_robot` takes it, with its ``profile`` and ``fixed_base``):
    where the robot has a hardware config, its speed and acceleration limits are narrowed to
    the loop's (``limits`` when the caller has them, else :func:`bridge_limits`), so that the
    safety filter sends its plans nearly as planned (a servo's profile acceleration, or the
    loop's 0.8 x no-load speed below the profile's speed limit, would otherwise make the servos
    lag the plan)."""
    from retarget.robot import load_robot

    rb = load_robot(robot, profile, fixed_base=fixed_base)
    if limits is None:
        limits = _hardware_limits(robot)
    if limits is not None:
        rb.narrow_limits(limits.names, limits.max_velocity, limits.max_acceleration)
    return rb


def _hardware_limits(robot) -> JointLimits | None:
    """:func:`bridge_limits` of ``robot``'s hardware config; None without one, or for one the
    loop cannot drive yet (a serial-link channel with no speed limit, say): retargeting does not
    need it, and `run` names what is wrong itself."""
    try:
        found = resolve(robot)
    except ConfigError:  # a bare MJCF load_robot took with a profile given: no hardware to heed
        return None
    if found.hardware is None:
        return None
    try:
        return bridge_limits(load_config(found.hardware, found.mjcf))
    except (ConfigError, BridgeError):
        return None


def loop_limits(files: RobotFiles) -> JointLimits:
    """The limits the bridge's loop drives robot ``files`` with: its hardware config's
    (:func:`bridge_limits`) when it has one, else its model's (:func:`model_limits`: a model
    just brought in, simulated or recorded)."""
    if files.hardware is not None:
        return bridge_limits(files.hardware_config())
    from retarget.robot import load_robot

    return model_limits(load_robot(files.mjcf, files.profile))


def check_command_filter(robot, control_hz: float):
    """A :class:`sim.check.CheckConfig` ``command_filter`` for ``robot`` (a bundled name, a robot
    folder or an MJCF): the safety filter of the bridge's loop at ``control_hz``, with the
    limits it drives that robot with (:func:`loop_limits`), so that the physics check plays a
    trajectory as the bridge would send it. BridgeError names a robot it cannot resolve."""
    from ros_free_bridge.control.safety import SafetyFilter

    files = resolve_robot(robot)
    limits = loop_limits(files)
    dt = 1.0 / float(control_hz)

    def make(joint_names, start):
        try:
            lim = limits.in_order(joint_names)
        except BridgeError as exc:
            raise BridgeError(f"robot {files.ref}: the bridge's {exc}") from None
        f = SafetyFilter(lim, dt)
        f.reset(start)
        return lambda q: f.step(q)[0]

    return make


def bridge_check_config(robot, **fields):
    """A :class:`sim.check.CheckConfig` with ``fields`` that plays each command through the
    bridge's safety filter for ``robot`` (:func:`check_command_filter`): what ``check``,
    ``render`` and ``retarget-check`` judge."""
    from sim.check import CheckConfig

    config = CheckConfig(**fields)
    config.validate()  # a bad rate is named before the filter is made at it
    return replace(config, command_filter=check_command_filter(robot, config.control_hz))
