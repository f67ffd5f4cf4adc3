"""Training DualFlow: config file, AdamW with warm-up, clipping, EMA, checkpoints, DDP, AMP.

Run::

    dualflow-bridge train --config dualflow/configs/small_synthetic.yaml [--set steps=200 ...]
    torchrun --standalone --nproc_per_node 2 -m dualflow.train --config FILE

Contract: :class:`TrainConfig` is the YAML file (every field optional; ``data`` is a
:class:`dualflow.datasets.config.TrainingDataConfig`, ``retrieval`` a
:class:`dualflow.retrieval.RagConfig`). Every random draw is seeded from (seed, step, rank), so
a resumed run continues exactly as the uninterrupted one. Outputs under ``out_dir``:
``checkpoints/step_*`` (:mod:`dualflow.checkpoint`), ``latest.json``, ``final/`` (EMA weights)
and ``train_log.csv``. What one step does: docs/model.md.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import datetime as _dt
import itertools
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import torch
import torch.distributed as dist
import yaml
from safetensors.torch import save_file
from torch.nn.parallel import DistributedDataParallel
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from dualflow.checkpoint import checkpoint_text_encoder, load_checkpoint, replace_directory, save_checkpoint
from dualflow.datasets.config import SYNTHETIC, TrainingDataConfig
from dualflow.datasets.training import make_datasets
from dualflow.errors import DualFlowError
from dualflow.flow import StepSettings, TimeSampler, flow_training_step
from dualflow.losses import LossSettings, LossWeights, step_losses
from dualflow.model import Conditions, DualFlow, DualFlowConfig, sample_condition_drop
from dualflow.retrieval import RagConfig
from dualflow.text import as_text_embedder

#: music condition: none; beats (the 4-d beat track, any dataset); edge35 / duolando54 (spectral
#: features: the dataset's own, or on the synthetic duets those of a rendered click track);
#: jukebox (4800-d precomputed features the dataset ships, e.g. MDD with data.options.music: jukebox).
MUSIC_SOURCES = ("none", "beats", "edge35", "duolando54", "jukebox")
#: music setting -> dualflow.music kind of the per-frame features
MUSIC_KIND = {"beats": "beats4", "edge35": "edge35", "duolando54": "duolando54", "jukebox": "jukebox"}
#: "paper": L_flow + triplet + geometric + interaction losses (dualflow.losses, eq. 10);
#: "flow": L_flow alone.
LOSS_SETS = ("paper", "flow")
AMP_MODES = ("auto", "bf16", "off")


# ---------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs; loadable from yaml/json (:func:`load_train_config`).

    preset / model: the DualFlowConfig preset and field overrides (e.g. {"width": 64}).
    data: :class:`dualflow.datasets.config.TrainingDataConfig` fields: the synthetic duets (default) or any dataset
    by name (``dataset``, ``root``, ``splits``, ``stride``, ``options``). music: "none" (music
    absent, learned null), "beats" (the 4-d beat track; model.music_dim = 4), "edge35" /
    "duolando54" (spectral features, music_dim 35 / 54) or "jukebox" (precomputed, 4800).
    retrieval: :class:`dualflow.retrieval.RagConfig` fields ({enabled: true} trains with RAG).
    steps, batch_size (per process), lr, weight_decay, warmup_steps, betas, grad_clip
    (0 = off), ema_decay (0 = off), reactive_prob, look_ahead (None = model default),
    time_sampler ("uniform" | "logit_normal" with time_mean, time_std: t = sigmoid(N(mean, std));
    a negative mean shifts training towards the noise end, t = 0), cfg_drop (classifier-free-guidance drops),
    uncued_rules (synthetic data only; empty = every duet): the follower rules whose duets may lose
    their text in a drop; the other rules' duets keep it, so the partner made without a text cue
    learns only these rules (e.g. [hand_hold, orbit], the two that face the leader),
    losses ("paper": flow + triplet + geometric + interaction terms of dualflow.losses with
    the synthetic rule as the triplet label; "flow": the flow loss alone), loss_weights
    (LossWeights overrides, e.g. {"sync": 0}).
    out_dir, log_every, ckpt_every (0 = only at the end), keep_last checkpoints,
    val_every (0 = off; validation flow loss on the val split), seed, device
    ("auto" | "cpu" | "cuda"), amp ("auto": bf16 autocast on CUDA only), threads
    (torch intra-op threads per process, 0 = leave the default), progress bar,
    save_replicas, export_dtype ("float32" | "float16" for final/model.safetensors),
    max_minutes (0 = no limit): stop after this much wall time (checked every step, agreed
    across ranks), then checkpoint and export as at the end; the step reached is in the
    checkpoint, so ``--steps`` reproduces the run. data_cache: a directory where the generated
    synthetic splits are kept as npz (empty = regenerate every run); data_workers: processes that
    generate them (0 = this one; the clips are the same either way). text_encoder: "hashed"
    (the bag-of-words stand-in, dualflow.text.template_text_embedding) or "minilm"
    (dualflow.text, 384-d; model.text_dim must match); text_cache: its embedding cache dir.
    """

    preset: str = "small"
    model: dict = field(default_factory=dict)
    data: dict = field(default_factory=dict)
    music: str = "none"
    retrieval: dict = field(default_factory=dict)
    steps: int = 2000
    batch_size: int = 16
    lr: float = 2e-4
    weight_decay: float = 2e-5
    warmup_steps: int = 1000
    betas: tuple[float, float] = (0.9, 0.999)
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    reactive_prob: float = 0.5
    look_ahead: int | None = None
    time_sampler: str = "uniform"
    time_mean: float = 0.0
    time_std: float = 1.0
    cfg_drop: bool = True
    uncued_rules: tuple[str, ...] = ()
    losses: str = "paper"
    loss_weights: dict = field(default_factory=dict)
    out_dir: str = "runs/dualflow"
    log_every: int = 10
    ckpt_every: int = 500
    keep_last: int = 2
    val_every: int = 0
    seed: int = 0
    device: str = "auto"
    amp: str = "auto"
    threads: int = 0
    progress: bool = True
    save_replicas: bool = False
    max_minutes: float = 0.0
    data_cache: str = ""
    data_workers: int = 0
    text_encoder: str = "hashed"
    text_cache: str = ""
    export_dtype: str = "float32"
    init_from: str = ""
    compile: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))
        object.__setattr__(self, "model", dict(self.model or {}))
        object.__setattr__(self, "data", dict(self.data or {}))
        object.__setattr__(self, "loss_weights", dict(self.loss_weights or {}))
        object.__setattr__(self, "retrieval", dict(self.retrieval or {}))
        if not isinstance(self.uncued_rules or (), (list, tuple)):  # a string is neither
            raise DualFlowError(
                "train config: uncued_rules must be a list of rules, e.g. [hand_hold, orbit]; "
                f"got {self.uncued_rules!r}"
            )
        object.__setattr__(self, "uncued_rules", tuple(self.uncued_rules or ()))
        checks = [
            (self.steps >= 1, "steps must be >= 1"),
            (self.batch_size >= 1, "batch_size must be >= 1"),
            (self.lr > 0, "lr must be > 0"),
            (self.weight_decay >= 0, "weight_decay must be >= 0"),
            (self.warmup_steps >= 0, "warmup_steps must be >= 0"),
            (len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas), "betas must be two numbers in [0, 1)"),
            (self.grad_clip >= 0, "grad_clip must be >= 0 (0 = off)"),
            (0 <= self.ema_decay < 1, "ema_decay must be in [0, 1) (0 = off)"),
            (0 <= self.reactive_prob <= 1, "reactive_prob must be in [0, 1]"),
            (self.look_ahead is None or self.look_ahead >= 0, "look_ahead must be >= 0 or null"),
            (self.music in MUSIC_SOURCES, f"music must be one of {MUSIC_SOURCES}"),
            (self.losses in LOSS_SETS, f"losses must be one of {LOSS_SETS}"),
            (self.amp in AMP_MODES, f"amp must be one of {AMP_MODES}"),
            (self.device in ("auto", "cpu", "cuda"), "device must be auto, cpu or cuda"),
            (self.log_every >= 1, "log_every must be >= 1"),
            (self.ckpt_every >= 0 and self.val_every >= 0, "ckpt_every and val_every must be >= 0"),
            (self.keep_last >= 1, "keep_last must be >= 1"),
            (self.max_minutes >= 0, "max_minutes must be >= 0 (0 = no limit)"),
            (self.data_workers >= 0, "data_workers must be >= 0 (0 = generate in this process)"),
            (self.text_encoder in ("hashed", "minilm"), "text_encoder must be 'hashed' or 'minilm'"),
            (
                self.export_dtype in ("float32", "float16", "bfloat16"),
                "export_dtype must be float32, float16 or bfloat16",
            ),
        ]
        for ok, message in checks:
            if not ok:
                raise DualFlowError(f"train config: {message}")
        TimeSampler(self.time_sampler, self.time_mean, self.time_std)
        self.loss_weights_config()
        self.model_config()
        self.data_config()
        self.rag_config()
        self.uncued_rule_mask()

    def uncued_rule_mask(self) -> tuple[bool, ...] | None:
        """Per data.rules entry: may its duets lose their text? None: every duet may."""
        if not self.uncued_rules:
            return None
        data = self.data_config()
        if data.dataset != SYNTHETIC:
            raise DualFlowError(
                f"train config: uncued_rules picks synthetic follower rules, but data.dataset is "
                f"{data.dataset!r}; remove uncued_rules for a dataset"
            )
        bad = [r for r in self.uncued_rules if r not in data.rules]
        if bad:
            raise DualFlowError(
                f"train config: uncued_rules {bad} are not among data.rules {list(data.rules)}; choose from those"
            )
        return tuple(r in self.uncued_rules for r in data.rules)

    def model_config(self) -> DualFlowConfig:
        try:
            cfg = DualFlowConfig.preset(self.preset, **self.model)
        except TypeError as exc:
            raise DualFlowError(f"train config: bad 'model' overrides {self.model}: {exc}") from None
        if self.music == "beats" and cfg.music_dim != 4:
            raise DualFlowError("train config: music 'beats' feeds the 4-d beat track; set model.music_dim: 4")
        if self.music in MUSIC_KIND:
            from dualflow.music import MUSIC_DIMS

            want = MUSIC_DIMS[MUSIC_KIND[self.music]]
            if cfg.music_dim != want:
                raise DualFlowError(
                    f"train config: music {self.music!r} gives {want}-d features; set model.music_dim: {want}"
                )
        return cfg

    def rag_config(self) -> RagConfig:
        return RagConfig.from_dict(self.retrieval, "train config 'retrieval'")

    def loss_weights_config(self) -> LossWeights:
        try:
            return LossWeights(**self.loss_weights)
        except TypeError:
            known = sorted(f.name for f in fields(LossWeights))
            raise DualFlowError(f"train config: bad loss_weights {self.loss_weights}; valid keys: {known}") from None

    def data_config(self) -> TrainingDataConfig:
        try:
            return TrainingDataConfig.from_dict(self.data, "train config 'data'")
        except TypeError as exc:
            raise DualFlowError(f"train config 'data': {exc}") from None

    def to_dict(self) -> dict:
        d = asdict(self)
        d["betas"] = list(self.betas)
        return d


