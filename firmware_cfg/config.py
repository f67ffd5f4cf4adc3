"""The per-robot hardware config (``hardware.yaml``): buses, servos, joint mapping, limits, settings.

:func:`load_config` reads one robot's file with ``yaml.safe_load`` and validates it into
frozen dataclasses (:class:`RobotConfig`), optionally against the robot's MJCF. Angles in
rad: joint side, except ``zero_offset`` (servo side). Every error is a :class:`ConfigError`
whose message starts with ``<file>: <field path>:`` and says what is wrong and the fix.
The file's fields, units and checks: docs/dynamixel.md, "The hardware config".
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from firmware_cfg import device_models, servo_models
from firmware_cfg.errors import ConfigError

PROTOCOLS = ("1.0", "2.0", "serial-link")
STOP_POLICIES = ("hold", "limp")
#: Serial-link wire range: int16 centi-degrees.
SERIAL_LINK_RANGE_RAD = 32767 * math.pi / 18000.0
SERIAL_LINK_MAX_CHANNELS = 32
#: Slack when comparing config limits with MJCF ranges written with fewer digits (rad).
MJCF_TOLERANCE = 1e-6

_SERVO_KEYS = {
    "id",
    "joint",
    "model",
    "direction",
    "zero_offset",
    "limits",
    "profile_velocity",
    "profile_acceleration",
    "pid",
    "return_delay_us",
    "status_return_level",
    "bus_watchdog_ms",
    "temperature_limit_c",
    "voltage_limits_v",
}
_DXL_ONLY = {
    "pid",
    "return_delay_us",
    "status_return_level",
    "bus_watchdog_ms",
    "profile_velocity",
    "profile_acceleration",
    "temperature_limit_c",
    "voltage_limits_v",
}
_BUS_KEYS = {"name", "port", "baud", "protocol", "defaults", "servos", "devices"}
_DEVICE_KEYS = {"id", "model", "role"}
#: What a non-servo device on a bus is for: ``imu`` = it reports the body's attitude and
#: angular velocity (the OP3's OpenCR).
DEVICE_ROLES = ("imu",)
_TOP_KEYS = {"robot", "mjcf", "stop_policy", "servo_defaults", "buses"}


@dataclass(frozen=True)
class PID:
    """Raw position-loop gains as stored in the servo's control table (unitless)."""

    p: int
    i: int
    d: int


@dataclass(frozen=True)
class ServoConfig:
    """One servo (or serial-link channel). Angles in rad, see the module docstring."""

    id: int
    joint: str
    model: str | None
    direction: int
    zero_offset: float
    lower: float
    upper: float
    profile_velocity: float | None = None
    profile_acceleration: float | None = None
    pid: PID | None = None
    return_delay_us: int | None = None
    status_return_level: int | None = None
    bus_watchdog_ms: int | None = None
    temperature_limit_c: int | None = None
    voltage_limits_v: tuple[float, float] | None = None

    def to_servo(self, joint_angle):
        """Joint angle (rad, scalar or array) → servo-side angle (rad):
        servo = direction · joint + zero_offset."""
        return self.direction * joint_angle + self.zero_offset

    def to_joint(self, servo_angle):
        """Servo-side angle (rad) → joint angle (rad): joint = direction · (servo − zero_offset)."""
        return self.direction * (servo_angle - self.zero_offset)

    def servo_limits(self) -> tuple[float, float]:
        """The joint limits mapped to the servo side, ordered (low, high), in rad."""
        a, b = self.to_servo(self.lower), self.to_servo(self.upper)
        return (min(a, b), max(a, b))


@dataclass(frozen=True)
class DeviceConfig:
    """A non-servo device on a Dynamixel bus (e.g. the OP3's OpenCR, ID 200, role imu)."""

    id: int
    model: str
    role: str


@dataclass(frozen=True)
class BusConfig:
    name: str
    port: str
    baud: int
    protocol: str
    servos: tuple[ServoConfig, ...]
    devices: tuple[DeviceConfig, ...] = ()

    @property
    def protocol_version(self) -> float:
        """1.0 or 2.0 for Dynamixel buses (the SDK's PacketHandler argument)."""
        if self.protocol == "serial-link":
            raise ConfigError(f"bus {self.name!r} is a serial link, not a Dynamixel bus")
        return float(self.protocol)


