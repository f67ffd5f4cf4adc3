"""Command-line arguments of the trainer, without importing torch.

Shared by ``dualflow-bridge train`` (:mod:`ros_free_bridge.commands.train`) and
``python -m dualflow.train`` / ``torchrun ... -m dualflow.train``, so ``--help``
stays fast and both spell the options the same way.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """--config, --set KEY=VALUE (repeatable), --out-dir, --steps, --resume, --evaluate, --print-params."""
    parser.add_argument(
        "--config",
        help="training config file (yaml or json), e.g. dualflow/configs/small_synthetic.yaml; "
        "without it the TrainConfig defaults are used",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config field (repeatable), e.g. --set steps=200 --set model.width=64",
    )
    parser.add_argument("--out-dir", help="output directory (overrides out_dir)")
    parser.add_argument("--steps", type=int, help="total optimisation steps (overrides steps)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT_DIR/latest.json")
    parser.add_argument(
        "--evaluate",
        metavar="CHECKPOINT",
        nargs="?",
        const="bundled",
        help="instead of training: reactor position error of a checkpoint (default: the bundled one) "
        "on synthetic validation duets, against the same model with the actor masked and a static pose",
    )
    parser.add_argument("--eval-clips", type=int, default=32, help="validation clips for --evaluate")
    parser.add_argument(
        "--mid-dance",
        action="store_true",
        help="with --evaluate: validation windows cut at random offsets from longer duets (as a live stream sees them)",
    )
    parser.add_argument(
        "--print-params",
        action="store_true",
        help="print the parameter count of each model preset (paper, small, tiny) and exit",
    )