def _parse_override(item: str) -> tuple[list[str], object]:
    if "=" not in item:
        raise DualFlowError(f"override {item!r}: expected key=value, e.g. steps=100 or model.width=64")
    key, value = item.split("=", 1)
    try:
        parsed = yaml.safe_load(value)
    except yaml.YAMLError:
        parsed = value
    return key.strip().split("."), parsed


def _coerce(name: str, value, type_name: str, where: str):
    """Numbers written as strings (YAML reads ``1e-3`` as a string) -> the field's type."""
    base = type_name.replace(" | None", "")
    if value is None and "None" in type_name:
        return None
    try:
        if base == "float" and not isinstance(value, bool):
            return float(value)
        if base == "int" and not isinstance(value, bool):
            as_float = float(value)
            if as_float != int(as_float):
                raise ValueError("not a whole number")
            return int(as_float)
        if base == "bool" and not isinstance(value, bool):
            raise ValueError("expected true or false")
        if base == "str" and not isinstance(value, str):
            raise ValueError("expected a string")
    except (TypeError, ValueError) as exc:
        raise DualFlowError(f"{where}: field {name!r} must be {base}, got {value!r} ({exc})") from None
    return value


def load_train_config(
    path: str | os.PathLike | None = None, overrides: list[str] | tuple[str, ...] = ()
) -> TrainConfig:
    """TrainConfig from a yaml or json file (or the defaults when ``path`` is None),
    then ``key=value`` overrides (dotted keys reach into ``model`` and ``data``)."""
    raw: dict = {}
    where = "defaults"
    if path is not None:
        where = str(path)
        p = Path(path)
        if not p.is_file():
            raise DualFlowError(f"{p}: training config file not found; see dualflow/configs/small_synthetic.yaml")
        try:
            raw = yaml.safe_load(p.read_bytes().decode("utf-8")) or {}
        except yaml.YAMLError as exc:
            raise DualFlowError(f"{p}: not valid yaml/json ({str(exc).splitlines()[0]})") from None
        except UnicodeDecodeError as exc:
            raise DualFlowError(
                f"{p}: not UTF-8 text (byte {exc.start}); a training config is a yaml or json file"
            ) from None
        except RecursionError:
            raise DualFlowError(f"{p}: nested too deeply to be a training config; fix the syntax") from None
        if not isinstance(raw, dict):
            raise DualFlowError(f"{p}: the training config must be a mapping of fields, got {type(raw).__name__}")
    for item in overrides:
        keys, value = _parse_override(item)
        node = raw
        for k in keys[:-1]:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise DualFlowError(f"override {item!r}: {k} is not a section")
        node[keys[-1]] = value
    types = {f.name: f.type for f in fields(TrainConfig)}
    unknown = sorted(set(raw) - set(types))
    if unknown:
        raise DualFlowError(f"{where}: unknown training field(s) {unknown}; valid fields: {sorted(types)}")
    raw = {k: _coerce(k, v, types[k], where) for k, v in raw.items()}
    try:
        return TrainConfig(**raw)
    except DualFlowError as exc:
        raise DualFlowError(f"{where}: {exc}") from None
    except TypeError as exc:
        raise DualFlowError(f"{where}: {exc}") from None


