"""The ``dualflow-bridge`` command line (also ``python -m ros_free_bridge``).

Each subcommand lives in its own module under :mod:`ros_free_bridge.commands`
with a ``register(subparsers)`` function that adds its parser and sets
``func(args) -> int``. Modules import their heavy dependencies (torch, mujoco,
casadi) inside ``func`` so that ``--help`` stays fast.

Exit codes (DESIGN.md, README "Exit codes"; every leaf parser's --help ends with
:data:`EXIT_CODES`): 0 it ended normally (and a check passed), 1 a fault, e-stop, watchdog
stop or failed verdict (the commands return it), 2 bad usage or bad input: user errors (each
package's one error type) print one line and exit 2; any other exception is a bug and keeps
its traceback.
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

#: The exit-code contract, appended to every leaf command's --help.
EXIT_CODES = (
    "Exit codes: 0 it ended normally (a run stopped at the motion's end, --max-duration or a stop request; "
    "a check or verification passed); 1 a fault, e-stop or watchdog stop (bus error, overheat, generator "
    "failure, no frames, Ctrl-C/SIGTERM while the robot is under control) or a failed check; 2 bad usage or "
    "bad input (one line naming the file or field and the fix)."
)


def _add_exit_codes(parser: argparse.ArgumentParser) -> None:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    for action in subs:
        for sub in action.choices.values():
            _add_exit_codes(sub)
    if not subs:
        import textwrap

        text = textwrap.fill(EXIT_CODES, 78, break_on_hyphens=False)  # raw formatters print it as it is
        parser.epilog = f"{parser.epilog}\n\n{text}" if parser.epilog else text


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dualflow-bridge",
        description="DualFlow partner-robot bridge: human motion in, a safe robot partner out.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        module = importlib.import_module(f"ros_free_bridge.commands.{name}")
        module.register(sub)
    _add_exit_codes(parser)
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