@dataclass(frozen=True)
class RobotConfig:
    robot: str
    buses: tuple[BusConfig, ...]
    stop_policy: str = "hold"
    source: str = "<config>"
    mjcf: Path | None = None

    @property
    def servos(self) -> tuple[ServoConfig, ...]:
        return tuple(s for b in self.buses for s in b.servos)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Joint names in file order (for the bundled robots: the MJCF's order)."""
        return tuple(s.joint for s in self.servos)

    def servo(self, joint: str) -> ServoConfig:
        for s in self.servos:
            if s.joint == joint:
                return s
        raise ConfigError(
            f"{self.source}: no servo drives joint {joint!r}; known joints: {', '.join(self.joint_names)}"
        )

    def bus(self, name: str | None = None) -> BusConfig:
        if name is None:
            if len(self.buses) != 1:
                raise ConfigError(f"{self.source}: {len(self.buses)} buses; name one of {[b.name for b in self.buses]}")
            return self.buses[0]
        for b in self.buses:
            if b.name == name:
                return b
        raise ConfigError(f"{self.source}: no bus named {name!r}; buses: {[b.name for b in self.buses]}")


# ----------------------------------------------------------------------------- loading


def robot_config_path(robot: str | Path) -> Path:
    """The hardware config of a robot reference (a bundled name, a robot folder, an MJCF in a
    robot folder, or the config itself), through the robot registry."""
    from firmware_cfg.registry import resolve

    path = Path(str(robot)).expanduser()
    if path.suffix.lower() in (".yaml", ".yml"):
        return path  # the config itself (it may name no MJCF: a servo bench, a bus on its own)
    return resolve(robot).require_hardware()


def load_config(path: str | Path, mjcf: str | Path | None = None, *, check_mjcf: bool = True) -> RobotConfig:
    """Read and validate a robot's hardware config.

    ``mjcf``: validate joints and limits against this MJCF; when None, the file's own
    ``mjcf`` key is used (resolved relative to the YAML file). ``check_mjcf=False``
    skips the MJCF check (e.g. on a machine without the robot description).
    """
    path = Path(path)
    if not path.is_file():
        from firmware_cfg.registry import bundled_names

        raise ConfigError(
            f"{path}: hardware config not found; give a robot's hardware.yaml, a robot folder "
            f"or a bundled robot ({', '.join(bundled_names())})"
        )
    try:
        data = yaml.safe_load(path.read_bytes().decode("utf-8"))
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc}); fix the syntax") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}); is it really a hardware.yaml?") from None
    except RecursionError:
        raise ConfigError(f"{path}: nested too deeply to be a hardware config; fix the syntax") from None
    return parse_config(data, source=str(path), base_dir=path.parent, mjcf=mjcf, check_mjcf=check_mjcf)