# ---------------------------------------------------------------------------------------------
# distributed context
# ---------------------------------------------------------------------------------------------


@dataclass
class DistContext:
    """rank / world size / device of this process; DDP when launched by torchrun (WORLD_SIZE > 1)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")
    initialised_here: bool = False

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @staticmethod
    def from_env(device: str = "auto") -> DistContext:
        """Read torchrun's RANK / WORLD_SIZE / LOCAL_RANK; start the process group
        (NCCL for CUDA, gloo for CPU) when more than one process runs."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        rank = int(os.environ.get("RANK", "0"))
        local = int(os.environ.get("LOCAL_RANK", "0"))
        use_cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
        if device == "cuda" and not torch.cuda.is_available():
            raise DualFlowError("train config: device is 'cuda' but no CUDA device is available; use device: cpu")
        dev = torch.device(f"cuda:{local}") if use_cuda else torch.device("cpu")
        if use_cuda:
            torch.cuda.set_device(dev)
        ctx = DistContext(rank, world, local, dev)
        if world > 1 and not dist.is_initialized():
            dist.init_process_group(backend="nccl" if use_cuda else "gloo")
            ctx.initialised_here = True
        return ctx

    def barrier(self) -> None:
        if self.distributed:
            dist.barrier()

    def close(self) -> None:
        if self.initialised_here and dist.is_initialized():
            dist.destroy_process_group()


# ---------------------------------------------------------------------------------------------
# small helpers with one job each
# ---------------------------------------------------------------------------------------------


def warmup_lr(base_lr: float, step: int, warmup_steps: int) -> float:
    """lr_s = base_lr · min(1, (s + 1) / warmup_steps) (constant after the warm-up)."""
    if warmup_steps <= 0:
        return base_lr
    return base_lr * min(1.0, (step + 1) / warmup_steps)


def step_seed(*parts: int) -> int:
    """A 63-bit seed mixed from integers (splitmix64 over the parts)."""
    x = 0x9E3779B97F4A7C15
    for p in parts:
        x = (x ^ (int(p) & 0xFFFFFFFFFFFFFFFF)) * 0xBF58476D1CE4E5B9 & 0xFFFFFFFFFFFFFFFF
        x = (x ^ (x >> 31)) * 0x94D049BB133111EB & 0xFFFFFFFFFFFFFFFF
    return x & 0x7FFFFFFFFFFFFFFF


