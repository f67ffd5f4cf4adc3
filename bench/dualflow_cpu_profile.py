"""What the CPU can show about DualFlow's GPU speed: operations per forward and per training
step, host synchronisations per step, graph breaks under torch.compile, CPU step times.

    python bench/dualflow_cpu_profile.py [--preset small] [--width W] [--baseline-src DIR] [--compile]

No GPU here, so the figures are the causes a GPU run pays for, counted on the CPU:

* ops / forward: ATen operations of one forward pass (batch 2, 60 frames), interactive and
  reactive; on a GPU each is about one kernel launch, so at small batch the forward is
  launch-bound in proportion to this count;
* ops / train step and host syncs / train step: one ``Trainer.train_step`` (batch 8, 60
  frames, the paper's four losses, reactive and interactive), counting the operations that
  make the host wait for the device (``aten::_local_scalar_dense``: ``float()``, ``.item()``,
  ``bool()`` of a tensor; ``aten::nonzero``: boolean indexing, ``.any()`` in Python
  control flow) -- with ``sync=False``, the way ``Trainer.run`` now calls it between logged steps;
  the optimizer's own scalar reads are listed apart (AdamW reads its per-parameter step
  counters, which live on the host unless ``fused``/``capturable``: not a device sync);
* CPU time per forward and per train step (median of ``--repeats``; one thread);
* with ``--compile``: graph breaks of ``torch._dynamo.explain`` on one block's stages and on
  the whole reactive forward, and the compile time of one block (``dualflow.compile``).

``--baseline-src DIR``: the same measurements, in a subprocess, on another copy of the code
(e.g. ``mkdir /tmp/base && git archive HEAD dualflow | tar -x -C /tmp/base``: the code before
your changes), printed next to this tree's: the baseline of the same run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

SYNC_OPS = ("aten::_local_scalar_dense", "aten::nonzero", "aten::masked_select", "aten::item")


class OpCounter(TorchDispatchMode):
    """Counts ATen operations dispatched while active (forward and backward)."""

    def __init__(self):
        super().__init__()
        self.ops = Counter()
        self.phase = "step"  # "optimizer" while the optimizer steps (see measure)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[(self.phase, func._schema.name)] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.ops.values())

    def syncs(self, phase: str = "step") -> int:
        return sum(self.ops[(phase, name)] for name in SYNC_OPS)


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def measure(preset: str, repeats: int, root: str, width: int | None = None) -> dict:
    """The figures of the module docstring for the code under ``root`` (imported from there)."""
    sys.path.insert(0, root)
    import dualflow.model
    from dualflow.model import Conditions, DualFlow, DualFlowConfig
    from dualflow.train import Trainer, load_train_config

    torch.set_num_threads(1)
    torch.manual_seed(0)
    out = {"root": str(Path(dualflow.model.__file__).parents[1])}
    over = {"music_dim": 4} if width is None else {"music_dim": 4, "width": width, "ff_dim": 2 * width}
    model = DualFlow(DualFlowConfig.preset(preset, **over)).eval()
    for p in model.parameters():  # the zero-initialised linears would make some branches trivial
        torch.nn.init.normal_(p, std=0.02) if p.dim() > 1 else None
    x = torch.randn(2, 60, 262)
    cond = Conditions(text=torch.randn(2, 384), music=torch.randn(2, 60, 4))
    for mode in ("interactive", "reactive"):
        with torch.no_grad():
            counter = OpCounter()
            with counter:
                model(x, x, 0.5, cond, mode=mode)
            out[f"ops_forward_{mode}"] = counter.total
            out[f"ms_forward_{mode}"] = 1e3 * _median_time(lambda mode=mode: model(x, x, 0.5, cond, mode=mode), repeats)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_train_config(
            None,
            [
                f"preset={preset}",
                "data.n_clips=16",
                "data.val_clips=0",
                "data.frames=60",
                "batch_size=8",
                "threads=1",
                "progress=false",
                "music=beats",
                "model.music_dim=4",
                f"out_dir={tmp}",
                "text_encoder=hashed",
            ]
            + ([] if width is None else [f"model.width={width}", f"model.ff_dim={2 * width}"]),
        )
        trainer = Trainer(cfg)
        trainer.train_step()  # warm-up
        counter = OpCounter()
        step = trainer.optimizer.step

        def tagged_step(*a, **k):  # the optimizer's scalar reads are of CPU step counters, not device syncs
            counter.phase = "optimizer"
            try:
                return step(*a, **k)
            finally:
                counter.phase = "step"

        trainer.optimizer.step = tagged_step
        for mode_prob, mode in ((1.0, "reactive"), (0.0, "interactive")):
            object.__setattr__(trainer.config, "reactive_prob", mode_prob)
            counter.ops.clear()
            kwargs = {"sync": False} if "sync" in trainer.train_step.__code__.co_varnames else {}
            with counter:
                trainer.train_step(**kwargs)
            out[f"ops_step_{mode}"] = counter.total
            out[f"syncs_step_{mode}"] = counter.syncs("step")
            out[f"scalar_reads_optimizer_{mode}"] = counter.syncs("optimizer")
            out[f"ms_step_{mode}"] = 1e3 * _median_time(lambda kwargs=kwargs: trainer.train_step(**kwargs), repeats)
    return out


def graph_breaks(preset: str) -> dict:
    """torch._dynamo.explain on one block's stages and on the reactive forward; compile time of one block."""
    import torch._dynamo

    from dualflow.model import Conditions, DualFlow, DualFlowConfig

    model = DualFlow(DualFlowConfig.preset(preset, music_dim=4)).eval()
    x = torch.randn(2, 60, 262)
    cond = Conditions(text=torch.randn(2, 384), music=torch.randn(2, 60, 4))
    out = {}
    with torch.no_grad():
        explained = torch._dynamo.explain(lambda a: model(a, a, 0.5, cond, mode="reactive"))(x)
        out["whole_forward_graph_breaks"] = explained.graph_break_count
        out["whole_forward_graphs"] = explained.graph_count
        out["whole_forward_break_reasons"] = sorted({str(b.reason)[:90] for b in explained.break_reasons})[:4]
        try:
            from dualflow.compile import compile_blocks
        except ImportError:
            return out
        torch._dynamo.reset()
        compile_blocks(model)
        t0 = time.perf_counter()
        model(x, x, 0.5, cond, mode="reactive")
        out["compile_blocks_first_call_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        model(x, x, 0.5, cond, mode="reactive")
        out["compiled_second_call_s"] = time.perf_counter() - t0
        from torch._dynamo.utils import counters

        out["dynamo_unique_graphs"] = int(counters["stats"]["unique_graphs"])
        out["dynamo_graph_breaks"] = int(sum(counters["graph_break"].values()))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="small", choices=("paper", "small", "tiny"))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--baseline-src", help="a directory holding another copy of the dualflow package")
    ap.add_argument("--compile", action="store_true", help="also graph breaks and one block's compile time")
    ap.add_argument(
        "--width",
        type=int,
        help="override the width (and ff_dim = 2 width): op and sync counts do "
        "not depend on it, so e.g. --preset paper --width 64 counts the paper model's on a small machine",
    )
    ap.add_argument("--json-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    root = str(Path(__file__).resolve().parents[1])
    if args.json_only:
        print(json.dumps(measure(args.preset, args.repeats, args.baseline_src or root, args.width)))
        return 0
    runs = {"this tree": measure(args.preset, args.repeats, root, args.width)}
    if args.baseline_src:
        if not (Path(args.baseline_src) / "dualflow" / "model.py").is_file():
            print(f"error: --baseline-src {args.baseline_src} has no dualflow/model.py", file=sys.stderr)
            return 2
        proc = subprocess.run(
            [
                sys.executable,
                __file__,
                "--preset",
                args.preset,
                "--repeats",
                str(args.repeats),
                "--baseline-src",
                args.baseline_src,
                "--json-only",
            ]
            + ([] if args.width is None else ["--width", str(args.width)]),
            capture_output=True,
            text=True,
            check=True,
            cwd=args.baseline_src,
        )
        runs["baseline"] = json.loads(proc.stdout.strip().splitlines()[-1])
    for name, run in runs.items():
        print(f"{name}: code from {run['root']}")
    keys = [k for k in runs["this tree"] if k != "root"]
    print(
        f"DualFlow '{args.preset}' preset{'' if args.width is None else f' at width {args.width}'}, CPU, one "
        f"thread (median of {args.repeats}); forward: batch 2, 60 frames; train step: batch 8, 60 frames, paper losses"
    )
    print(f"{'figure':28s} " + " ".join(f"{name:>12s}" for name in runs))
    for k in keys:
        vals = [runs[name].get(k, float("nan")) for name in runs]
        print(f"{k:28s} " + " ".join(f"{v:12.1f}" if isinstance(v, float) else f"{v:12d}" for v in vals))
    if args.compile:
        for k, v in graph_breaks(args.preset).items():
            print(f"{k}: {v}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