def parse_config(
    data: Any,
    *,
    source: str = "<config>",
    base_dir: Path | None = None,
    mjcf: str | Path | None = None,
    check_mjcf: bool = True,
) -> RobotConfig:
    """Validate an already-parsed config mapping (see :func:`load_config`)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: top level must be a mapping with keys robot, buses")
    _unknown(data, _TOP_KEYS, source, "")
    robot = data.get("robot")
    if not isinstance(robot, str) or not robot:
        raise ConfigError(f"{source}: robot: required, the robot's name (e.g. op3)")
    stop_policy = data.get("stop_policy", "hold")
    if stop_policy not in STOP_POLICIES:
        raise ConfigError(f"{source}: stop_policy: {stop_policy!r} is not one of {STOP_POLICIES}")
    top_defaults = _mapping(data.get("servo_defaults", {}), source, "servo_defaults")
    _unknown(top_defaults, _SERVO_KEYS - {"id", "joint"}, source, "servo_defaults")
    buses_raw = data.get("buses")
    if not isinstance(buses_raw, list) or not buses_raw:
        raise ConfigError(f"{source}: buses: required, a non-empty list of buses")

    buses = []
    for bi, braw in enumerate(buses_raw):
        buses.append(_parse_bus(braw, top_defaults, source, f"buses[{bi}]"))
    _check_unique([(b.name, f"buses[{i}].name") for i, b in enumerate(buses)], source, "bus name")
    _check_unique([(b.port, f"buses[{i}].port") for i, b in enumerate(buses)], source, "port")
    joints = [
        (s.joint, f"buses[{bi}].servos[{si}].joint") for bi, b in enumerate(buses) for si, s in enumerate(b.servos)
    ]
    _check_unique(joints, source, "joint")

    mjcf_path: Path | None = None
    if mjcf is not None:
        mjcf_path = Path(mjcf)
    elif data.get("mjcf") is not None:
        if not isinstance(data["mjcf"], str):
            raise ConfigError(f"{source}: mjcf: must be a path string")
        mjcf_path = Path(data["mjcf"])
        if not mjcf_path.is_absolute() and base_dir is not None:
            mjcf_path = (base_dir / mjcf_path).resolve()
    cfg = RobotConfig(robot, tuple(buses), stop_policy, source, mjcf_path)
    if check_mjcf and mjcf_path is not None:
        check_against_mjcf(cfg, mjcf_path)
    return cfg


def _parse_bus(braw: Any, top_defaults: dict, source: str, where: str) -> BusConfig:
    b = _mapping(braw, source, where)
    _unknown(b, _BUS_KEYS, source, where)
    name = b.get("name", where)
    port = b.get("port")
    if not isinstance(port, str) or not port:
        raise ConfigError(f"{source}: {where}.port: required, the serial device (e.g. /dev/ttyUSB0)")
    protocol = str(b.get("protocol", "2.0"))
    if protocol not in PROTOCOLS:
        raise ConfigError(f"{source}: {where}.protocol: {b.get('protocol')!r} is not one of {PROTOCOLS}")
    baud = b.get("baud")
    if not isinstance(baud, int) or isinstance(baud, bool) or baud <= 0:
        raise ConfigError(f"{source}: {where}.baud: required, a positive integer (e.g. 2000000)")
    defaults = dict(top_defaults)
    bus_defaults = _mapping(b.get("defaults", {}), source, f"{where}.defaults")
    _unknown(bus_defaults, _SERVO_KEYS - {"id", "joint"}, source, f"{where}.defaults")
    defaults.update(bus_defaults)
    servos_raw = b.get("servos")
    if not isinstance(servos_raw, list) or not servos_raw:
        raise ConfigError(f"{source}: {where}.servos: required, a non-empty list")
    servos = tuple(
        _parse_servo(
            {**defaults, **_mapping(s, source, f"{where}.servos[{i}]")}, protocol, baud, source, f"{where}.servos[{i}]"
        )
        for i, s in enumerate(servos_raw)
    )
    devices_raw = b.get("devices", [])
    if not isinstance(devices_raw, list):
        raise ConfigError(f"{source}: {where}.devices: must be a list of {{id, model, role}}")
    if devices_raw and protocol == "serial-link":
        raise ConfigError(f"{source}: {where}.devices: a serial-link bus has no devices; remove the list")
    devices = tuple(
        _parse_device(_mapping(d, source, f"{where}.devices[{i}]"), protocol, source, f"{where}.devices[{i}]")
        for i, d in enumerate(devices_raw)
    )
    _check_unique([(s.id, f"{where}.servos[{i}].id") for i, s in enumerate(servos)], source, "servo ID")
    _check_unique(
        [(s.id, f"{where}.servos[{i}].id") for i, s in enumerate(servos)]
        + [(d.id, f"{where}.devices[{i}].id") for i, d in enumerate(devices)],
        source,
        "bus ID",
    )
    return BusConfig(str(name), port, baud, protocol, servos, devices)


def _parse_device(d: dict, protocol: str, source: str, where: str) -> DeviceConfig:
    _unknown(d, _DEVICE_KEYS, source, where)
    did = d.get("id")
    if not _is_int(did) or not 0 <= did <= 252:
        raise ConfigError(f"{source}: {where}.id: {did!r} must be an integer 0..252")
    model = d.get("model")
    if not isinstance(model, str) or not model:
        raise ConfigError(f"{source}: {where}.model: required, the device's name (e.g. OpenCR)")
    known = device_models.find_device_model(model)
    if known is None:
        raise ConfigError(
            f"{source}: {where}.model: {model!r} is not a known device model; use one of "
            f"{device_models.device_model_names()} (firmware_cfg/device_models.py)"
        )
    if protocol != "serial-link" and float(protocol) != known.protocol:
        raise ConfigError(
            f"{source}: {where}.model: {known.name} speaks protocol {known.protocol}.0 but the bus is "
            f"{protocol}; put it on a protocol {known.protocol}.0 bus"
        )
    role = d.get("role")
    if role not in DEVICE_ROLES:
        raise ConfigError(f"{source}: {where}.role: {role!r} is not one of {DEVICE_ROLES}")
    if role == "imu" and known.imu is None:
        raise ConfigError(f"{source}: {where}.role: {known.name} has no IMU; use a device model with one")
    return DeviceConfig(did, known.name, role)


@dataclass(frozen=True)
class _Field:
    """Where a servo entry is (``source`` file, ``where`` path such as ``buses[0].servos[3]``);
    calling it with a key gives the prefix of an error message about that field."""

    source: str
    where: str

    def __call__(self, key: str) -> str:
        return f"{self.source}: {self.where}.{key}"


def _parse_servo(s: dict, protocol: str, baud: int, source: str, where: str) -> ServoConfig:
    """One servo entry (bus defaults already merged in) of a bus of ``protocol`` at ``baud``."""
    _unknown(s, _SERVO_KEYS, source, where)
    f = _Field(source, where)
    sid, joint, direction, zero, lower, upper = _parse_joint_mapping(s, protocol, f)
    if protocol == "serial-link":
        model = s.get("model")
        servo = ServoConfig(sid, joint, model if isinstance(model, str) else None, direction, zero, lower, upper)
        return _check_serial_link(s, servo, f)
    spec = _dynamixel_model(s.get("model"), protocol, baud, f)
    pid = _parse_pid(s.get("pid"), f)
    rd, srl, wd = _parse_bus_registers(s, protocol, f)
    pv, pa = _parse_profile(s, f)
    temp = _parse_temperature_limit(s.get("temperature_limit_c"), spec, f)
    volt = _parse_voltage_limits(s.get("voltage_limits_v"), spec, f)
    servo = ServoConfig(sid, joint, spec.name, direction, zero, lower, upper, pv, pa, pid, rd, srl, wd, temp, volt)
    _check_position_range(servo, spec, f)
    return servo


def _parse_joint_mapping(s: dict, protocol: str, f: _Field) -> tuple[int, str, int, float, float, float]:
    """(id, joint, direction, zero_offset rad, lower rad, upper rad), the fields every bus has."""
    sid = s.get("id")
    max_id = SERIAL_LINK_MAX_CHANNELS - 1 if protocol == "serial-link" else 252
    if not _is_int(sid) or not 0 <= sid <= max_id:
        raise ConfigError(f"{f('id')}: {sid!r} must be an integer 0..{max_id}")
    joint = s.get("joint")
    if not isinstance(joint, str) or not joint:
        raise ConfigError(f"{f('joint')}: required, the MJCF joint name this servo drives")
    direction = s.get("direction", 1)
    if direction not in (1, -1) or isinstance(direction, bool):
        raise ConfigError(f"{f('direction')}: {direction!r} must be 1 or -1")
    zero = _number(s.get("zero_offset", 0.0), f("zero_offset"))
    lim = s.get("limits")
    if not isinstance(lim, (list, tuple)) or len(lim) != 2:
        raise ConfigError(f"{f('limits')}: required, [lower, upper] in radians")
    lower, upper = (_number(v, f("limits")) for v in lim)
    if not lower < upper:
        raise ConfigError(f"{f('limits')}: lower {lower} must be below upper {upper}")
    return sid, joint, direction, zero, lower, upper


def _check_serial_link(s: dict, servo: ServoConfig, f: _Field) -> ServoConfig:
    """A serial-link channel has no Dynamixel fields, and its limits fit the link's int16
    centi-degrees; returns ``servo``."""
    extra = sorted(k for k in _DXL_ONLY if s.get(k) is not None)
    if extra:
        raise ConfigError(f"{f(extra[0])}: not used on a serial-link bus; remove it")
    lo, hi = servo.servo_limits()
    if lo < -SERIAL_LINK_RANGE_RAD or hi > SERIAL_LINK_RANGE_RAD:
        raise ConfigError(
            f"{f('limits')}: maps to servo angles [{lo:.3f}, {hi:.3f}] rad, outside the serial link's ±327.67°"
        )
    return servo


def _dynamixel_model(model: Any, protocol: str, baud: int, f: _Field) -> servo_models.ServoModel:
    """The servo model named by ``model``, checked against the bus's protocol and baud."""
    known = ", ".join(servo_models.servo_model_names())
    if not isinstance(model, str):
        raise ConfigError(f"{f('model')}: required on a Dynamixel bus; one of {known}")
    try:
        spec = servo_models.load_servo_model(model)
    except ConfigError:
        raise ConfigError(f"{f('model')}: unknown servo model {model!r}; known: {known}") from None
    if float(spec.protocol) != float(protocol):
        raise ConfigError(
            f"{f('model')}: {spec.name} speaks protocol {spec.protocol}.0, the bus is {protocol}; "
            "move it to a bus of its protocol"
        )
    if baud not in spec.baud_rates.values():
        raise ConfigError(
            f"{f('model')}: {spec.name} cannot run at the bus baud {baud}; "
            f"it supports {sorted(set(spec.baud_rates.values()))}"
        )
    return spec