class CsvLog:
    """Append-only CSV of training metrics; on resume rows after the resumed step are dropped."""

    TERMS = ("flow", "triplet", "foot", "vel", "bone", "dm", "ro", "sync")
    COLUMNS = ("step", "mode", "loss") + TERMS + ("lr", "grad_norm", "val_loss", "elapsed_s", "samples_per_s")

    def __init__(self, path: Path, resume_step: int | None):
        self.path = path
        rows = []
        if resume_step is not None and path.is_file():
            with open(path, newline="") as fh:
                rows = [r for r in csv.DictReader(fh) if int(r["step"]) <= resume_step]
        tmp = path.with_name(path.name + ".partial")
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, self.COLUMNS)
            w.writeheader()
            w.writerows(rows)
        os.replace(tmp, path)

    def write(self, row: dict) -> None:
        with open(self.path, "a", newline="") as fh:
            csv.DictWriter(fh, self.COLUMNS).writerow({k: row.get(k, "") for k in self.COLUMNS})


@dataclass
class TrainResult:
    """What a run produced: final step, last logged loss, paths, seconds, replica check."""

    step: int
    loss: float
    out_dir: Path
    final_checkpoint: Path | None
    log_path: Path
    seconds: float
    replica_max_abs_diff: float | None = None


# ---------------------------------------------------------------------------------------------
# the trainer
# ---------------------------------------------------------------------------------------------


def ema_update(ema: AveragedModel, model: torch.nn.Module, decay: float) -> None:
    """``ema.update_parameters(model)`` for an EMA made with ``get_ema_multi_avg_fn(decay)``, the
    same arithmetic (a copy at the first update, then lerp(ema, theta, 1 - decay) for parameters and
    buffers) without reading ``n_averaged`` on the host each step (two device syncs per step on a
    GPU). Whether the EMA has started is read once per EMA and kept (``_dualflow_started``)."""
    started = getattr(ema, "_dualflow_started", None)
    if started is None:
        started = bool(ema.n_averaged > 0)
    mine = [p.detach() for p in itertools.chain(ema.module.parameters(), ema.module.buffers())]
    theirs = [p.detach().to(q.device) for p, q in zip(itertools.chain(model.parameters(), model.buffers()), mine)]
    with torch.no_grad():
        if started:
            torch._foreach_lerp_(mine, theirs, 1.0 - decay)
        else:
            torch._foreach_copy_(mine, theirs)
        ema.n_averaged += 1
    ema._dualflow_started = True


