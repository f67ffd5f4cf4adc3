"""Servo model tables: control-table registers, units and ratings, loaded from data.

Each model is one YAML file in ``firmware_cfg/servo_models/`` (numbers from the ROBOTIS
e-Manual); :func:`load_servo_model` validates it into a :class:`ServoModel` with register
lookups and rad <-> tick conversions. Depends on nothing else of this project (numpy and
PyYAML only). The file format and the position convention: docs/robots.md.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from firmware_cfg.errors import ConfigError

#: Folder holding one YAML file per servo model.
MODELS_DIR = Path(__file__).resolve().parent / "servo_models"

_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_ACCESS = ("R", "RW")
_AREAS = ("EEPROM", "RAM")
_RPM_TO_RAD_S = 2.0 * math.pi / 60.0

#: Relative baud-rate mismatch a UART still decodes (the e-Manual's tables list errors
#: of up to about 3 % as usable).
BAUD_TOLERANCE = 0.03


@dataclass(frozen=True)
class Register:
    """One control-table item. ``address`` and ``size`` in bytes; ``initial`` is the
    factory value (None where the e-Manual gives none); ``range`` is the inclusive
    range of values a write may carry (None: unchecked)."""

    name: str
    address: int
    size: int
    access: str
    area: str
    initial: int | None = None
    range: tuple[int, int] | None = None
    signed: bool = False
    sign_bit: int | None = None
    unit: str | None = None

    @property
    def end(self) -> int:
        """One past the last byte of this register."""
        return self.address + self.size

    @property
    def writable(self) -> bool:
        return self.access == "RW"

    @property
    def eeprom(self) -> bool:
        return self.area == "EEPROM"

    def encode(self, value: int) -> bytes:
        """Little-endian bytes for ``value`` (two's complement or sign-magnitude as declared)."""
        value = int(value)
        if self.sign_bit is not None:
            magnitude = min(abs(value), (1 << self.sign_bit) - 1)
            value = magnitude | ((1 << self.sign_bit) if value < 0 else 0)
        bits = 8 * self.size
        return (value & ((1 << bits) - 1)).to_bytes(self.size, "little")

    def decode(self, data: bytes) -> int:
        """Value of this register from its little-endian bytes."""
        raw = int.from_bytes(bytes(data[: self.size]), "little")
        if self.sign_bit is not None:
            magnitude = raw & ((1 << self.sign_bit) - 1)
            return -magnitude if raw & (1 << self.sign_bit) else magnitude
        if self.signed and raw & (1 << (8 * self.size - 1)):
            raw -= 1 << (8 * self.size)
        return raw

    def in_range(self, value: int) -> bool:
        return self.range is None or self.range[0] <= value <= self.range[1]


@dataclass(frozen=True)
class PositionSpec:
    """Encoder mapping: ``ticks_per_turn`` (4096 for X/MX; 1228.8 for AX, i.e. 1024 over 300°),
    the valid tick range and the tick that means 0 rad."""

    ticks_per_turn: float
    min_tick: int
    max_tick: int
    center_tick: int


@dataclass(frozen=True)
class Ratings:
    """Datasheet ratings at ``rated_voltage_v``: stall torque (N·m) and current (A), no-load speed (rpm)."""

    stall_torque_nm: float
    stall_current_a: float
    no_load_speed_rpm: float
    rated_voltage_v: float
    voltage_range_v: tuple[float, float]


@dataclass(frozen=True)
class ServoModel:
    """One servo model: its control table, units, ratings and baud-rate table."""

    name: str
    model_number: int
    protocol: int
    firmware_version: int
    position: PositionSpec
    ratings: Ratings
    registers: Mapping[str, Register]
    baud_rates: Mapping[int, int]
    velocity_rpm: float
    voltage_v: float
    temperature_c: float
    return_delay_us: float
    current_ma: float | None = None
    load_percent: float | None = None
    source: str = ""
    _by_address: Mapping[int, Register] = field(default_factory=dict, repr=False, compare=False)

    # ---------------------------------------------------------------- lookups
    def register(self, name: str) -> Register:
        """The register called ``name``; a ConfigError lists the known names otherwise."""
        try:
            return self.registers[name]
        except KeyError:
            raise ConfigError(
                f"servo model {self.name}: no register named {name!r} (known: {', '.join(sorted(self.registers))})"
            ) from None

    def has(self, name: str) -> bool:
        return name in self.registers

    def first_register(self, *names: str) -> Register:
        """The first of ``names`` this model has (e.g. 'present_input_voltage', 'present_voltage')."""
        for name in names:
            if name in self.registers:
                return self.registers[name]
        raise ConfigError(f"servo model {self.name}: has none of the registers {', '.join(names)}")

    def register_at(self, address: int) -> Register | None:
        """The register starting at ``address``, or None."""
        return self._by_address.get(address)

    def registers_in(self, start: int, end: int) -> list[Register]:
        """Registers overlapping the byte span [start, end), in address order."""
        cover = self._cover
        out: list[Register] = []
        for a in range(max(start, 0), min(end, len(cover))):
            r = cover[a]
            if r is not None and (not out or out[-1] is not r):
                out.append(r)
        return out

    @property
    def _cover(self) -> tuple[Register | None, ...]:
        """For each byte address, the register covering it (None in gaps); built once."""
        cover = self.__dict__.get("_cover_cache")
        if cover is None:
            table = [None] * self.table_size
            for r in self._by_address.values():
                for a in range(r.address, r.end):
                    table[a] = r
            cover = tuple(table)
            object.__setattr__(self, "_cover_cache", cover)
        return cover

    @property
    def table_size(self) -> int:
        """Bytes of control table the listed registers span (0 .. last register's end)."""
        return max(r.end for r in self.registers.values())

    # ---------------------------------------------------------------- units
    @property
    def ticks_per_rad(self) -> float:
        return self.position.ticks_per_turn / (2.0 * math.pi)

    def rad_to_ticks(self, rad: Any, direction: int = 1, offset_ticks: int = 0) -> Any:
        """tick = center + direction * rad * ticks_per_turn / (2 pi) + offset, rounded to int.

        Scalars give an int, arrays an int64 array. No clipping: the caller checks limits."""
        ticks = self.position.center_tick + direction * np.asarray(rad, dtype=float) * self.ticks_per_rad + offset_ticks
        out = np.rint(ticks).astype(np.int64)
        return int(out) if out.ndim == 0 else out

    def ticks_to_rad(self, ticks: Any, direction: int = 1, offset_ticks: int = 0) -> Any:
        """Inverse of :meth:`rad_to_ticks`: rad = direction * (tick - center - offset) * 2 pi / ticks_per_turn."""
        rad = (
            direction * (np.asarray(ticks, dtype=float) - self.position.center_tick - offset_ticks) / self.ticks_per_rad
        )
        return float(rad) if np.ndim(rad) == 0 else rad

    def velocity_to_rad_s(self, units: Any) -> Any:
        """Velocity register units → rad/s (units * velocity_rpm * 2 pi / 60)."""
        return np.asarray(units, dtype=float) * self.velocity_rpm * _RPM_TO_RAD_S

    def rad_s_to_velocity(self, rad_s: Any) -> Any:
        """rad/s → velocity register units (rounded)."""
        out = np.rint(np.asarray(rad_s, dtype=float) / (self.velocity_rpm * _RPM_TO_RAD_S)).astype(np.int64)
        return int(out) if out.ndim == 0 else out

    def current_to_amps(self, units: Any) -> Any:
        """Current register units → A; a ConfigError for models that only report load."""
        if self.current_ma is None:
            raise ConfigError(f"servo model {self.name} has no current sensing (it reports load in %)")
        return np.asarray(units, dtype=float) * self.current_ma / 1000.0

    def amps_to_current(self, amps: Any) -> Any:
        if self.current_ma is None:
            raise ConfigError(f"servo model {self.name} has no current sensing (it reports load in %)")
        out = np.rint(np.asarray(amps, dtype=float) * 1000.0 / self.current_ma).astype(np.int64)
        return int(out) if out.ndim == 0 else out

    def voltage_to_volts(self, units: Any) -> Any:
        return np.asarray(units, dtype=float) * self.voltage_v

    def temperature_to_celsius(self, units: Any) -> Any:
        return np.asarray(units, dtype=float) * self.temperature_c

    def return_delay_s(self, units: int) -> float:
        """Return Delay Time register value → seconds (2 µs per unit)."""
        return units * self.return_delay_us * 1e-6

    @property
    def no_load_speed_rad_s(self) -> float:
        return self.ratings.no_load_speed_rpm * _RPM_TO_RAD_S

    @property
    def torque_constant_nm_per_a(self) -> float:
        """Stall torque / stall current (N·m/A), a rough linear torque constant."""
        return self.ratings.stall_torque_nm / self.ratings.stall_current_a

    # ---------------------------------------------------------------- baud
    def baud_to_register(self, baud: int) -> int:
        """Baud Rate register value for ``baud`` bps: the listed rate nearest to it within
        :data:`BAUD_TOLERANCE` (protocol 1.0 rates are 2 Mbps / (value + 1), so 57600 bps
        maps to 57142); ConfigError if the model has none that close."""
        value, bps = min(self.baud_rates.items(), key=lambda kv: abs(kv[1] - baud))
        if abs(bps - baud) <= BAUD_TOLERANCE * baud:
            return value
        raise ConfigError(
            f"servo model {self.name} does not support {baud} bps "
            f"(supported: {', '.join(str(b) for b in sorted(set(self.baud_rates.values())))})"
        )

    def register_to_baud(self, value: int) -> int:
        """Bits per second for Baud Rate register ``value`` (protocol 1.0: 2 Mbps / (value + 1))."""
        if value in self.baud_rates:
            return self.baud_rates[value]
        if self.protocol == 1 and 0 <= value < 250:
            return round(2_000_000 / (value + 1))
        raise ConfigError(f"servo model {self.name}: Baud Rate value {value} is not defined")


# ------------------------------------------------------------------------- loading


def _need(data: Mapping, key: str, where: str, kind: type | tuple[type, ...]) -> Any:
    if key not in data:
        raise ConfigError(f"{where}: missing field '{key}'")
    value = data[key]
    if not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool):
        raise ConfigError(f"{where}: field '{key}' must be a {getattr(kind, '__name__', kind)}, got {value!r}")
    return value


