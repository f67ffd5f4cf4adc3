"""``dualflow-bridge servo ACTION``: set up and inspect Dynamixel servo buses.

Actions scan, provision, verify, calibrate, monitor and emulate, each a ``run_*`` function
(what each does: :data:`DESCRIPTION`, the command's help). Errors are ConfigError or
BridgeError, which the command line turns into one message and exit 2; ``verify`` exits 1
on a mismatch.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from pathlib import Path

from firmware_cfg.errors import ConfigError
from ros_free_bridge.errors import BridgeError

#: The ``servo --help`` text: what each action does.
DESCRIPTION = """``dualflow-bridge servo scan|provision|verify|calibrate|monitor|emulate``: set up and
inspect Dynamixel servo buses.

- ``scan``: ping IDs across baud rates and protocols; print each servo's model and firmware.
- ``provision CONFIG``: write each servo's EEPROM/RAM settings from the robot's hardware
  config with torque off, read them back and print the diff; refuses (writes nothing)
  when a servo's model differs from the config.
- ``verify CONFIG``: compare models and EEPROM settings with the config, report hardware
  errors; exit 1 on a mismatch. (RAM settings - gains, profiles, bus watchdog - reset at
  power-off; the Dynamixel transport applies them whenever it opens the bus.)
- ``calibrate CONFIG --out FILE``: with the robot held in its zero pose, record each
  servo's zero offset into a new config file.
- ``monitor CONFIG``: a live table of positions, velocities, currents, temperatures,
  voltages and hardware errors.
- ``emulate CONFIG``: start an emulated bus with the config's servos on a pseudo-terminal
  and print its port, for trying everything above without hardware.

