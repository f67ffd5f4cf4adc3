"""``dualflow-bridge eval``: score checkpoints on a dataset and print a Table-1-shaped table.

    dualflow-bridge eval train-evaluator --dataset synthetic --out runs/evaluator [--steps 400]
    dualflow-bridge eval --dataset synthetic --evaluator runs/evaluator \\
        --full runs/a/final --no-triplet runs/b/final --look-ahead 0=runs/c/final [--mode both] [--quick]
    dualflow-bridge eval --print-ablation-recipes

Rows: the ground truth, then every checkpoint, grouped under "Interactive Task" /
"Reactive Task" (``--mode``). Checkpoints come from ``--checkpoint LABEL=PATH`` or
from the ablation switches, which only *label* the checkpoint they are given
with the paper's row names (Table 4, app. D): ``--full`` (DualFlow), ``--no-rag``,
``--no-triplet``, ``--no-sync``, ``--spectral`` / ``--jukebox`` (music features),
``--look-ahead L=PATH`` and ``--retrieval-k K=PATH`` (repeatable). Train each one
with the overrides that ``--print-ablation-recipes`` lists. Metrics, protocol and
the evaluator: :mod:`dualflow.evaluation`. torch is imported only when a command runs.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

QUICK = {"replications": 2, "batch_size": 32, "diversity_times": 100, "mm_samples": 10, "mm_repeats": 5, "mm_times": 5}


def _dataset_args(p: argparse.ArgumentParser, split: str) -> None:
    p.add_argument(
        "--dataset",
        default="synthetic",
        help="interhuman | interhuman_as | dd100 | mdd | bvh_pairs | synthetic (default synthetic)",
    )
    p.add_argument("--root", default=None, help="dataset folder (not for synthetic)")
    p.add_argument("--split", default=split, help=f"split to use (default {split})")
    p.add_argument("--frames", type=int, default=60, help="feature rows per window (default 60 = 2 s at 30 fps)")
    p.add_argument("--stride", type=int, default=None, help="window stride in frames (default: --frames)")
    p.add_argument("--limit", type=int, default=None, help="use at most this many clips")
    p.add_argument(
        "--clips", type=int, default=None, help="synthetic only: number of clips (default 64 / 256 for training)"
    )
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "eval",
        help="evaluate checkpoints (FID, R-precision, MMDist, diversity, MModality, BED, BAS)",
        description="Score DualFlow checkpoints against a dataset's ground truth with a trained motion-text "
        "evaluator and print a table shaped like the paper's Table 1.",
    )
    _dataset_args(parser, "test")
    _row_args(parser)
    _protocol_args(parser)
    _output_args(parser)
    parser.set_defaults(func=run_eval)
    sub = parser.add_subparsers(dest="eval_action", metavar="ACTION")
    _register_train_evaluator(sub)


def _row_args(parser) -> None:
    """The checkpoints to score: the evaluator, the rows and the ablations of the paper's table."""
    parser.add_argument("--evaluator", default=None, help="evaluator folder from `eval train-evaluator`")
    parser.add_argument("--checkpoint", action="append", default=[], metavar="[LABEL=]PATH", help="a row (repeatable)")
    parser.add_argument("--full", metavar="PATH", help="the full model (row 'DualFlow')")
    parser.add_argument("--no-rag", metavar="PATH", help="ablation: trained without retrieval")
    parser.add_argument("--no-triplet", metavar="PATH", help="ablation: trained without the triplet loss")
    parser.add_argument("--no-sync", metavar="PATH", help="ablation: trained without the sync loss")
    parser.add_argument("--spectral", metavar="PATH", help="ablation: spectral music features")
    parser.add_argument("--jukebox", metavar="PATH", help="ablation: Jukebox music features")
    parser.add_argument("--look-ahead", action="append", default=[], metavar="L=PATH", help="ablation: look-ahead L")
    parser.add_argument(
        "--retrieval-k", action="append", default=[], metavar="K=PATH", help="ablation: retrieval depth k"
    )