def _parse_register(name: str, spec: Any, where: str) -> Register:
    where = f"{where}: registers.{name}"
    if not isinstance(spec, dict):
        raise ConfigError(f"{where}: must be a mapping with address, size, access, area")
    unknown = set(spec) - {"address", "size", "access", "area", "initial", "range", "signed", "sign_bit", "unit"}
    if unknown:
        raise ConfigError(f"{where}: unknown field(s) {sorted(unknown)}")
    address = _need(spec, "address", where, int)
    size = _need(spec, "size", where, int)
    if address < 0 or size not in (1, 2, 4):
        raise ConfigError(f"{where}: address must be >= 0 and size 1, 2 or 4 (got {address}, {size})")
    access = _need(spec, "access", where, str)
    if access not in _ACCESS:
        raise ConfigError(f"{where}: access must be one of {_ACCESS}, got {access!r}")
    area = _need(spec, "area", where, str)
    if area not in _AREAS:
        raise ConfigError(f"{where}: area must be one of {_AREAS}, got {area!r}")
    rng = spec.get("range")
    if rng is not None:
        if not (isinstance(rng, list) and len(rng) == 2 and all(isinstance(v, int) for v in rng) and rng[0] <= rng[1]):
            raise ConfigError(f"{where}: range must be [lo, hi] integers with lo <= hi, got {rng!r}")
        rng = (rng[0], rng[1])
    initial = spec.get("initial")
    if initial is not None and not isinstance(initial, int):
        raise ConfigError(f"{where}: initial must be an integer, got {initial!r}")
    unit = spec.get("unit")
    return Register(
        name,
        address,
        size,
        access,
        area,
        initial,
        rng,
        bool(spec.get("signed", False)),
        spec.get("sign_bit"),
        None if unit is None else str(unit),
    )