Every action but ``emulate`` takes ``--port`` (default: the config's bus port) and
``--emulate`` (run against an emulated bus started in-process from the config, e.g.
``dualflow-bridge servo provision op3 --emulate``).
"""

#: Baud rates ``scan`` tries by default (those both the SDK and the bundled models know).
SCAN_BAUDS = (57600, 115200, 1000000, 2000000, 3000000, 4000000, 9600, 500000)


def register(subparsers) -> None:
    """Add ``servo`` and its actions to the command line's ``subparsers``."""
    p = subparsers.add_parser(
        "servo",
        help="scan, provision, verify, calibrate and monitor Dynamixel servos",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="servo_command", metavar="ACTION")
    for add in (_add_scan, _add_provision, _add_verify, _add_calibrate, _add_monitor, _add_emulate):
        add(sub)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
    for name, action in sub.choices.items():
        action.set_defaults(func=_with_robot(action.get_default("func"), required=name != "scan"))


def _add_bus_options(q) -> None:
    """The robot, and which bus to talk to and how: the options the config-driven actions share."""
    add_robot_arguments(q)
    q.add_argument("--port", help="serial device (default: the config's bus port)")
    q.add_argument("--bus", help="bus name in the config (default: the only Dynamixel bus)")
    q.add_argument("--emulate", action="store_true", help="use an emulated bus started from the config (no hardware)")
    q.add_argument("--retries", type=int, default=2, help="retries per packet (default 2)")


def _add_scan(sub) -> None:
    s = sub.add_parser(
        "scan",
        help="find servos: ping IDs across baud rates and protocols",
        description="Ping every ID at each baud rate and protocol (2.0 by broadcast ping, 1.0 one ID "
        "at a time) and print each servo found: ID, model, firmware, baud, protocol. "
        "Reads only; use it first on a new bus, or when a servo does not answer.",
    )
    add_robot_arguments(
        s, "with --emulate: the robot whose servos to emulate (a bundled name, a robot folder or its hardware.yaml)"
    )
    s.add_argument("--port", help="serial device (e.g. /dev/ttyUSB0)")
    s.add_argument("--bus", help="bus name in the config")
    s.add_argument("--emulate", action="store_true", help="scan an emulated bus started from CONFIG")
    s.add_argument(
        "--bauds",
        default=",".join(str(b) for b in SCAN_BAUDS),
        help=f"comma-separated baud rates to try, in order (default {','.join(str(b) for b in SCAN_BAUDS)})",
    )
    s.add_argument("--protocols", default="2,1", help="protocols to try: 2,1 (default), 2 or 1")
    s.add_argument(
        "--ids", default="0-252", help="ID range for protocol 1.0 unicast pings, e.g. 0-30 (2.0 uses broadcast ping)"
    )
    s.add_argument(
        "--latency-ms",
        type=float,
        default=4.0,
        help="reply latency allowed per ping, ms (default 4; the timeout adds the bytes' time and 3 ms)",
    )
    s.set_defaults(func=run_scan)


def _add_provision(sub) -> None:
    s = sub.add_parser(
        "provision",
        help="write EEPROM/RAM settings from CONFIG (torque off), read back, show the diff",
        description="Make each servo on the bus match CONFIG: switch torque off, write the EEPROM "
        "settings (return delay, temperature and voltage limits, position limits from the joint limits) "
        "and RAM settings (status return level, PID gains, profiles, bus watchdog), "
        "read everything back and print what changed. Writes nothing when a servo's "
        "model differs from the config. Run once per new servo, with the robot "
        "supported (torque goes off).",
    )
    _add_bus_options(s)
    s.add_argument("--dry-run", action="store_true", help="show the diff only; write nothing")
    s.set_defaults(func=run_provision)


def _add_verify(sub) -> None:
    s = sub.add_parser(
        "verify",
        help="check models and settings against CONFIG (exit 1 on a mismatch)",
        description="Read each servo's model and EEPROM settings and compare them with CONFIG, "
        "and its hardware error flags. Reads only. Exit code 0 when everything matches "
        "and no flag is set, 1 otherwise (a settings mismatch: run `servo provision`).",
    )
    _add_bus_options(s)
    s.set_defaults(func=run_verify)


def _add_calibrate(sub) -> None:
    s = sub.add_parser(
        "calibrate",
        help="record zero offsets with the robot held in its zero pose",
        description="With the robot held in its zero pose (the MJCF's zero: every joint at 0 rad), "
        "read each servo's position several times and write a copy of CONFIG with "
        "those zero offsets to --out. Torque is switched off first (unless "
        "--keep-torque), so support the robot.",
    )
    _add_bus_options(s)
    s.add_argument("--out", required=True, help="where to write the calibrated config (YAML)")
    s.add_argument("--samples", type=int, default=10, help="readings averaged per servo (default 10)")
    s.add_argument("--joints", help="comma-separated joints to calibrate (default: all on the bus)")
    s.add_argument("--keep-torque", action="store_true", help="do not switch torque off before reading")
    s.set_defaults(func=run_calibrate)


def _add_monitor(sub) -> None:
    s = sub.add_parser(
        "monitor",
        help="live table of positions, temperatures, voltages and errors",
        description="A live table, one row per servo: position, velocity, current, temperature, "
        "input voltage and hardware error flags, refreshed --rate times a second. "
        "Reads only; torque is left as it is.",
    )
    _add_bus_options(s)
    s.add_argument("--rate", type=float, default=5.0, help="table refreshes per second (default 5)")
    s.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    s.add_argument("--once", action="store_true", help="print one table and exit")
    s.set_defaults(func=run_monitor)


def _add_emulate(sub) -> None:
    s = sub.add_parser(
        "emulate",
        help="start an emulated bus from CONFIG on a pty and print its port",
        description="Start a byte-level emulation of CONFIG's bus on a pseudo-terminal (its "
        "servos in the bus's protocol, with their registers and a motor model; a "
        "serial-link bus gets an emulated DFSL board) and print its device path; point --port "
        "of the other servo actions, or `run --transport dynamixel`, at it to try them "
        "without hardware.",
    )
    add_robot_arguments(s)
    s.add_argument("--bus", help="bus name in the config (a serial-link bus starts an emulated DFSL board)")
    s.add_argument("--provisioned", action="store_true", help="servos start with the config's settings (verify passes)")
    s.add_argument("--wire-timing", action="store_true", help="delay replies by their time on the wire")
    s.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    s.set_defaults(func=run_emulate)


def _with_robot(func, required: bool):
    """Let each action read ``args.config`` whichever way the robot was given."""

    def run(args):
        args.config = robot_argument(args, required=required)
        return func(args)

    return run


# ----------------------------------------------------------------------------- shared

ROBOT_HELP = "the robot: a bundled name (op3), a robot folder, or its hardware config .yaml"


def add_robot_arguments(q, help_text: str = ROBOT_HELP) -> None:
    """The robot as a positional CONFIG (as before) or as ``--robot NAME|DIR``, like every command."""
    q.add_argument("config", nargs="?", metavar="ROBOT", help=help_text)
    q.add_argument("--robot", dest="robot_option", metavar="NAME|DIR", help=f"{help_text} (same as the positional)")


def robot_argument(args, required: bool = True) -> str | None:
    ref = getattr(args, "robot_option", None) or getattr(args, "config", None)
    if getattr(args, "robot_option", None) and getattr(args, "config", None) and args.robot_option != args.config:
        raise BridgeError(f"give the robot once: positional {args.config!r} and --robot {args.robot_option!r} differ")
    if ref is None and required:
        raise BridgeError(
            "servo: which robot? give a bundled name (op3), a robot folder or a hardware config, "
            "positionally or with --robot"
        )
    return ref


def load_robot_config(ref: str):
    """The hardware config of a robot reference (a bundled name such as ``op3``, a robot folder
    or the config file itself), through the robot registry."""
    from firmware_cfg.config import load_config, robot_config_path

    return load_config(robot_config_path(ref))


def dynamixel_bus_of(cfg, name: str | None):
    if name is not None:
        bus = cfg.bus(name)
    else:
        dxl = [b for b in cfg.buses if b.protocol in ("1.0", "2.0")]
        if len(dxl) != 1:
            raise ConfigError(
                f"{cfg.source}: {len(dxl)} Dynamixel buses; choose one with --bus "
                f"({', '.join(b.name for b in dxl) or 'none'})"
            )
        bus = dxl[0]
    if bus.protocol == "serial-link":
        raise BridgeError(f"bus {bus.name!r} is a serial link; the servo commands work on Dynamixel buses")
    return bus


def start_emulator(bus, *, provisioned: bool = False, wire_timing: bool = False):
    """A :class:`DynamixelBusEmulator` with the bus's servos (IDs and models) and devices
    (e.g. the OP3's OpenCR IMU), started. ``provisioned``: the servos' control tables
    already hold the config's settings."""
    from firmware_cfg.servo_models import load_servo_model
    from ros_free_bridge.dynamixel.servos import servo_register_settings
    from ros_free_bridge.emulators import DynamixelBusEmulator, ServoSpec

    specs = [ServoSpec(s.id, s.model) for s in bus.servos] + [ServoSpec(d.id, d.model) for d in bus.devices]
    emu = DynamixelBusEmulator(
        servos=specs, baud=bus.baud, protocol=int(float(bus.protocol)), wire_timing=wire_timing, return_delay_us=None
    ).start()
    if provisioned:
        for s in bus.servos:
            for name, value in servo_register_settings(s, load_servo_model(s.model)).items():
                emu.write_register(s.id, name, value)
    return emu


@contextlib.contextmanager
def open_bus(args, bus):
    """(DynamixelBus, emulator or None) for the command's port or its emulator."""
    from ros_free_bridge.dynamixel.bus import DynamixelBus

    emu = start_emulator(bus) if getattr(args, "emulate", False) else None
    try:
        port = emu.port_path if emu is not None else (args.port or bus.port)
        dxl = DynamixelBus(
            port, bus.baud, bus.protocol_version, retries=args.retries, names={s.id: s.joint for s in bus.servos}
        )
        with dxl:
            yield dxl, emu
    finally:
        if emu is not None:
            emu.stop()


def check_models(dxl, bus) -> list[tuple[object, object, int]]:
    """Ping every servo; BridgeError listing every missing servo or model mismatch."""
    from firmware_cfg.servo_models import load_servo_model

    problems, found = [], []
    for s in bus.servos:
        model = load_servo_model(s.model)
        try:
            number = dxl.ping(s.id)
        except BridgeError as exc:
            problems.append(str(exc))
            continue
        if number != model.model_number:
            try:
                other = load_servo_model(number, protocol=model.protocol).name
            except ConfigError:
                other = "not in the model table"
            problems.append(
                f"{dxl.label(s.id)}: model number {number} ({other}), config says {model.name} ({model.model_number})"
            )
            continue
        fw = dxl.read(s.id, model.register("firmware_version"))[0] if model.has("firmware_version") else -1
        found.append((s, model, fw))
    if problems:
        raise BridgeError(
            "refusing: " + "; ".join(problems) + ". Fix the wiring or the config (scan shows what is on the bus)"
        )
    return found


def read_settings(dxl, servo, model, eeprom_only: bool = False) -> tuple[dict[str, int], dict[str, int]]:
    """(wanted, present) register values for one servo (``eeprom_only``: the persistent
    ones; RAM settings reset at power-off and the transport applies them at open)."""
    from ros_free_bridge.dynamixel.servos import servo_register_settings

    wanted = servo_register_settings(servo, model)
    if eeprom_only:
        wanted = {k: v for k, v in wanted.items() if model.register(k).eeprom}
    present = {name: dxl.read(servo.id, model.register(name))[0] for name in wanted}
    return wanted, present


def print_table(rows: list[list[str]], header: list[str], out=None) -> None:
    out = out or sys.stdout
    widths = [max(len(str(r[i])) for r in rows + [header]) for i in range(len(header))]
    print("  ".join(str(h).ljust(w) for h, w in zip(header, widths)), file=out)
    for r in rows:
        print("  ".join(str(c).ljust(w) for c, w in zip(r, widths)), file=out)


# ----------------------------------------------------------------------------- scan


def _parse_ids(text: str) -> list[int]:
    ids: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part:
            a, b = part.split("-", 1)
            ids += list(range(int(a), int(b) + 1))
        elif part:
            ids.append(int(part))
    if not ids or min(ids) < 0 or max(ids) > 253:
        raise BridgeError(f"--ids {text!r}: give IDs 0..253 as e.g. 0-30 or 1,2,5")
    return ids


def run_scan(args) -> int:
    from firmware_cfg.servo_models import all_servo_models
    from ros_free_bridge.dynamixel.bus import DynamixelBus

    try:
        bauds = [int(b) for b in args.bauds.split(",") if b.strip()]
        protocols = [int(p) for p in args.protocols.split(",") if p.strip()]
    except ValueError:
        raise BridgeError(
            "--bauds and --protocols take comma-separated integers, e.g. --bauds 57600,1000000 --protocols 2,1"
        ) from None
    if not set(protocols) <= {1, 2}:
        raise BridgeError(f"--protocols {args.protocols!r}: use 2, 1 or 2,1")
    ids = _parse_ids(args.ids)
    emu = None
    if args.emulate:
        if not args.config:
            raise BridgeError("scan --emulate needs CONFIG, the robot whose servos to emulate")
        emu = start_emulator(dynamixel_bus_of(load_robot_config(args.config), args.bus))
        port = emu.port_path
    elif args.port:
        port = args.port
    elif args.config:
        port = dynamixel_bus_of(load_robot_config(args.config), args.bus).port
    else:
        raise BridgeError("scan: give --port (e.g. /dev/ttyUSB0), a CONFIG, or --emulate CONFIG")
    from firmware_cfg.device_models import DEVICE_MODELS

    known = {(m.model_number, m.protocol): m for m in (*all_servo_models(), *DEVICE_MODELS)}
    rows = []
    try:
        for protocol in protocols:
            for baud in bauds:
                print(f"protocol {protocol}.0 at {baud} bps ...", file=sys.stderr, flush=True)
                dxl = DynamixelBus(port, baud, float(protocol), retries=0, latency_ms=args.latency_ms)
                with dxl:
                    if protocol == 2:
                        found, result = dxl.call(dxl.ph.broadcastPing)
                        hits = sorted((sid, info[0], info[1]) for sid, info in (found or {}).items())
                    else:
                        hits = []
                        for sid in ids:
                            for _try in range(2):  # one retry: a missed reply must not hide a servo
                                model, result, _ = dxl.call(dxl.ph.ping, sid)
                                if result == 0:
                                    hits.append((sid, model, None))
                                    break
                    for sid, number, fw in hits:
                        m = known.get((number, protocol))
                        if fw is None and m is not None and "firmware_version" in m.registers:
                            try:
                                fw = dxl.read(sid, m.register("firmware_version"))[0]
                            except BridgeError:
                                fw = None
                        rows.append(
                            [
                                f"{protocol}.0",
                                str(baud),
                                str(sid),
                                str(number),
                                m.name if m else "unknown",
                                "?" if fw is None else str(fw),
                            ]
                        )
    finally:
        if emu is not None:
            emu.stop()
    if not rows:
        print(f"no servo answered on {port} (protocols {args.protocols}, bauds {args.bauds})")
        return 1
    print_table(rows, ["protocol", "baud", "id", "model#", "model", "firmware"])
    return 0


# ----------------------------------------------------------------------------- provision / verify


def run_provision(args) -> int:
    cfg = load_robot_config(args.config)
    bus = dynamixel_bus_of(cfg, args.bus)
    with open_bus(args, bus) as (dxl, _emu):
        servos = check_models(dxl, bus)
        rows, changes = [], 0
        for s, model, _fw in servos:
            wanted, present = read_settings(dxl, s, model)
            diff = {k: v for k, v in wanted.items() if present[k] != v}
            for k, v in wanted.items():
                if k in diff:
                    rows.append([str(s.id), s.joint, k, str(present[k]), str(v)])
            if not diff or args.dry_run:
                continue
            torque = model.register("torque_enable")
            if dxl.read(s.id, torque)[0]:
                print(f"{dxl.label(s.id)}: torque off to unlock EEPROM", file=sys.stderr)
                dxl.write(s.id, torque, 0)
            for name, value in diff.items():  # EEPROM first, then RAM
                reg = model.register(name)
                if reg.eeprom:
                    dxl.write(s.id, reg, value)
            for name, value in diff.items():
                reg = model.register(name)
                if not reg.eeprom:
                    dxl.write(s.id, reg, value)
            _, after = read_settings(dxl, s, model)
            bad = {k: (after[k], v) for k, v in wanted.items() if after[k] != v}
            if bad:
                raise BridgeError(
                    f"{dxl.label(s.id)}: read-back differs after writing: "
                    + ", ".join(f"{k} = {a} (wanted {w})" for k, (a, w) in bad.items())
                )
            changes += len(diff)
        if rows:
            print_table(rows, ["id", "joint", "register", "was", "now" if not args.dry_run else "wanted"])
        verb = "would change" if args.dry_run else "changed"
        print(
            f"{verb} {sum(1 for _ in rows)} register(s) on {len(servos)} servo(s); "
            f"{'read back and verified' if not args.dry_run else 'nothing written (--dry-run)'}"
        )
        if not args.dry_run:
            print(
                "note: RAM settings (gains, profiles, watchdog) are lost at power-off; "
                "the bridge re-applies them at start"
            )
    return 0


def run_verify(args) -> int:
    cfg = load_robot_config(args.config)
    bus = dynamixel_bus_of(cfg, args.bus)
    with open_bus(args, bus) as (dxl, _emu):
        servos = check_models(dxl, bus)
        rows, bad = [], 0
        for s, model, fw in servos:
            wanted, present = read_settings(dxl, s, model, eeprom_only=True)
            diff = [f"{k}={present[k]} (want {v})" for k, v in wanted.items() if present[k] != v]
            hw = ""
            if model.has("hardware_error_status"):
                from ros_free_bridge.dynamixel.protocol import decode_hardware_error

                bits = dxl.read(s.id, model.register("hardware_error_status"))[0]
                hw = ", ".join(decode_hardware_error(bits))
            bad += bool(diff) or bool(hw)
            rows.append([str(s.id), s.joint, model.name, str(fw), "ok" if not diff else "; ".join(diff), hw or "-"])
        print_table(rows, ["id", "joint", "model", "firmware", "settings", "hardware error"])
    if bad:
        print(f"{bad} servo(s) differ from {cfg.source}; run `dualflow-bridge servo provision {args.config}`")
        return 1
    print(f"all {len(servos)} servos match {cfg.source}")
    return 0


# ----------------------------------------------------------------------------- calibrate


def run_calibrate(args) -> int:
    import dataclasses

    from firmware_cfg.config import RobotConfig, check_against_mjcf, save_config
    from firmware_cfg.servo_models import load_servo_model

    cfg = load_robot_config(args.config)
    bus = dynamixel_bus_of(cfg, args.bus)
    joints = set(args.joints.split(",")) if args.joints else {s.joint for s in bus.servos}
    unknown = joints - {s.joint for s in bus.servos}
    if unknown:
        raise BridgeError(f"--joints: {sorted(unknown)} are not on bus {bus.name!r}")
    offsets = {}
    with open_bus(args, bus) as (dxl, emu):
        check_models(dxl, bus)
        if not args.keep_torque:
            for s in bus.servos:
                if s.joint in joints:
                    dxl.write(s.id, load_servo_model(s.model).register("torque_enable"), 0)
        if emu is not None:
            print("(emulated bus: servos are where they started)", file=sys.stderr)
        for s in bus.servos:
            if s.joint not in joints:
                continue
            model = load_servo_model(s.model)
            reg = model.register("present_position")
            ticks = [dxl.read(s.id, reg)[0] for _ in range(max(1, args.samples))]
            # with the joint at 0: servo = direction · 0 + zero_offset, so zero_offset = servo angle
            offsets[s.joint] = float(model.ticks_to_rad(sum(ticks) / len(ticks)))
    new_buses = []
    for b in cfg.buses:
        if b is bus:
            b = dataclasses.replace(
                b,
                servos=tuple(
                    dataclasses.replace(s, zero_offset=round(offsets[s.joint], 6)) if s.joint in offsets else s
                    for s in b.servos
                ),
            )
        new_buses.append(b)
    new_cfg = RobotConfig(cfg.robot, tuple(new_buses), cfg.stop_policy, str(args.out), cfg.mjcf)
    # validate the result like any config (limits must still fit the servo's range)
    from firmware_cfg.config import config_to_dict, parse_config

    parse_config(config_to_dict(new_cfg), source=str(args.out), check_mjcf=False)
    if new_cfg.mjcf is not None and Path(new_cfg.mjcf).exists():
        check_against_mjcf(new_cfg, new_cfg.mjcf)
    save_config(new_cfg, args.out)
    rows = [
        [s.joint, str(s.id), f"{offsets[s.joint]:+.4f}", f"{math.degrees(offsets[s.joint]):+.2f}"]
        for s in bus.servos
        if s.joint in offsets
    ]
    print_table(rows, ["joint", "id", "zero_offset rad", "deg"])
    print(f"wrote {args.out}")
    return 0


# ----------------------------------------------------------------------------- monitor


def monitor_rows(dxl, bus) -> list[list[str]]:
    from firmware_cfg.servo_models import load_servo_model
    from ros_free_bridge.dynamixel.protocol import decode_hardware_error

    rows = []
    for s in bus.servos:
        m = load_servo_model(s.model)

        def get(*names, m=m, s=s):
            for n in names:
                if m.has(n):
                    return dxl.read(s.id, m.register(n))[0]
            return None

        try:
            pos = s.to_joint(m.ticks_to_rad(get("present_position")))
            vel = get("present_velocity", "present_speed")
            cur = get("present_current")
            temp = get("present_temperature")
            volt = get("present_input_voltage", "present_voltage")
            hw = get("hardware_error_status")
            torque = get("torque_enable")
        except BridgeError as exc:
            rows.append([str(s.id), s.joint] + ["-"] * 6 + [str(exc).split(": ", 1)[-1][:60]])
            continue
        rows.append(
            [
                str(s.id),
                s.joint,
                f"{math.degrees(pos):+8.2f}",
                "-" if vel is None else f"{s.direction * float(m.velocity_to_rad_s(vel)):+6.2f}",
                "-" if cur is None or m.current_ma is None else f"{float(m.current_to_amps(cur)):+5.2f}",
                "-" if temp is None else f"{temp:3d}",
                "-" if volt is None else f"{float(m.voltage_to_volts(volt)):4.1f}",
                "on" if torque else "off",
                ", ".join(decode_hardware_error(hw)) if hw else "-",
            ]
        )
    return rows


def run_monitor(args) -> int:
    cfg = load_robot_config(args.config)
    bus = dynamixel_bus_of(cfg, args.bus)
    header = ["id", "joint", "pos deg", "vel rad/s", "cur A", "temp C", "volt V", "torque", "hardware error"]
    with open_bus(args, bus) as (dxl, _emu):
        end = None if args.duration is None else time.monotonic() + args.duration
        tty = sys.stdout.isatty()
        while True:
            rows = monitor_rows(dxl, bus)
            if tty:
                print("\x1b[2J\x1b[H", end="")
            print_table(rows, header)
            sys.stdout.flush()
            if args.once or (end is not None and time.monotonic() >= end):
                return 0
            time.sleep(1.0 / max(args.rate, 0.1))


# ----------------------------------------------------------------------------- emulate


def run_emulate(args) -> int:
    cfg = load_robot_config(args.config)
    bus = cfg.bus(args.bus) if args.bus else None
    if bus is not None and bus.protocol == "serial-link":
        from ros_free_bridge.emulators.serial_mcu import SerialMcuEmulator

        emu = SerialMcuEmulator(n_channels=max(s.id for s in bus.servos) + 1).start()
        port = emu.port
        what = f"a DFSL serial-link board with {emu.n_channels} channels"
    else:
        bus = dynamixel_bus_of(cfg, args.bus)
        emu = start_emulator(bus, provisioned=args.provisioned, wire_timing=args.wire_timing)
        port = emu.port_path
        what = f"{len(bus.servos)} servo(s) of {cfg.robot} at {bus.baud} bps, protocol {bus.protocol}"
    try:
        print(port, flush=True)
        print(f"emulating {what} on {port}; use --port {port}. Ctrl-C to stop.", file=sys.stderr, flush=True)
        end = None if args.duration is None else time.monotonic() + args.duration
        while end is None or time.monotonic() < end:
            time.sleep(0.1)
    finally:
        emu.stop()
    return 0
