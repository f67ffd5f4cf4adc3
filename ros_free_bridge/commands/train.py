"""``dualflow-bridge train``: train the DualFlow generator from a config file.

    dualflow-bridge train --config dualflow/configs/small_synthetic.yaml [--set KEY=VALUE ...]
    dualflow-bridge train --print-params          parameter count of each model preset
    torchrun --standalone --nproc_per_node 2 -m ros_free_bridge train --config FILE   (DDP)

The trainer itself is :mod:`dualflow.train`; torch is imported only when the
command runs.
"""

from __future__ import annotations

import argparse

from dualflow.train_cli import add_arguments


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "train",
        help="train the DualFlow generator (config file, AdamW, EMA, checkpoints, DDP via torchrun)",
        description="Train the DualFlow generator. Without --config the TrainConfig defaults are used.",
    )
    add_arguments(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dualflow.train import run_from_args

    return run_from_args(args)