def parse_servo_model(data: Any, source: str) -> ServoModel:
    """Validate one model's parsed YAML; errors name ``source`` and the field."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: must be a YAML mapping")
    name = _need(data, "name", source, str)
    number = _need(data, "model_number", source, int)
    protocol = _need(data, "protocol", source, int)
    if protocol not in (1, 2):
        raise ConfigError(f"{source}: protocol must be 1 or 2, got {protocol}")
    pos = _need(data, "position", source, dict)
    units = _need(data, "units", source, dict)
    rat = _need(data, "ratings", source, dict)
    try:
        position = PositionSpec(
            float(pos["ticks_per_turn"]), int(pos["min_tick"]), int(pos["max_tick"]), int(pos["center_tick"])
        )
        ratings = Ratings(
            float(rat["stall_torque_nm"]),
            float(rat["stall_current_a"]),
            float(rat["no_load_speed_rpm"]),
            float(rat["rated_voltage_v"]),
            tuple(float(v) for v in rat["voltage_range_v"]),
        )
        velocity_rpm = float(units["velocity_rpm"])
        voltage_v = float(units["voltage_v"])
        temperature_c = float(units["temperature_c"])
        return_delay_us = float(units["return_delay_us"])
    except KeyError as exc:
        raise ConfigError(f"{source}: missing field {exc.args[0]!r} in position/units/ratings") from None
    if not position.min_tick <= position.center_tick <= position.max_tick:
        raise ConfigError(f"{source}: position.center_tick must lie within [min_tick, max_tick]")
    bauds = _need(data, "baud_rates", source, dict)
    regs_raw = _need(data, "registers", source, dict)
    registers = {key: _parse_register(key, spec, source) for key, spec in regs_raw.items()}
    ordered = sorted(registers.values(), key=lambda r: r.address)
    for a, b in zip(ordered, ordered[1:]):
        if b.address < a.end:
            raise ConfigError(f"{source}: registers {a.name} ({a.address}+{a.size}) and {b.name} ({b.address}) overlap")
    for needed in ("model_number", "id", "torque_enable", "goal_position", "present_position", "return_delay_time"):
        if needed not in registers:
            raise ConfigError(f"{source}: registers must include '{needed}'")
    if registers["model_number"].initial != number:
        raise ConfigError(
            f"{source}: registers.model_number.initial ({registers['model_number'].initial}) != model_number ({number})"
        )
    return ServoModel(
        name=name,
        model_number=number,
        protocol=protocol,
        firmware_version=int(data.get("firmware_version", 0)),
        position=position,
        ratings=ratings,
        registers=registers,
        baud_rates={int(k): int(v) for k, v in bauds.items()},
        velocity_rpm=velocity_rpm,
        voltage_v=voltage_v,
        temperature_c=temperature_c,
        return_delay_us=return_delay_us,
        current_ma=None if units.get("current_ma") is None else float(units["current_ma"]),
        load_percent=None if units.get("load_percent") is None else float(units["load_percent"]),
        source=source,
        _by_address={r.address: r for r in ordered},
    )


def load_servo_model_file(path: str | Path) -> ServoModel:
    """Load and validate one model file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read servo model file ({exc.strerror})") from None
    try:
        data = yaml.load(text, Loader=_SAFE_LOADER)  # safe loader (libyaml's when present)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from None
    return parse_servo_model(data, str(path))


@cache
def _bundled() -> tuple[ServoModel, ...]:
    return tuple(load_servo_model_file(p) for p in sorted(MODELS_DIR.glob("*.yaml")))


def all_servo_models() -> tuple[ServoModel, ...]:
    """Every bundled model, in file-name order."""
    return _bundled()


def servo_model_names() -> list[str]:
    return [m.name for m in _bundled()]


def load_servo_model(key: str | int, protocol: int | None = None) -> ServoModel:
    """A bundled model by name (case-insensitive, e.g. 'xm430-w350') or model number
    (e.g. 1020). ``protocol`` disambiguates numbers shared across protocols."""
    models = _bundled()
    if isinstance(key, str) and not key.strip().isdigit():
        wanted = key.strip().upper()
        for m in models:
            if m.name.upper() == wanted:
                return m
        raise ConfigError(f"unknown servo model {key!r} (known: {', '.join(servo_model_names())})")
    number = int(key)
    hits = [m for m in models if m.model_number == number and (protocol is None or m.protocol == protocol)]
    if not hits:
        known = ", ".join(f"{m.name}={m.model_number}" for m in models)
        raise ConfigError(f"unknown servo model number {number} (known: {known})")
    return hits[0]