def _parse_pid(raw: Any, f: _Field) -> PID | None:
    """``pid: {p, i, d}`` raw register gains 0..16383 (a missing gain is 0), or None."""
    if raw is None:
        return None
    p = _mapping(raw, f.source, f"{f.where}.pid")
    _unknown(p, {"p", "i", "d"}, f.source, f"{f.where}.pid")
    vals = {}
    for k in ("p", "i", "d"):
        v = p.get(k, 0)
        if not _is_int(v) or not 0 <= v <= 16383:
            raise ConfigError(f"{f('pid.' + k)}: {v!r} must be an integer register value 0..16383")
        vals[k] = v
    return PID(**vals)


def _parse_bus_registers(s: dict, protocol: str, f: _Field) -> tuple[int | None, int | None, int | None]:
    """(return_delay_us, status_return_level, bus_watchdog_ms), each None when not set."""
    rd = s.get("return_delay_us")
    if rd is not None and (not _is_int(rd) or not 0 <= rd <= 508 or rd % 2):
        raise ConfigError(f"{f('return_delay_us')}: {rd!r} must be an even integer 0..508 µs (register unit 2 µs)")
    srl = s.get("status_return_level")
    if srl is not None and srl not in (0, 1, 2):
        raise ConfigError(f"{f('status_return_level')}: {srl!r} must be 0, 1 or 2")
    if srl is not None and srl < 1:
        raise ConfigError(f"{f('status_return_level')}: 0 makes every READ unanswered; the bridge needs 1 or 2")
    wd = s.get("bus_watchdog_ms")
    if wd is not None and (not _is_int(wd) or not 0 <= wd <= 127 * 20 or wd % 20):
        raise ConfigError(f"{f('bus_watchdog_ms')}: {wd!r} must be a multiple of 20 ms in 0..2540 (0 = off)")
    if wd and protocol != "2.0":
        raise ConfigError(f"{f('bus_watchdog_ms')}: the bus watchdog exists on protocol 2.0 servos only; remove it")
    return rd, srl, wd


