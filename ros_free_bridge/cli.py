"""The ``dualflow-bridge`` command line (also ``python -m ros_free_bridge``).

Each subcommand lives in its own module under :mod:`ros_free_bridge.commands`
with a ``register(subparsers)`` function that adds its parser and sets
``func(args) -> int``. Modules import their heavy dependencies (torch, mujoco,
casadi) inside ``func`` so that ``--help`` stays fast.

User errors (each package's one error type) print one line and exit 2; any
other exception is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from dualflow.errors import DualFlowError
from firmware_cfg.errors import ConfigError
from retarget.errors import RetargetError
from ros_free_bridge.errors import BridgeError
from sim.errors import SimError

#: Subcommand modules, in the order ``--help`` lists them.
COMMAND_MODULES: tuple[str, ...] = (
    "demo",
    "motion",
    "train",
    "eval",
    "servo",
    "check",
    "render",
    "view",
    "retarget",
    "retarget_check",
    "run",
    "telemetry",
    "robot",
)

USER_ERRORS = (DualFlowError, RetargetError, SimError, ConfigError, BridgeError)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dualflow-bridge",
        description="DualFlow partner-robot bridge: human motion in, a safe robot partner out.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        module = importlib.import_module(f"ros_free_bridge.commands.{name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    try:
        return int(func(args) or 0)
    except USER_ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
