"""Run an emulated Dynamixel bus until Ctrl-C, for trying the bridge without hardware::

    python -m ros_free_bridge.emulators --ids 1-20 --model XM430-W350 --baud 2000000
    # prints the pty path (e.g. /dev/pts/7); point a transport or dynamixel-sdk at it,
    # or give --link /tmp/ttyDXL for a stable name.

Options: ``--ids`` (ranges and lists: ``1-18,19,20``), ``--model`` (any bundled servo
model), ``--device ID:MODEL`` (a non-servo device, e.g. ``200:OpenCR``, the OP3's IMU
board; repeatable), ``--baud``, ``--wire-timing`` (replies take the time the bytes need on the
wire), ``--return-delay-us``. Exits 0 on Ctrl-C or SIGTERM, 2 on a bad option.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

from ros_free_bridge.errors import BridgeError


def parse_ids(text: str) -> list[int]:
    """'1-3,7' -> [1, 2, 3, 7]; a BridgeError names the bad part."""
    ids: list[int] = []
    for part in text.split(","):
        part = part.strip()
        try:
            if "-" in part:
                lo, hi = (int(v) for v in part.split("-", 1))
                ids.extend(range(lo, hi + 1))
            else:
                ids.append(int(part))
        except ValueError:
            raise BridgeError(f"--ids: cannot read {part!r}; use IDs and ranges like 1-18,19,20") from None
    bad = [i for i in ids if not 0 <= i <= 252]
    if bad or not ids:
        raise BridgeError(f"--ids: IDs must be 0..252, got {bad or 'none'}")
    return ids


def parse_device(text: str) -> tuple[int, str]:
    """'200:OpenCR' -> (200, 'OpenCR'); a BridgeError names the bad option."""
    from firmware_cfg.device_models import device_model_names, find_device_model

    sid, _, name = text.partition(":")
    try:
        ident = int(sid)
    except ValueError:
        raise BridgeError(f"--device {text!r}: use ID:MODEL, e.g. 200:OpenCR") from None
    if find_device_model(name) is None or not 0 <= ident <= 252:
        raise BridgeError(f"--device {text!r}: ID 0..252 and a model of {device_model_names()}")
    return ident, name


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m ros_free_bridge.emulators", description="Emulated Dynamixel servo bus on a pseudo-terminal."
    )
    parser.add_argument("--ids", default="1-20", help="servo IDs, e.g. 1-20 or 1,2,5 (default 1-20)")
    parser.add_argument("--model", default=None, help="servo model (default XM430-W350; AX-12A for --protocol 1)")
    parser.add_argument("--protocol", type=int, choices=(1, 2), default=2)
    parser.add_argument("--baud", type=int, default=1_000_000)
    parser.add_argument("--wire-timing", action="store_true", help="delay replies by their time on the wire")
    parser.add_argument("--return-delay-us", type=float, default=0.0)
    parser.add_argument("--link", default=None, help="also make this symlink to the pty")
    parser.add_argument(
        "--device",
        action="append",
        default=[],
        metavar="ID:MODEL",
        help="a non-servo device on the bus, e.g. 200:OpenCR (the OP3's IMU); repeatable",
    )
    args = parser.parse_args(argv)

    from ros_free_bridge.emulators.dynamixel_bus import DEFAULT_MODELS, DynamixelBusEmulator

    try:
        model = args.model or DEFAULT_MODELS[args.protocol]
        servos = [(i, model) for i in parse_ids(args.ids)] + [parse_device(d) for d in args.device]
        emu = DynamixelBusEmulator(
            servos,
            baud=args.baud,
            protocol=args.protocol,
            wire_timing=args.wire_timing,
            return_delay_us=args.return_delay_us,
        )
    except Exception as exc:  # ConfigError / BridgeError: one line, exit 2
        print(f"error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with emu:
        if args.link:
            tmp = f"{args.link}.partial"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(emu.port_path, tmp)
            os.replace(tmp, args.link)
        print(emu.port_path, flush=True)
        print(
            f"{len(servos) - len(args.device)} x {model} (+ {len(args.device)} device(s)) "
            f"at {args.baud} bps, protocol {args.protocol}; Ctrl-C to stop",
            file=sys.stderr,
            flush=True,
        )
        try:
            while not stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            if args.link and os.path.islink(args.link):
                os.unlink(args.link)
    return 0


if __name__ == "__main__":
    sys.exit(main())