class Trainer:
    """Builds data, model, optimiser, EMA from a TrainConfig and runs the loop (module docstring)."""

    def __init__(self, config: TrainConfig, resume: bool = False, ctx: DistContext | None = None):
        self.config = config
        self.ctx = ctx or DistContext.from_env(config.device)
        if config.threads > 0:
            torch.set_num_threads(config.threads)
        self.out_dir = Path(config.out_dir)
        self.model_config = config.model_config()
        self.data_config = config.data_config()
        mask = config.uncued_rule_mask()
        self.uncued = None if mask is None else torch.tensor(mask, device=self.ctx.device)
        self.text_encoder = checkpoint_text_encoder(
            {"text_encoder_name": config.text_encoder}, self.model_config.text_dim, config.text_cache or None
        )
        init = self._init_checkpoint()
        self._build_data(init)
        self._build_model(init)
        self._build_optimizer()
        self.step = 0
        self.resumed_from: Path | None = None
        if resume:
            self._resume()
        if config.compile:  # after the EMA copy: only the trained model runs compiled
            from dualflow.compile import compile_blocks

            compile_blocks(self.model)
        self._wrap_for_training()
        self.time_sampler = TimeSampler(config.time_sampler, config.time_mean, config.time_std)
        self.loss_weights = config.loss_weights_config()
        self.stats_mean = torch.tensor(self.stats.mean, dtype=torch.float32, device=self.ctx.device)
        self.stats_std = torch.tensor(self.stats.std, dtype=torch.float32, device=self.ctx.device)
        use_amp = config.amp == "bf16" or (config.amp == "auto" and self.ctx.device.type == "cuda")
        self.autocast_dtype = torch.bfloat16 if use_amp else None

    # -- construction ---------------------------------------------------------------------

    def _init_checkpoint(self):
        """The checkpoint named by ``init_from`` (fine-tuning), or None; its model config must match."""
        config = self.config
        if not config.init_from:
            return None
        init = load_checkpoint(config.init_from)
        if init.config != self.model_config:
            raise DualFlowError(
                f"init_from {config.init_from}: its model config differs from this training "
                "config's; fine-tune with the same preset and model overrides"
            )
        return init

    def _build_data(self, init) -> None:
        """Training and validation sets and normalisation stats (the init checkpoint's when fine-tuning)."""
        config = self.config
        self.train_set, self.val_set, self.stats = make_datasets(
            self.data_config,
            self.model_config.text_dim,
            as_text_embedder(self.text_encoder),
            cache_dir=config.data_cache or None,
            music_kind=MUSIC_KIND.get(config.music),
            stats=None if init is None else init.stats,
            workers=config.data_workers,
        )
        self.music_kind = MUSIC_KIND.get(config.music)
        if self.music_kind is not None:
            self.train_set.music_of(self.music_kind)  # a clear error now when the data lacks that music
        if self.ctx.device.type == "cuda":  # batches gathered on the GPU (no per-step host copy), or pinned
            for ds in (self.train_set, self.val_set):
                if ds is not None:
                    ds.place(self.ctx.device)

    def _build_model(self, init) -> None:
        """The DualFlow model (seeded alike on every rank, or the init weights) and, with RAG, retrieval."""
        torch.manual_seed(step_seed(self.config.seed, 0xA11CE))  # identical initial weights on every rank
        self.model = DualFlow(self.model_config).to(self.ctx.device)
        if init is not None:
            self.model.load_state_dict(init.state_dict)
        self.rag = self.config.rag_config()
        self.retrieval_encoder = self.retriever = self.val_retriever = None
        if self.rag.enabled:
            self._build_retrieval()

    def _build_optimizer(self) -> None:
        """AdamW over the model (and retrieval encoder) and, when ``ema_decay`` > 0, their EMA copies."""
        config = self.config
        # fused AdamW on a GPU: one kernel for all parameters, step counters on the device (no host reads)
        self.optimizer = torch.optim.AdamW(
            self._parameters(),
            lr=config.lr,
            weight_decay=config.weight_decay,
            betas=config.betas,
            fused=True if self.ctx.device.type == "cuda" else None,
        )
        self.ema = self.retrieval_ema = None
        if config.ema_decay > 0:
            self.ema = AveragedModel(self.model, multi_avg_fn=get_ema_multi_avg_fn(config.ema_decay), use_buffers=True)
            if self.retrieval_encoder is not None:
                self.retrieval_ema = AveragedModel(
                    self.retrieval_encoder, multi_avg_fn=get_ema_multi_avg_fn(config.ema_decay), use_buffers=True
                )

    def _wrap_for_training(self) -> None:
        """Freezes the unused music encoder and sets ``ddp``/``retrieval_ddp``: the modules themselves,
        or their DistributedDataParallel wrappers when distributed."""
        self.ddp = self.model
        self.retrieval_ddp = self.retrieval_encoder
        if self.config.music == "none":  # never fed: frozen, so that every trainable weight gets a gradient
            for part in (self.model.music_in, self.model.music_encoder, self.model.music_norm):
                part.requires_grad_(False)
        if self.ctx.distributed:
            ids = [self.ctx.device.index] if self.ctx.device.type == "cuda" else None
            # Every trainable weight takes part in every step (the music encoder is frozen when music
            # is absent; a reactive step touches the actor's output head with weight 0, train_step),
            # so DDP need not search the graph for unused ones after each backward. With retrieval,
            # a step whose cues are all dropped leaves parts of it out: there the search stays on.
            self.ddp = DistributedDataParallel(self.model, device_ids=ids, find_unused_parameters=self.rag.enabled)
            if self.retrieval_encoder is not None:
                self.retrieval_ddp = DistributedDataParallel(
                    self.retrieval_encoder, device_ids=ids, find_unused_parameters=True
                )

    # -- retrieval ------------------------------------------------------------------------

    def _build_retrieval(self) -> None:
        """Database of the training windows, neighbours of every training (and validation) window
        with its own clip excluded, and the retrieval encoder (dualflow.retrieval)."""
        from dualflow.retrieval import NeighbourTable, RetrievalConditioner, build_training_database, cue_queries

        def music_of(ds):
            return None if self.music_kind is None else ds.music_of(self.music_kind).numpy()

        db = build_training_database(self.train_set, self.rag, self.text_encoder, music_of(self.train_set))
        groups = self.train_set.groups
        queries = {c: db.embeddings[c] for c in db.cues}
        table = NeighbourTable.compute(db, queries, db.lengths, self.rag.max_depth, self.rag.lam, groups, groups)
        self.retriever = RetrievalConditioner(db, table, self.rag)
        if self.val_set is not None:
            vq = cue_queries(db, self.val_set.texts, music_of(self.val_set), self.text_encoder)
            vt = NeighbourTable.compute(db, vq, self.val_set.n_frames, self.rag.max_depth, self.rag.lam)
            self.val_retriever = RetrievalConditioner(db, vt, self.rag)
        torch.manual_seed(step_seed(self.config.seed, 0xBEEF))
        self.retrieval_encoder = self.rag.encoder(self.model_config.width, self.model_config.n_heads).to(
            self.ctx.device
        )

    def _parameters(self) -> list[torch.nn.Parameter]:
        params = list(self.model.parameters())
        if self.retrieval_encoder is not None:
            params += list(self.retrieval_encoder.parameters())
        return params

    def _retrieval_tokens(self, batch: dict, mode: str, drop_text=None, drop_music=None, validation: bool = False):
        """z_R (B, 2K, width) of the batch's windows, or None without RAG (dualflow.retrieval)."""
        if self.retrieval_encoder is None:
            return None
        if validation:
            if self.val_retriever is None:
                return None
            encoder = self.retrieval_ema.module if self.retrieval_ema is not None else self.retrieval_encoder
            return self.val_retriever.tokens(encoder, batch["index"].numpy(), mode, self.ctx.device)
        return self.retriever.tokens(
            self.retrieval_ddp,
            batch["index"].numpy(),
            mode,
            self.ctx.device,
            null=self.model.null_retrieval,
            drop_text=drop_text,
            drop_music=drop_music,
        )

    def _publish(self, write) -> Path:
        """Run ``write(directory) -> Path`` (a checkpoint writer) into a temporary sibling, add the
        retrieval files, then rename it into place: a checkpoint is complete or absent."""

        def with_rag(path: Path) -> Path:
            if self.retrieval_encoder is None:
                return write(path)
            from dualflow.retrieval import save_rag_files

            tmp = path.with_name(f".{path.name}.rag-{os.getpid()}")
            write(tmp)
            final = path.name == "final"
            encoder = (
                self.retrieval_ema.module if (final and self.retrieval_ema is not None) else self.retrieval_encoder
            )
            save_rag_files(
                tmp,
                encoder.state_dict(),
                db=self.retriever.db if final else None,
                ema_state=None if final or self.retrieval_ema is None else self.retrieval_ema.state_dict(),
            )
            replace_directory(tmp, path)
            return path

        return with_rag

    # -- checkpoints ----------------------------------------------------------------------

    def _meta(self) -> dict:
        return {
            "text_encoder": self.text_encoder.encoder_id,
            "text_encoder_name": self.config.text_encoder,
            "music": self.config.music,
            "retrieval": self.rag.to_dict(),
            "step": self.step,
            "train": self.config.to_dict(),
            "data": self.data_config.to_dict(),
            "synthetic": self.data_config.is_synthetic,
            "world_size": self.ctx.world_size,
            "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "torch": torch.__version__,
        }

    def _resume(self) -> None:
        latest = self.out_dir / "latest.json"
        if not latest.is_file():
            raise DualFlowError(f"{latest}: nothing to resume from (no checkpoint written yet); run without --resume")
        info = json.loads(latest.read_text())
        ckpt = load_checkpoint(self.out_dir / info["path"], resume=True)
        if ckpt.config != self.model_config:
            raise DualFlowError(
                f"{ckpt.path}: its model config differs from this training config; resume with the same config"
            )
        self.model.load_state_dict(ckpt.state_dict)
        if ckpt.optimizer_state is not None:
            self.optimizer.load_state_dict(ckpt.optimizer_state)
        if self.ema is not None and ckpt.ema_state is not None:
            self.ema.load_state_dict(ckpt.ema_state)
        if self.retrieval_encoder is not None:
            from safetensors.torch import load_file

            from dualflow.retrieval import ENCODER_EMA_FILE, ENCODER_FILE

            if not (ckpt.path / ENCODER_FILE).is_file():
                raise DualFlowError(
                    f"{ckpt.path}: lacks {ENCODER_FILE}; it was trained without retrieval, "
                    "resume with retrieval.enabled: false"
                )
            self.retrieval_encoder.load_state_dict(load_file(str(ckpt.path / ENCODER_FILE)))
            if self.retrieval_ema is not None and (ckpt.path / ENCODER_EMA_FILE).is_file():
                self.retrieval_ema.load_state_dict(load_file(str(ckpt.path / ENCODER_EMA_FILE)))
        self.step = int(ckpt.trainer_state["step"])
        self.resumed_from = ckpt.path

    def save(self) -> Path:
        """Write checkpoints/step_XXXXXXX (rank 0), update latest.json, prune old ones."""
        root = self.out_dir / "checkpoints"
        path = root / f"step_{self.step:07d}"
        self._publish(
            lambda p: save_checkpoint(
                p,
                model=self.model,
                stats=self.stats,
                meta=self._meta(),
                ema_state=None if self.ema is None else self.ema.state_dict(),
                optimizer=self.optimizer,
                trainer_state={"step": self.step},
            )
        )(path)
        tmp = self.out_dir / "latest.json.partial"
        tmp.write_text(json.dumps({"step": self.step, "path": str(path.relative_to(self.out_dir))}) + "\n")
        os.replace(tmp, self.out_dir / "latest.json")
        kept = sorted(p for p in root.glob("step_*") if p.is_dir())
        for old in kept[: -self.config.keep_last]:
            for f in old.iterdir():
                f.unlink()
            old.rmdir()
        return path

    def export(self) -> Path:
        """out_dir/final: inference checkpoint (EMA weights when EMA is on), no optimizer."""
        model = self.model
        if self.ema is not None:
            model = DualFlow(self.model_config)
            model.load_state_dict(self.ema.module.state_dict())
        meta = self._meta()
        meta["weights"] = "ema" if self.ema is not None else "raw"
        dtype = getattr(torch, self.config.export_dtype)
        return self._publish(
            lambda p: save_checkpoint(
                p, model=model, stats=self.stats, meta=meta, weights_dtype=None if dtype == torch.float32 else dtype
            )
        )(self.out_dir / "final")

    # -- one step -------------------------------------------------------------------------

    def _music(self, batch: dict) -> torch.Tensor | None:
        if self.music_kind is None:
            return None
        return (batch["beats"] if self.music_kind == "beats4" else batch["music"]).to(self.ctx.device)

    def _conditions(self, batch: dict, gen: torch.Generator, mode: str = "interactive") -> Conditions:
        dev = self.ctx.device
        b = batch["text"].shape[0]
        music = self._music(batch)
        drop_text = drop_music = None
        if self.config.cfg_drop:
            drop_text, drop_music = sample_condition_drop(b, gen, dev)
            if self.uncued is not None:  # duets of the other rules keep their text
                drop_text = drop_text & self.uncued[batch["rule"].to(dev)]
        retrieval = self._retrieval_tokens(batch, mode, drop_text, drop_music)
        return Conditions(
            text=batch["text"].to(dev),
            music=music,
            retrieval=retrieval,
            drop_text=drop_text,
            drop_music=drop_music if music is not None else None,
        )

    def train_step(self, sync: bool = True) -> dict:
        """One optimiser step; returns its log row. sync=False: the row's loss terms and gradient
        norm stay tensors on the device (no host synchronisation, no cross-rank loss mean);
        ``run`` syncs only on the steps it logs (``row_values``)."""
        cfg, ctx = self.config, self.ctx
        shared = torch.Generator().manual_seed(step_seed(cfg.seed, self.step))
        mode = "reactive" if torch.rand(1, generator=shared).item() < cfg.reactive_prob else "interactive"
        seed = step_seed(cfg.seed, self.step, ctx.rank + 1)
        gen = torch.Generator().manual_seed(seed)
        torch.manual_seed(step_seed(cfg.seed, self.step, ctx.rank + 1, 7))  # dropout masks
        idx = torch.randint(len(self.train_set), (cfg.batch_size,), generator=gen)
        if ctx.device.type != "cpu":  # noise, t and CFG drops drawn where the batch lives (CPU: one stream, as before)
            gen = torch.Generator(device=ctx.device).manual_seed(seed)
        batch = self.train_set.batch(idx)
        lr = warmup_lr(cfg.lr, self.step, cfg.warmup_steps)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        self.ddp.train()
        if self.retrieval_ddp is not None:
            self.retrieval_ddp.train()
        amp = (
            torch.autocast(ctx.device.type, dtype=self.autocast_dtype)
            if self.autocast_dtype is not None
            else contextlib.nullcontext()
        )
        with amp:
            cond = self._conditions(batch, gen, mode)
            x_a = batch["actor"].to(ctx.device, non_blocking=True)
            x_b = batch["reactor"].to(ctx.device, non_blocking=True)
            out = flow_training_step(
                self.ddp,
                x_a,
                x_b,
                cond,
                mode=mode,
                settings=StepSettings(time_sampler=self.time_sampler, look_ahead=cfg.look_ahead),
                generator=gen,
            )
            terms = {"flow": out.loss}
            if cfg.losses == "paper":
                terms = step_losses(
                    out,
                    x_a,
                    x_b,
                    self.stats_mean,
                    self.stats_std,
                    mode=mode,
                    text=cond.text,
                    labels=batch["rule"].to(ctx.device),
                    settings=LossSettings(weights=self.loss_weights),
                )
                loss = terms.pop("total")
            else:
                loss = out.loss
        loss = loss.float()
        if ctx.distributed and mode == "reactive":  # the actor's output head, with weight 0 (see __init__)
            head = self.model.out_a
            loss = loss + 0.0 * (head.weight.sum() + head.bias.sum())
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        params = [p for p in self._parameters() if p.requires_grad]
        if cfg.grad_clip > 0:
            grad_norm = torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        else:
            grad_norm = torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in params if p.grad is not None]))
        self.optimizer.step()
        if self.ema is not None:
            ema_update(self.ema, self.model, cfg.ema_decay)
        if self.retrieval_ema is not None:
            ema_update(self.retrieval_ema, self.retrieval_encoder, cfg.ema_decay)
        self.step += 1
        row = {"step": self.step, "mode": mode, "loss": loss.detach(), "lr": lr, "grad_norm": grad_norm.detach()}
        row.update({k: v.detach() for k, v in terms.items()})  # this rank's terms (the loss is the rank mean)
        return self.row_values(row) if sync else row

    def row_values(self, row: dict) -> dict:
        """A ``train_step(sync=False)`` row with its tensors as floats (one host sync); the loss
        averaged over the ranks (a collective: every rank calls it on the same steps)."""
        out = dict(row)
        if torch.is_tensor(out["loss"]):
            loss_value = out["loss"].clone()
            if self.ctx.distributed:
                dist.all_reduce(loss_value)
                loss_value /= self.ctx.world_size
            out["loss"] = loss_value
        return {k: float(v) if torch.is_tensor(v) else v for k, v in out.items()}

    @torch.no_grad()
    def validation_loss(self, n_batches: int = 4) -> float:
        """Mean reactive flow loss on the val split with fixed noise (seeded), EMA weights if on."""
        if self.val_set is None:
            return float("nan")
        model = self.ema.module if self.ema is not None else self.model
        model.eval()
        gen = torch.Generator().manual_seed(step_seed(self.config.seed, 0x5A1))
        n = len(self.val_set)
        bs = max(1, min(self.config.batch_size, n))
        losses = []
        for start in range(0, min(n, bs * n_batches), bs):
            idx = torch.arange(start, min(start + bs, n))
            batch = self.val_set.batch(idx)
            if self.retrieval_encoder is not None:
                (self.retrieval_ema.module if self.retrieval_ema is not None else self.retrieval_encoder).eval()
            cond = Conditions(
                text=batch["text"].to(self.ctx.device),
                music=self._music(batch),
                retrieval=self._retrieval_tokens(batch, "reactive", validation=True),
            )
            out = flow_training_step(
                model,
                batch["actor"].to(self.ctx.device),
                batch["reactor"].to(self.ctx.device),
                cond,
                mode="reactive",
                settings=StepSettings(time_sampler=self.time_sampler, look_ahead=self.config.look_ahead),
                generator=gen,
            )
            losses.append(float(out.loss))
        return sum(losses) / len(losses)

    def _out_of_time(self, t0: float) -> bool:
        """True once max_minutes of wall time have passed (rank 0's clock decides for all)."""
        if self.config.max_minutes <= 0:
            return False
        flag = torch.tensor(float(time.perf_counter() - t0 > 60.0 * self.config.max_minutes))
        if self.ctx.distributed:
            flag = flag.to(self.ctx.device)
            dist.broadcast(flag, src=0)
        return bool(flag.item())

    def replica_max_abs_diff(self) -> float:
        """max |θ_rank − θ_rank0| over all parameters and ranks (0.0 in one process)."""
        if not self.ctx.distributed:
            return 0.0
        worst = torch.zeros((), device=self.ctx.device)
        for p in self.model.parameters():
            ref = p.detach().clone()
            dist.broadcast(ref, src=0)
            worst = torch.maximum(worst, (p.detach() - ref).abs().max())
        dist.all_reduce(worst, op=dist.ReduceOp.MAX)
        return float(worst)

    # -- the loop -------------------------------------------------------------------------

    def run(self) -> TrainResult:
        cfg, ctx = self.config, self.ctx
        from tqdm import tqdm

        log = None
        if ctx.is_main:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            (self.out_dir / "train_config.json").write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")
            log = CsvLog(self.out_dir / "train_log.csv", self.step if self.resumed_from else None)
        ctx.barrier()
        bar = tqdm(
            total=cfg.steps,
            initial=self.step,
            disable=not (ctx.is_main and cfg.progress),
            desc="train",
            unit="step",
            dynamic_ncols=True,
        )
        t0 = time.perf_counter()
        start_step = self.step
        last = {"loss": float("nan")}
        while self.step < cfg.steps:
            if self._out_of_time(t0):
                break
            step = self.step + 1  # sync (tensors -> floats) only on the steps that are logged or shown
            logged = step % cfg.log_every == 0 or step == cfg.steps or (cfg.val_every and step % cfg.val_every == 0)
            last = self.train_step(sync=False)
            bar.update(1)
            if logged or cfg.progress:  # the same steps on every rank (row_values is a collective)
                last = self.row_values(last)
                if not math.isfinite(last["loss"]):
                    raise DualFlowError(
                        f"training diverged by step {self.step} (loss {last['loss']}); lower lr or raise warmup_steps"
                    )
                bar.set_postfix(loss=f"{last['loss']:.4f}", lr=f"{last['lr']:.1e}", mode=last["mode"][0])
            val = None
            if cfg.val_every and self.step % cfg.val_every == 0:
                val = self.validation_loss()
            if ctx.is_main and (self.step % cfg.log_every == 0 or val is not None or self.step == cfg.steps):
                elapsed = time.perf_counter() - t0
                done = self.step - start_step
                log.write(
                    {
                        **{k: f"{last[k]:.6f}" for k in CsvLog.TERMS if k in last},
                        "step": last["step"],
                        "mode": last["mode"],
                        "val_loss": "" if val is None else f"{val:.6f}",
                        "loss": f"{last['loss']:.6f}",
                        "lr": f"{last['lr']:.3e}",
                        "grad_norm": f"{last['grad_norm']:.4f}",
                        "elapsed_s": f"{elapsed:.2f}",
                        "samples_per_s": f"{done * cfg.batch_size * ctx.world_size / max(elapsed, 1e-9):.2f}",
                    }
                )
            if cfg.ckpt_every and self.step % cfg.ckpt_every == 0 and self.step < cfg.steps:
                if ctx.is_main:
                    self.save()
                ctx.barrier()
        bar.close()
        last = self.row_values(last) if any(torch.is_tensor(v) for v in last.values()) else last
        final = None
        if ctx.is_main:
            self.save()
            final = self.export()
        replica = self.replica_max_abs_diff() if ctx.distributed else None
        if cfg.save_replicas:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            weights = {k: v.detach().cpu().contiguous() for k, v in self.model.state_dict().items()}
            save_file(weights, str(self.out_dir / f"replica_rank{ctx.rank}.safetensors"))
        ctx.barrier()
        return TrainResult(
            step=self.step,
            loss=last["loss"],
            out_dir=self.out_dir,
            final_checkpoint=final,
            log_path=self.out_dir / "train_log.csv",
            seconds=time.perf_counter() - t0,
            replica_max_abs_diff=replica,
        )