def _parse_profile(s: dict, f: _Field) -> tuple[float | None, float | None]:
    """(profile_velocity rad/s, profile_acceleration rad/s²), each >= 0 or None."""
    pv = s.get("profile_velocity")
    pv = None if pv is None else _number(pv, f("profile_velocity"))
    pa = s.get("profile_acceleration")
    pa = None if pa is None else _number(pa, f("profile_acceleration"))
    for key, val in (("profile_velocity", pv), ("profile_acceleration", pa)):
        if val is not None and val < 0:
            raise ConfigError(f"{f(key)}: {val} must be >= 0 (0 = no limit)")
    return pv, pa


def _parse_temperature_limit(temp: Any, spec: servo_models.ServoModel, f: _Field) -> int | None:
    """``temperature_limit_c`` (°C) within the model's register range, or None."""
    max_temp = spec.register("temperature_limit").range[1] if spec.has("temperature_limit") else 100
    if temp is not None and (not _is_int(temp) or not 0 < temp <= max_temp):
        raise ConfigError(f"{f('temperature_limit_c')}: {temp!r} must be an integer 1..{max_temp} °C for {spec.name}")
    return temp


def _parse_voltage_limits(volt: Any, spec: servo_models.ServoModel, f: _Field) -> tuple[float, float] | None:
    """``voltage_limits_v`` [min, max] (V) within what the model's registers accept, or None."""
    if volt is None:
        return None
    if not isinstance(volt, (list, tuple)) or len(volt) != 2:
        raise ConfigError(f"{f('voltage_limits_v')}: must be [min, max] volts")
    vmin, vmax = (_number(v, f("voltage_limits_v")) for v in volt)
    lo_v, hi_v = spec_voltage_range(spec)
    if not lo_v <= vmin < vmax <= hi_v:
        raise ConfigError(
            f"{f('voltage_limits_v')}: [{vmin}, {vmax}] V must satisfy {lo_v} <= min < max <= {hi_v} for {spec.name}"
        )
    return (vmin, vmax)