def _protocol_args(parser) -> None:
    """How the scoring runs: mode, sampling, replications and the metrics' sample counts."""
    parser.add_argument(
        "--mode",
        choices=("interactive", "reactive", "both"),
        default="both",
        help="interactive: both people generated from text/music; reactive: the reactor generated "
        "from the ground-truth actor; both: two row groups, as in the paper (default both)",
    )
    parser.add_argument("--steps", type=int, default=20, help="Euler steps per sample (paper: 20)")
    parser.add_argument(
        "--cfg-scale",
        type=float,
        default=1.0,
        help="classifier-free guidance scale of the conditions (1 = no guidance; default 1)",
    )
    parser.add_argument(
        "--replications",
        type=int,
        default=20,
        help="repeats of the whole protocol with different seeds; figures are mean ± 1.96 σ/√n (default 20)",
    )
    parser.add_argument("--batch-size", type=int, default=96, help="R-precision batch (InterGen: 96)")
    parser.add_argument(
        "--diversity-times",
        type=int,
        default=300,
        help="pairs of generated samples whose embedding distance makes the diversity (default 300)",
    )
    parser.add_argument(
        "--mm-samples", type=int, default=100, help="multimodality: conditions sampled from the test set (default 100)"
    )
    parser.add_argument(
        "--mm-repeats", type=int, default=30, help="multimodality: generations per condition (default 30)"
    )
    parser.add_argument(
        "--mm-times",
        type=int,
        default=10,
        help="multimodality: pairs of those generations compared per condition (default 10)",
    )


def _output_args(parser) -> None:
    """The protocol's size, the ground-truth row and what is written."""
    parser.add_argument(
        "--quick", action="store_true", help="smaller protocol: " + ", ".join(f"{k}={v}" for k, v in QUICK.items())
    )
    parser.add_argument("--no-ground-truth", action="store_true", help="leave out the ground-truth row")
    parser.add_argument("--json", default=None, help="also write the results to this JSON file")
    parser.add_argument(
        "--print-ablation-recipes",
        action="store_true",
        help="print the training overrides of every ablation switch and exit",
    )


def _register_train_evaluator(sub) -> None:
    """`eval train-evaluator`: train the motion-text evaluator the scores use."""
    tr = sub.add_parser(
        "train-evaluator",
        help="train the contrastive motion-text evaluator",
        description="Train the InterCLIP-style motion-text evaluator on a dataset split.",
    )
    _dataset_args(tr, "train")
    tr.add_argument("--out", required=True, help="output folder for the evaluator")
    tr.add_argument("--steps", type=int, default=400, help="training steps (default 400)")
    tr.add_argument("--batch-size", type=int, default=32, help="motion-text pairs per step (default 32)")
    tr.add_argument("--lr", type=float, default=3e-4, help="AdamW learning rate (default 3e-4)")
    tr.add_argument("--width", type=int, default=128, help="transformer width of each encoder (default 128)")
    tr.add_argument("--layers", type=int, default=2, help="transformer layers of each encoder (default 2)")
    tr.add_argument("--seed", type=int, default=0, help="seed of the initial weights and batch order (default 0)")
    tr.set_defaults(func=run_train_evaluator)


def _load(args, split: str | None = None):
    from dualflow.datasets import load_dataset
    from dualflow.evaluation.protocol import EvalSet

    opts = {}
    if args.limit is not None:
        opts["limit"] = args.limit
    if args.dataset == "synthetic":
        opts.update(frames=args.frames, n_clips=args.clips or (256 if split == "train" else 64))
    elif args.clips is not None:
        from dualflow.errors import DualFlowError

        raise DualFlowError("--clips is for the synthetic dataset; use --limit for real datasets")
    dset = load_dataset(args.dataset, args.root, split or args.split, **opts)
    print(dset.summary())
    return EvalSet.from_duet_set(dset, args.frames, args.stride)


def run_train_evaluator(args: argparse.Namespace) -> int:
    import torch

    from dualflow.evaluation.evaluator import EvaluatorConfig, EvaluatorTraining, train_evaluator

    data = _load(args, args.split)
    torch.manual_seed(args.seed)
    cfg = EvaluatorConfig(width=args.width, layers=args.layers, ff_dim=2 * args.width, dim=args.width)
    model = train_evaluator(
        data.features,
        data.texts,
        config=cfg,
        device=args.device,
        training=EvaluatorTraining(steps=args.steps, batch_size=args.batch_size, lr=args.lr, seed=args.seed),
        log=lambda step, loss: print(f"step {step:5d}  contrastive loss {loss:.4f}"),
    )
    model.summary.update(dataset=args.dataset, split=args.split, root=str(args.root) if args.root else None)
    out = model.save(args.out, model.summary)
    print(f"evaluator written to {out} ({len(data)} windows, final loss {model.summary['final_loss']:.4f})")
    return 0