def train(config: TrainConfig, resume: bool = False) -> TrainResult:
    """Run a training job in this process (DDP when launched by torchrun)."""
    trainer = Trainer(config, resume=resume)
    try:
        return trainer.run()
    finally:
        trainer.ctx.close()


# ---------------------------------------------------------------------------------------------
# command line (shared by ``dualflow-bridge train`` and ``python -m dualflow.train``)
# ---------------------------------------------------------------------------------------------


def run_from_args(args: argparse.Namespace) -> int:
    if args.print_params:
        from dualflow.model import parameter_report

        print(parameter_report())
        return 0
    if args.evaluate:
        from dualflow.evaluation.reactor import evaluate_checkpoint

        errors = evaluate_checkpoint(
            None if args.evaluate == "bundled" else args.evaluate, n_clips=args.eval_clips, mid_dance=args.mid_dance
        )
        print(errors.summary())
        return 0
    overrides = list(args.overrides)
    if args.out_dir:
        overrides.append(f"out_dir={args.out_dir}")
    if args.steps is not None:
        overrides.append(f"steps={args.steps}")
    config = load_train_config(args.config, overrides)
    result = train(config, resume=args.resume)
    if int(os.environ.get("RANK", "0")) == 0:
        print(f"trained to step {result.step} in {result.seconds:.1f} s, last loss {result.loss:.4f}")
        print(f"checkpoint: {result.final_checkpoint}")
        print(f"log: {result.log_path}")
        if result.replica_max_abs_diff is not None:
            print(
                f"replica max |diff| across {os.environ.get('WORLD_SIZE')} processes: {result.replica_max_abs_diff:.3e}"
            )
    return 0


def main(argv: list[str] | None = None) -> int:
    from dualflow.train_cli import add_arguments

    parser = argparse.ArgumentParser(prog="python -m dualflow.train", description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run_from_args(args)
    except DualFlowError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