def _check_position_range(servo: ServoConfig, spec: servo_models.ServoModel, f: _Field) -> None:
    """The joint limits, mapped to the servo side, must lie in the model's position range."""
    lo, hi = servo.servo_limits()
    rmin, rmax = spec_angle_range(spec)
    if lo < rmin - 1e-9 or hi > rmax + 1e-9:
        raise ConfigError(
            f"{f('limits')}: [{servo.lower:.4f}, {servo.upper:.4f}] rad maps to servo angles [{lo:.4f}, {hi:.4f}] rad "
            f"(direction {servo.direction}, zero_offset {servo.zero_offset}), outside {spec.name}'s position range "
            f"[{rmin:.4f}, {rmax:.4f}]; narrow the limits or fix zero_offset"
        )


# ----------------------------------------------------------------------------- servo model views


def spec_angle_range(spec: servo_models.ServoModel) -> tuple[float, float]:
    """Servo-side angle range (rad) of position mode, relative to the centre tick:
    (tick - center) · 2π / ticks_per_turn at min_tick and max_tick."""
    return (spec.ticks_to_rad(spec.position.min_tick), spec.ticks_to_rad(spec.position.max_tick))


def spec_voltage_range(spec: servo_models.ServoModel) -> tuple[float, float]:
    """Volts the voltage-limit registers accept (register range × unit), else the rating."""
    if spec.has("min_voltage_limit") and spec.register("min_voltage_limit").range:
        lo = spec.register("min_voltage_limit").range[0] * spec.voltage_v
        hi = spec.register("max_voltage_limit").range[1] * spec.voltage_v
        return (round(lo, 3), round(hi, 3))
    return spec.ratings.voltage_range_v


# ----------------------------------------------------------------------------- MJCF


def mjcf_joint_ranges(mjcf: str | Path) -> dict[str, tuple[float, float] | None]:
    """Hinge joints of an MJCF → (lower, upper) in rad, or None when unlimited.

    Honours ``<compiler angle="degree|radian">`` (MuJoCo's default is degree), default
    classes (``class`` / ``childclass``, nested ``<default>``) for ``type``, ``range`` and
    ``limited``, and ``limited="auto"`` (limited when a range is given).
    """
    from firmware_cfg.registry import parse_mjcf

    path = Path(mjcf)
    if not path.is_file():
        raise ConfigError(
            f"{path}: MJCF not found; pass the robot's MJCF (firmware_cfg/robots/<robot>/) or skip the check"
        )
    root = parse_mjcf(path)
    comp = root.find("compiler")
    degree = (comp.get("angle", "degree") if comp is not None else "degree") == "degree"

    # default classes: name -> merged joint attributes (parents first)
    classes: dict[str, dict[str, str]] = {}

    def walk_defaults(node: ET.Element, inherited: dict[str, str], name: str) -> None:
        attrs = dict(inherited)
        j = node.find("joint")
        if j is not None:
            attrs.update(j.attrib)
        classes[name] = attrs
        for child in node.findall("default"):
            walk_defaults(child, attrs, child.get("class", name))

    top = root.find("default")
    classes["main"] = {}
    if top is not None:
        walk_defaults(top, {}, top.get("class", "main"))

    out: dict[str, tuple[float, float] | None] = {}

    def walk_body(node: ET.Element, childclass: str) -> None:
        for child in node:
            if child.tag == "body":
                walk_body(child, child.get("childclass", childclass))
            elif child.tag == "joint":
                attrs = dict(classes.get(child.get("class", childclass), classes["main"]))
                attrs.update(child.attrib)
                if attrs.get("type", "hinge") != "hinge" or "name" not in attrs:
                    continue
                rng = attrs.get("range")
                limited = attrs.get("limited", "auto")
                if rng is None or limited == "false":
                    out[attrs["name"]] = None
                    continue
                lo, hi = (float(v) for v in rng.split())
                if degree:
                    lo, hi = math.radians(lo), math.radians(hi)
                out[attrs["name"]] = (lo, hi)

    wb = root.find("worldbody")
    if wb is not None:
        walk_body(wb, "main")
    return out