def _rows(args) -> list[tuple[str, str]]:
    """(label, checkpoint path) in table order."""
    from dualflow.errors import DualFlowError
    from dualflow.evaluation.ablations import ABLATION_SWITCHES

    rows = []
    for item in args.checkpoint:
        label, _, path = item.rpartition("=")
        rows.append((label or Path(path).parent.name or Path(path).name, path))
    for key in ("full", "no_rag", "no_triplet", "no_sync", "spectral", "jukebox"):
        path = getattr(args, key)
        if path:
            rows.append((ABLATION_SWITCHES[key][0], path))
    for key in ("look_ahead", "retrieval_k"):
        for item in getattr(args, key):
            value, sep, path = item.partition("=")
            if not sep or not value.strip().isdigit():
                raise DualFlowError(f"--{key.replace('_', '-')} {item!r}: expected N=PATH with a whole number N")
            rows.append((ABLATION_SWITCHES[key][0].format(v=int(value)), path))
    for label, path in rows:
        if not Path(path).is_dir():
            raise DualFlowError(f"{path}: checkpoint folder not found (row {label!r})")
    return rows


def print_recipes() -> None:
    from dualflow.evaluation.ablations import ABLATION_SWITCHES

    print("Ablation switches and how to train each checkpoint (dualflow-bridge train --config FILE --set ...):")
    for key, (label, sets) in ABLATION_SWITCHES.items():
        flag = "--" + key.replace("_", "-") + (" N=PATH" if "{v}" in label else " PATH")
        recipe = " ".join(f"--set {s.format(v='N')}" for s in sets)
        print(f"  {flag:24s} row {label.format(v='N')!r:28s} {recipe}")
    print(
        "Jukebox features (4800-d) are precomputed .npy files (e.g. MDD's, with --set data.options.music=jukebox);"
        " the synthetic duets have no audio to compute them from."
    )


def run_eval(args: argparse.Namespace) -> int:
    from dualflow.errors import DualFlowError

    if args.print_ablation_recipes:
        print_recipes()
        return 0
    if not args.evaluator:
        raise DualFlowError("eval: --evaluator DIR is required (train one with `dualflow-bridge eval train-evaluator`)")
    rows = _rows(args)
    if not rows and args.no_ground_truth:
        raise DualFlowError(
            "eval: nothing to evaluate; give --checkpoint / ablation switches or keep the ground-truth row"
        )
    import torch

    from dualflow.evaluation.evaluator import MotionTextEvaluator
    from dualflow.evaluation.protocol import CheckpointGenerator, ProtocolConfig, evaluate
    from dualflow.evaluation.table import format_table

    if os.environ.get("DUALFLOW_EVAL_THREADS"):
        torch.set_num_threads(int(os.environ["DUALFLOW_EVAL_THREADS"]))
    evaluator = MotionTextEvaluator.load(args.evaluator, args.device)
    data = _load(args)
    proto = dict(
        replications=args.replications,
        batch_size=args.batch_size,
        diversity_times=args.diversity_times,
        mm_samples=args.mm_samples,
        mm_repeats=args.mm_repeats,
        mm_times=args.mm_times,
    )
    if args.quick:
        proto.update(QUICK)
    modes = ["interactive", "reactive"] if args.mode == "both" else [args.mode]
    table, results = [], {}
    if not args.no_ground_truth:
        gt = evaluate(None, data, evaluator, ProtocolConfig(**proto, mode=modes[0]))
        table.append(("Ground Truth", gt))
        results["Ground Truth"] = gt
    for mode in modes:
        if rows:
            table.append((f"{mode.capitalize()} Task", None))
        for label, path in rows:
            gen = CheckpointGenerator(
                path, data, mode=mode, steps=args.steps, cfg_scale=args.cfg_scale, device=args.device
            )
            res = evaluate(gen, data, evaluator, ProtocolConfig(**proto, mode=mode))
            table.append((label, res))
            results[f"{mode}/{label}"] = res
    title = (
        f"{args.dataset}/{args.split}: {len(data)} windows of {args.frames} frames; "
        f"{proto['replications']} replication(s); {args.steps} steps"
    )
    print(format_table(table, title))
    if args.json:
        payload = {
            "title": title,
            "protocol": proto,
            "rows": {k: {m: {"mean": e.mean, "ci": e.ci, "n": e.n} for m, e in v.items()} for k, v in results.items()},
        }
        tmp = Path(args.json).with_name(Path(args.json).name + ".partial")
        tmp.write_text(json.dumps(payload, indent=2, allow_nan=True))
        os.replace(tmp, args.json)
    return 0
