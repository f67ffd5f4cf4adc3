"""DualFlow at GPU speed (issue 28 item 3): training throughput, a 10 s clip's generation and
streaming at hop 1, each next to today's configuration measured in the same run.

    python bench/dualflow_gpu.py --device cuda --json out.json      (where a GPU is lent)
    python bench/dualflow_gpu.py --quick                             (smoke run: tiny preset, CPU)

Sections (``--sections``, each writes its figures to ``--json`` as soon as it ends, so a run cut
short still leaves what it measured):

* conv: one block's multi-scale convolution (kernels 7, 11, 21) forward + backward at the
  paper width, batch 256, 60 frames: cuDNN's Conv1d (algorithm search off and on) against the
  tap-major matrix products of ``MultiScaleConv(gemm=True)``;
* train: ``Trainer.train_step`` of the paper preset on 60-frame windows (the paper losses,
  EMA, fused AdamW, bf16 autocast), samples/s after warm-up; the first variant is today's
  configuration (batch 32, Conv1d, no algorithm search), the others change one thing each;
* generate: ``dualflow.flow.generate``, reactive, a 10 s clip (300 frames), 20 Euler steps,
  random paper-preset weights: eager float32 (before issue 28) against the CUDA-graph replay
  at each ``SamplingSettings.precision`` and with compiled blocks (``GENERATE_VARIANTS``), each
  output's largest difference from eager float32, and a profile of one network call;
* stream: ``ReactiveStreamer`` at hop 1, window 60, in steady state: full windows (eager and
  replayed from a CUDA graph) and incremental windows, at 20 and at 2 Euler steps (the live
  bridge's setting), ms per emitted frame timed per ``push`` with the device synchronised,
  and a profile of one frame at 2 steps;
* partner: the bridge's partner stage (``ReactorStage``, ``--partner-device``) with this model:
  ms per actor frame at hop 1, 2 steps, full windows (CUDA graphs on CUDA) against incremental
  windows.

``--no-profile-generate`` / ``--no-profile-stream`` skip the profiles (torch.profiler).

Targets (issue 28): training >= 700 samples/s (10x today's 67 on an H200), generation <= 0.25 s,
streaming hop 1 <= 33 ms per frame.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
import traceback
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dualflow.flow import SamplingSettings, cuda_tf32, generate  # noqa: E402
from dualflow.model import Conditions, DualFlow, DualFlowConfig, MultiScaleConv  # noqa: E402
from dualflow.streaming import StreamConfig  # noqa: E402

TARGETS = {"train_samples_per_s": 700.0, "generate_s": 0.25, "stream_ms_per_frame": 33.0}
#: (label, batch, gemm convolutions, cuDNN algorithm search, compiled blocks); the first is
#: today's configuration. The compiled variant goes last: its compile time is the least predictable.
TRAIN_VARIANTS = [
    ("today: batch 32, Conv1d", 32, False, False, False),
    ("batch 256, gemm convolutions", 256, True, False, False),
    ("batch 32, gemm convolutions", 32, True, False, False),
    ("batch 128, gemm convolutions", 128, True, False, False),
    ("batch 256, Conv1d + cudnn.benchmark", 256, False, True, False),
    ("batch 32, Conv1d + cudnn.benchmark", 32, False, True, False),
    ("batch 256, gemm convolutions, compiled blocks", 256, True, False, True),
]


class Recorder:
    """Figures by section, written to a JSON file after each (a cut-short run keeps them)."""

    def __init__(self, path: Path | None, device: str):
        self.path = path
        name = torch.cuda.get_device_name(0) if device.startswith("cuda") else "cpu"
        self.data = {"device": name, "torch": torch.__version__, "targets": TARGETS, "sections": {}}

    def put(self, section: str, key: str, value) -> None:
        self.data["sections"].setdefault(section, {})[key] = value
        print(f"[{section}] {key}: {value}", flush=True)
        if self.path is not None:
            self.path.write_text(json.dumps(self.data, indent=2) + "\n")


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def timed(fn, repeats: int, device: str, warmup: int = 1) -> float:
    """Median wall time (s) of fn() over ``repeats`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    return statistics.median(call_times([fn] * repeats, device))


def call_times(calls, device: str) -> list[float]:
    """Wall time (s) of each call in ``calls`` (zero-argument functions), the device
    synchronised before and after each (a CUDA call returns before its kernels end)."""
    times = []
    for fn in calls:
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return times


def bench_conv(rec: Recorder, args) -> None:
    width, batch = (32, 8) if args.quick else (512, 256)
    conv = MultiScaleConv(width, (7, 11, 21), 0.0).to(args.device)
    z = torch.randn(batch, 60, width, device=args.device, requires_grad=True)
    for label, gemm, search in (
        ("Conv1d", False, False),
        ("Conv1d + cudnn.benchmark", False, True),
        ("gemm", True, False),
    ):
        conv.gemm = gemm
        torch.backends.cudnn.benchmark = search

        def step():
            with torch.autocast(z.device.type, dtype=torch.bfloat16):
                y = conv(z, causal=False, frame_mask=None)
            y.float().sum().backward()

        rec.put("conv", f"{label}: fwd+bwd ms (batch {batch}, width {width})", 1000 * timed(step, 5, args.device, 2))
    torch.backends.cudnn.benchmark = False


def bench_train(rec: Recorder, args) -> None:
    from dualflow.train import TrainConfig, Trainer

    variants = (
        [TRAIN_VARIANTS[int(i)] for i in args.train_variants.split(",")] if args.train_variants else TRAIN_VARIANTS
    )
    variants = variants[:2] if args.quick else variants
    cache = Path(tempfile.mkdtemp(prefix="dualflow_gpu_data_"))
    for label, batch, gemm, search, compiled in variants:
        if time.perf_counter() - args.t0 > args.budget_s:
            rec.put("train", label, "skipped: out of time")
            continue
        batch = min(batch, 4) if args.quick else batch
        torch.backends.cudnn.benchmark = search
        trainer = None
        try:
            config = TrainConfig(
                preset=args.preset,
                batch_size=batch,
                steps=10**6,
                device="cuda" if args.device.startswith("cuda") else "cpu",
                progress=False,
                out_dir=str(cache / "run"),
                ckpt_every=0,
                data_cache=str(cache),
                compile=compiled,
            )
            trainer = Trainer(config)
            for block in trainer.model.blocks:
                block.conv.gemm = gemm
            t_warm = time.perf_counter()
            for _ in range(args.train_warmup + (3 if compiled else 0)):  # both modes compile
                trainer.train_step(sync=False)
            sync(args.device)
            warm_s = time.perf_counter() - t_warm
            if args.device.startswith("cuda"):
                torch.cuda.reset_peak_memory_stats()
            t0 = time.perf_counter()
            for _ in range(args.train_steps):
                row = trainer.train_step(sync=False)
            trainer.row_values(row)
            sync(args.device)
            seconds = time.perf_counter() - t0
            peak = torch.cuda.max_memory_allocated() / 2**30 if args.device.startswith("cuda") else float("nan")
            rate = args.train_steps * batch / seconds
            rec.put(
                "train",
                label,
                {
                    "samples_per_s": round(rate, 1),
                    "step_ms": round(1000 * seconds / args.train_steps, 1),
                    "peak_GiB": round(peak, 1),
                    "warmup_s": round(warm_s, 1),
                },
            )
            if args.profile and label == args.profile:
                rec.put("profile", label, _profile(trainer, args.device))
        except Exception as exc:  # noqa: BLE001 (a bench row: the error is the figure)
            rec.put("train", label, f"error: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}")
        finally:
            del trainer
            if args.device.startswith("cuda"):
                torch.cuda.empty_cache()
    torch.backends.cudnn.benchmark = False


def _profile(trainer, device: str) -> str:
    """The top kernels of two training steps by device time (torch.profiler), as a table."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith("cuda") else [])
    with profile(activities=activities) as prof:
        for _ in range(2):
            trainer.train_step(sync=False)
        sync(device)
    key = "self_cuda_time_total" if device.startswith("cuda") else "self_cpu_time_total"
    return prof.key_averages().table(sort_by=key, row_limit=25, max_name_column_width=60)


def _actor_and_cond(cfg: DualFlowConfig, n: int, device: str):
    from dualflow.motion.features import encode_person
    from dualflow.synthetic import make_leader
    from dualflow.text import template_text_embedding

    leader = make_leader(seconds=(n + 1) / 30.0, fps=30.0, seed=0)
    actor = torch.tensor(encode_person(leader), dtype=torch.float32, device=device)[None]
    text = torch.tensor(
        template_text_embedding(["The leader steps in place; the partner mirrors."], cfg.text_dim), device=device
    )
    return actor, Conditions(text=text, music=torch.zeros(1, n, cfg.music_dim, device=device))


#: (label, CUDA graph, compiled blocks, SamplingSettings.precision); the first is the
#: configuration before issue 28, the third what ``generate`` does by default now
GENERATE_VARIANTS = [
    ("eager, float32", False, False, "float32"),
    ("CUDA graph, float32", True, False, "float32"),
    ("CUDA graph, TF32 (default)", True, False, "tf32"),
    ("CUDA graph, bf16 autocast", True, False, "bf16"),
    ("compiled blocks + CUDA graph, TF32", True, True, "tf32"),
    ("compiled blocks + CUDA graph, bf16 autocast", True, True, "bf16"),
]


def profile_call(fn, device: str, rows: int = 12) -> dict:
    """One call of fn() under torch.profiler: the number of device kernels, their summed device
    time against the call's wall time (a wall time far above the kernels' says the call is bound
    by launching them), and the top kernels by device time."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    cuda = device.startswith("cuda")
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    fn()
    sync(device)
    with profile(activities=activities) as prof:
        t0 = time.perf_counter()
        fn()
        sync(device)
        wall = time.perf_counter() - t0
    kernels = [e for e in prof.events() if e.device_type == DeviceType.CUDA]
    key = "self_cuda_time_total" if cuda else "self_cpu_time_total"
    return {
        "kernels": len(kernels),
        "kernel_ms": round(sum(getattr(e, "device_time", 0.0) for e in kernels) / 1000, 2),
        "wall_ms_profiled": round(1000 * wall, 2),
        "table": prof.key_averages().table(sort_by=key, row_limit=rows, max_name_column_width=50),
    }


def bench_generate(rec: Recorder, args, model: DualFlow) -> None:
    """A 10 s clip, reactive, 20 Euler steps: the variants of ``GENERATE_VARIANTS``, each's
    largest difference from float32 eager sampling, and a profile of one network call."""
    from dualflow.compile import compile_blocks
    from dualflow.flow import guided_velocity

    n = 60 if args.quick else 300
    steps = 5 if args.quick else 20
    actor, cond = _actor_and_cond(model.config, n, args.device)
    outputs = {}
    compiled = None
    variants = [GENERATE_VARIANTS[int(i)] for i in args.generate_variants.split(",")] if args.generate_variants else []
    for label, graph, use_compiled, precision in variants or GENERATE_VARIANTS:
        if time.perf_counter() - args.t0 > args.budget_s:
            rec.put("generate", label, "skipped: out of time")
            continue
        if use_compiled and compiled is None:  # a second model with the same weights: the others stay eager
            compiled = DualFlow(model.config).to(args.device).eval()
            compiled.load_state_dict(model.state_dict())
            compile_blocks(compiled)
        net = compiled if use_compiled else model
        sampling = SamplingSettings(steps=steps, seed=0, cuda_graph=graph, precision=precision)

        def run(net=net, sampling=sampling, label=label):
            with torch.inference_mode():
                outputs[label] = generate(net, n, cond, mode="reactive", x_actor=actor, sampling=sampling)[1]

        try:
            t0 = time.perf_counter()
            run()
            sync(args.device)
            first = time.perf_counter() - t0
            seconds = timed(run, args.repeats, args.device, warmup=0)
            rec.put(
                "generate",
                f"{label}: {n} frames, {steps} Euler steps (s)",
                {"s": round(seconds, 4), "first_call_s": round(first, 2)},
            )
        except Exception as exc:  # noqa: BLE001 (a bench row: the error is the figure)
            rec.put("generate", label, f"error: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}")
    base = GENERATE_VARIANTS[0][0]
    for label in list(outputs):
        if label != base and base in outputs:
            diff = (outputs[base] - outputs[label]).abs().max().item()
            rec.put("generate", f"max |{base} - {label}| (normalised features)", diff)
    if args.profile_generate:
        x = torch.randn(1, n, model.config.motion_dim, device=args.device)
        t = torch.full((1,), 0.5, device=args.device)
        for precision in ("float32", "tf32", "bf16"):
            velocity = guided_velocity(model, cond, mode="reactive", x_actor=actor)

            def call(velocity=velocity, precision=precision):
                bf16 = torch.autocast(x.device.type, torch.bfloat16, enabled=precision == "bf16")
                with torch.inference_mode(), bf16, cuda_tf32(precision == "tf32"):
                    velocity(x, t)

            rec.put("profile", f"one network call of generate, eager, {precision}", profile_call(call, args.device))


#: (label, StreamConfig): full windows eager and replayed from a CUDA graph, and incremental windows
STREAM_SETTINGS = [
    ("full windows, 20 steps, eager", StreamConfig(window=60, steps=20, cuda_graph=False)),
    ("full windows, 20 steps, CUDA graph", StreamConfig(window=60, steps=20)),
    ("full windows, 2 steps, eager", StreamConfig(window=60, steps=2, cuda_graph=False)),
    ("full windows, 2 steps, CUDA graph", StreamConfig(window=60, steps=2)),
    ("incremental, 20 steps", StreamConfig(window=60, steps=20, incremental=True)),
    ("incremental, 2 steps (the live bridge's setting)", StreamConfig(window=60, steps=2, incremental=True)),
]


def bench_stream(rec: Recorder, args, model: DualFlow) -> None:
    """ms per emitted frame at hop 1, window 60, in steady state (full windows), timed per
    ``push`` with the device synchronised (a replayed graph returns before its kernels end)."""
    from dualflow.streaming import ReactiveStreamer

    frames = 8 if args.quick else args.stream_frames
    actor, cond = _actor_and_cond(model.config, 120, args.device)
    settings = STREAM_SETTINGS
    if args.stream_settings:
        settings = [settings[int(i)] for i in args.stream_settings.split(",")]
    outputs = {}
    for label, config in settings:
        if time.perf_counter() - args.t0 > args.budget_s:
            rec.put("stream", label, "skipped: out of time")
            continue
        try:
            with torch.inference_mode():
                streamer = ReactiveStreamer(model, config, cond)
                first = config.window + 4  # in one push: a few wide windows, then full windows at hop 1
                streamer.push(actor[0, :first])
                for i in range(first, first + 3):  # the graphed setting captures here
                    streamer.push(actor[0, i])
                pushes = [lambda i=i, s=streamer: s.push(actor[0, i]) for i in range(first + 3, first + 3 + frames)]
                times = call_times(pushes, args.device)
                outputs[label] = streamer.emitted.clone()
                if args.profile_stream and config.steps == 2:
                    nxt = iter(actor[0, first + 3 + frames :])
                    prof = profile_call(lambda s=streamer, it=nxt: s.push(next(it)), args.device)
                    rec.put("profile", f"one frame of streaming, {label}", prof)
            rec.put(
                "stream",
                f"{label}: ms per frame (hop 1)",
                {
                    "ms_per_frame": round(1000 * statistics.mean(times), 2),
                    "max_ms": round(1000 * max(times), 2),
                    "frames": len(times),
                },
            )
        except Exception as exc:  # noqa: BLE001
            rec.put("stream", label, f"error: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}")
    for steps in (20, 2):
        eager, graphed = f"full windows, {steps} steps, eager", f"full windows, {steps} steps, CUDA graph"
        if eager in outputs and graphed in outputs:
            diff = (outputs[eager] - outputs[graphed]).abs().max().item()
            rec.put("stream", f"max |{eager} - {graphed}| over the stream (normalised features)", diff)


def bench_partner(rec: Recorder, args, model: DualFlow) -> None:
    """The bridge's partner stage (``ReactorStage``, ``--partner-device``) with this model saved
    as a checkpoint: ms per actor frame at hop 1, 2 Euler steps, window 60, steady state (frames
    from 80 on), with full windows (replayed from CUDA graphs on CUDA) and with incremental
    windows (the CPU's default), each push timed with the device synchronised."""
    from dualflow.checkpoint import BUNDLED_CHECKPOINT, load_checkpoint, save_checkpoint
    from dualflow.synthetic import make_leader
    from ros_free_bridge.partner.reactor import ReactorStage
    from ros_free_bridge.sources.udp import ActorFrame

    frames = 100 if args.quick else 180
    folder = Path(tempfile.mkdtemp(prefix="dualflow_gpu_partner_")) / "model"
    save_checkpoint(folder, model=model, stats=load_checkpoint(BUNDLED_CHECKPOINT).stats)
    leader = make_leader(frames / 30.0, 30.0, seed=3).positions
    for label, incremental in (("full windows", False), ("incremental windows", True)):
        config = StreamConfig(window=60, steps=2, incremental=incremental)
        stage = ReactorStage(30.0, folder, config, device=args.device)
        pushes = [
            lambda i=i, pos=pos, s=stage: s.push_many([ActorFrame(i, pos, i / 30.0)]) for i, pos in enumerate(leader)
        ]
        steady = call_times(pushes, args.device)[80:]
        rec.put(
            "partner",
            f"ReactorStage, {label}: ms per actor frame (hop 1, 2 steps)",
            {
                "median_ms": round(1000 * statistics.median(steady), 2),
                "mean_ms": round(1000 * statistics.mean(steady), 2),
                "max_ms": round(1000 * max(steady), 2),
                "frames": len(steady),
            },
        )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--preset", default="paper")
    p.add_argument("--sections", default="conv,generate,stream,partner,train")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--train-steps", type=int, default=8)
    p.add_argument("--train-warmup", type=int, default=3)
    p.add_argument("--stream-frames", type=int, default=12)
    p.add_argument("--budget-s", type=float, default=400.0, help="skip what would start after this many seconds")
    p.add_argument("--generate-variants", default="", help="indices into GENERATE_VARIANTS ('' = all)")
    p.add_argument("--stream-settings", default="", help="indices into STREAM_SETTINGS ('' = all)")
    p.add_argument("--train-variants", default="", help="indices into TRAIN_VARIANTS, e.g. 0,6 ('' = all)")
    p.add_argument("--profile", default="batch 256, gemm convolutions", help="train variant to profile ('' = none)")
    p.add_argument("--no-profile-generate", dest="profile_generate", action="store_false")
    p.add_argument("--no-profile-stream", dest="profile_stream", action="store_false")
    p.add_argument("--quick", action="store_true", help="smoke run: tiny preset on the CPU, small sizes")
    args = p.parse_args(argv)
    if args.quick:
        args.device, args.preset, args.repeats, args.train_steps, args.train_warmup = "cpu", "tiny", 1, 2, 1
        args.profile = TRAIN_VARIANTS[0][0]
    args.t0 = time.perf_counter()
    if args.device.startswith("cuda"):  # training's float32 products (outside its bf16 autocast)
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    rec = Recorder(args.json, args.device)
    print(f"device: {rec.data['device']}, torch {torch.__version__}, preset {args.preset}", flush=True)
    sections = args.sections.split(",")
    model = None
    if {"generate", "stream", "partner"} & set(sections):
        torch.manual_seed(0)
        model = DualFlow(DualFlowConfig.preset(args.preset)).to(args.device).eval()
        with torch.no_grad():  # the output heads start at zero (v = 0): give them weights, so outputs compare
            torch.nn.init.normal_(model.out_b.weight, std=0.02)
    for name in sections:
        try:
            if name == "conv":
                bench_conv(rec, args)
            elif name == "train":
                bench_train(rec, args)
            elif name == "generate":
                bench_generate(rec, args, model)
            elif name == "stream":
                bench_stream(rec, args, model)
            elif name == "partner":
                bench_partner(rec, args, model)
        except Exception:  # noqa: BLE001 (keep measuring the other sections)
            rec.put(name, "error", traceback.format_exc()[-1500:])
        if name in ("generate", "stream", "partner") and model is not None and name == sections[-1]:
            model = None
    print(json.dumps(rec.data, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