def check_against_mjcf(cfg: RobotConfig, mjcf: str | Path) -> None:
    """Every configured joint exists in the MJCF and its limits lie inside the MJCF's range."""
    ranges = mjcf_joint_ranges(mjcf)
    for bi, bus in enumerate(cfg.buses):
        for si, s in enumerate(bus.servos):
            where = f"{cfg.source}: buses[{bi}].servos[{si}]"
            if s.joint not in ranges:
                raise ConfigError(
                    f"{where}.joint: {s.joint!r} is not a hinge joint of {mjcf}; "
                    f"its joints are {', '.join(ranges) or '(none)'}"
                )
            rng = ranges[s.joint]
            if rng is None:
                continue
            if s.lower < rng[0] - MJCF_TOLERANCE or s.upper > rng[1] + MJCF_TOLERANCE:
                raise ConfigError(
                    f"{where}.limits: [{s.lower:.4f}, {s.upper:.4f}] rad is wider than the MJCF range "
                    f"[{rng[0]:.4f}, {rng[1]:.4f}] of joint {s.joint!r} in {mjcf}; narrow it to fit"
                )


# ----------------------------------------------------------------------------- saving


def config_to_dict(cfg: RobotConfig) -> dict:
    """A plain mapping that :func:`parse_config` reads back to an equal config."""
    buses = []
    for b in cfg.buses:
        servos = []
        for s in b.servos:
            d: dict[str, Any] = {"id": s.id, "joint": s.joint}
            if s.model is not None:
                d["model"] = s.model
            d.update(direction=s.direction, zero_offset=float(s.zero_offset), limits=[float(s.lower), float(s.upper)])
            for key in (
                "profile_velocity",
                "profile_acceleration",
                "return_delay_us",
                "status_return_level",
                "bus_watchdog_ms",
                "temperature_limit_c",
            ):
                if getattr(s, key) is not None:
                    d[key] = getattr(s, key)
            if s.pid is not None:
                d["pid"] = {"p": s.pid.p, "i": s.pid.i, "d": s.pid.d}
            if s.voltage_limits_v is not None:
                d["voltage_limits_v"] = list(s.voltage_limits_v)
            servos.append(d)
        bus: dict[str, Any] = {"name": b.name, "port": b.port, "baud": b.baud, "protocol": b.protocol, "servos": servos}
        if b.devices:
            bus["devices"] = [{"id": d.id, "model": d.model, "role": d.role} for d in b.devices]
        buses.append(bus)
    out: dict[str, Any] = {"robot": cfg.robot}
    if cfg.mjcf is not None:
        out["mjcf"] = str(cfg.mjcf)
    out.update(stop_policy=cfg.stop_policy, buses=buses)
    return out


def save_config(cfg: RobotConfig, path: str | Path) -> Path:
    """Write ``cfg`` as YAML atomically (temp file, then rename)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False, default_flow_style=None))
    tmp.replace(path)
    return path


# ----------------------------------------------------------------------------- helpers


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _number(v: Any, field_name: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{field_name}: {v!r} must be a finite number")
    return float(v)


def _mapping(v: Any, source: str, where: str) -> dict:
    if not isinstance(v, dict):
        raise ConfigError(f"{source}: {where}: must be a mapping, got {type(v).__name__}")
    return v


def _unknown(d: dict, allowed: set[str], source: str, where: str) -> None:
    extra = sorted(set(d) - allowed)
    if extra:
        prefix = f"{where}." if where else ""
        raise ConfigError(f"{source}: {prefix}{extra[0]}: unknown field; allowed: {', '.join(sorted(allowed))}")


def _check_unique(items: list[tuple[Any, str]], source: str, what: str) -> None:
    seen: dict[Any, str] = {}
    for value, where in items:
        if value in seen:
            raise ConfigError(
                f"{source}: {where}: duplicate {what} {value!r} (also at {seen[value]}); each must be unique"
            )
        seen[value] = where
