"""DualFlow checkpoints: safetensors weights + json config + npz statistics. No pickle.

Contract: a checkpoint is a folder ``model.safetensors`` (EMA weights when exported),
``config.json`` ({"format", "version", "model", "text_encoder", "music", "data", "train", ...})
and ``norm_stats.npz``; training checkpoints add ``ema.safetensors``, ``optimizer.safetensors``
and ``trainer_state.json`` for resuming. Loading runs no code; folders are written under a
temporary name and renamed (complete or absent). :data:`BUNDLED_CHECKPOINT` is the shipped
``small`` model trained on the synthetic duets (its README.md reproduces it).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from dualflow.errors import DualFlowError
from dualflow.model import DualFlow, DualFlowConfig, fuse_old_modulations
from dualflow.motion.normalization import NormStats

FORMAT = "dualflow-checkpoint"
VERSION = 1
MODEL_FILE = "model.safetensors"
EMA_FILE = "ema.safetensors"
OPTIMIZER_FILE = "optimizer.safetensors"
CONFIG_FILE = "config.json"
STATS_FILE = "norm_stats.npz"
TRAINER_STATE_FILE = "trainer_state.json"

#: The small synthetic-duet model shipped inside the package.
BUNDLED_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "synthetic_small"


@dataclass
class Checkpoint:
    """A loaded checkpoint (weights on the CPU).

    config: the model's DualFlowConfig; state_dict: weights to build it with;
    stats: NormStats of the training features; meta: the rest of config.json;
    ema_state: the EMA model's state (training checkpoints), else None;
    optimizer_state / trainer_state: for resuming, else None; path: the directory;
    converted: the weights predate the fused adaptive-LayerNorm linear and were converted on
    load (same function; ``dualflow.model.fuse_old_modulations``).
    """

    config: DualFlowConfig
    state_dict: dict[str, torch.Tensor]
    stats: NormStats
    meta: dict
    path: Path
    ema_state: dict[str, torch.Tensor] | None = None
    optimizer_state: dict | None = None
    trainer_state: dict = field(default_factory=dict)
    converted: bool = False  # weights written before issue 28's fused modulation, converted on load

    @property
    def text_encoder(self) -> str:
        """Id of the text encoder the model was trained with (config.json "text_encoder")."""
        return str(self.meta.get("text_encoder", ""))

    def make_text_encoder(self, cache_dir: str | os.PathLike | None = None):
        """That encoder, ready to embed prompts: ``encode(texts) -> (N, text_dim)``."""
        return checkpoint_text_encoder(self.meta, self.config.text_dim, cache_dir)

    def build_model(self, device: str | torch.device = "cpu", use_ema: bool = True) -> DualFlow:
        """The network in eval mode on ``device``, float32, EMA weights when present and asked."""
        model = DualFlow(self.config)
        state = self.state_dict
        if use_ema and self.ema_state is not None:
            state = ema_module_state(self.ema_state)
        missing, unexpected = model.load_state_dict({k: v.float() for k, v in state.items()}, strict=False)
        if missing or unexpected:
            raise DualFlowError(
                f"{self.path / MODEL_FILE}: weights do not match the model in {CONFIG_FILE} "
                f"(missing {missing[:3]}, unexpected {unexpected[:3]}); the checkpoint is from another model version"
            )
        return model.to(device).eval()


def checkpoint_text_encoder(meta: dict, dim: int, cache_dir: str | os.PathLike | None = None):
    """The text encoder a checkpoint was trained with (``dualflow.text.TextEncoder``).

    meta["text_encoder_name"]: "minilm" or "hashed" (checkpoints without the field used the
    hashed bag-of-words stand-in); dim: the model's text_dim; cache_dir: embedding cache.
    Embed prompts for this checkpoint's model with ``encoder.encode(texts)``.
    """
    from dualflow.text import make_text_encoder

    name = str(meta.get("text_encoder_name", "hashed"))
    return make_text_encoder(name, dim=int(dim), cache_dir=cache_dir)


def ema_module_state(ema_state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The wrapped model's weights from a ``torch.optim.swa_utils.AveragedModel`` state."""
    return {k[len("module.") :]: v for k, v in ema_state.items() if k.startswith("module.")}


# ---------------------------------------------------------------------------------------------
# optimizer state <-> flat tensors + json
# ---------------------------------------------------------------------------------------------


def optimizer_to_tensors(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], list[dict]]:
    """Split an optimizer's state_dict into tensors "state/<index>/<name>" and json param_groups."""
    sd = optimizer.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    for index, state in sd["state"].items():
        for name, value in state.items():
            t = value if isinstance(value, torch.Tensor) else torch.tensor(value)
            tensors[f"state/{index}/{name}"] = t.detach().cpu().contiguous()
    groups = []
    for g in sd["param_groups"]:
        groups.append({k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()})
    return tensors, groups


def optimizer_from_tensors(tensors: dict[str, torch.Tensor], param_groups: list[dict]) -> dict:
    """Inverse of :func:`optimizer_to_tensors`: a state_dict for ``optimizer.load_state_dict``."""
    state: dict[int, dict] = {}
    for key, value in tensors.items():
        _, index, name = key.split("/", 2)
        state.setdefault(int(index), {})[name] = value
    groups = []
    for g in param_groups:
        g = dict(g)
        if "betas" in g:
            g["betas"] = tuple(g["betas"])
        groups.append(g)
    return {"state": state, "param_groups": groups}


# ---------------------------------------------------------------------------------------------
# save / load
# ---------------------------------------------------------------------------------------------


def _contiguous_cpu(state: dict[str, torch.Tensor], dtype: torch.dtype | None = None) -> dict[str, torch.Tensor]:
    out = {}
    for k, v in state.items():
        v = v.detach().cpu()
        if dtype is not None and v.is_floating_point():
            v = v.to(dtype)
        out[k] = v.contiguous().clone()
    return out


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")


def save_checkpoint(
    path: str | os.PathLike,
    *,
    model: DualFlow,
    stats: NormStats,
    meta: dict | None = None,
    ema_state: dict[str, torch.Tensor] | None = None,
    optimizer: torch.optim.Optimizer | None = None,
    trainer_state: dict | None = None,
    weights_dtype: torch.dtype | None = None,
) -> Path:
    """Write a checkpoint directory atomically (temp dir, then rename over ``path``).

    model: its config and weights; stats: NormStats; meta: json-able extras merged
    into config.json; ema_state: an AveragedModel state (saved as ema.safetensors);
    optimizer / trainer_state: resume information; weights_dtype: e.g.
    torch.float16 to store model.safetensors at half size (loading casts back
    to float32).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        weights = _contiguous_cpu(model.state_dict(), weights_dtype)
        save_file(weights, str(tmp / MODEL_FILE), metadata={"format": FORMAT, "version": str(VERSION)})
        if ema_state is not None:
            save_file(_contiguous_cpu(ema_state), str(tmp / EMA_FILE), metadata={"format": FORMAT})
        config = {"format": FORMAT, "version": VERSION, "model": model.config.to_dict()}
        config.update(meta or {})
        config["weights_dtype"] = str(weights_dtype or torch.float32).replace("torch.", "")
        _write_json(tmp / CONFIG_FILE, config)
        stats.save(tmp / STATS_FILE)
        if optimizer is not None or trainer_state is not None:
            state = dict(trainer_state or {})
            if optimizer is not None:
                tensors, groups = optimizer_to_tensors(optimizer)
                save_file(tensors, str(tmp / OPTIMIZER_FILE), metadata={"format": FORMAT})
                state["optimizer_param_groups"] = groups
            _write_json(tmp / TRAINER_STATE_FILE, state)
        _publish_permissions(tmp)
        replace_directory(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def replace_directory(tmp: Path, path: Path) -> None:
    """Put the finished directory ``tmp`` at ``path``, replacing what is there, so that a reader
    sees the old directory or the new one, never a half-written one (two renames on one file
    system; the old copy is removed afterwards)."""
    old = None
    if path.exists():
        old = path.with_name(f".{path.name}.old-{os.getpid()}")
        os.replace(path, old)
    os.replace(tmp, path)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _publish_permissions(directory: Path) -> None:
    """mkdtemp makes a 0700 directory and safetensors writes 0600 files; give the checkpoint
    the usual permissions (0755 directory, 0644 files, minus the process umask)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(directory, 0o755 & ~umask)
    for f in directory.iterdir():
        os.chmod(f, 0o644 & ~umask)


def _load_tensors(file: Path) -> dict[str, torch.Tensor]:
    try:
        return load_file(str(file))
    except (SafetensorError, OSError, ValueError) as exc:
        raise DualFlowError(f"{file}: not a readable safetensors file ({exc}); re-save the checkpoint") from None


def _read_json(file: Path) -> dict:
    """A JSON object from ``file``; DualFlowError naming it for anything else."""
    try:
        data = json.loads(file.read_bytes().decode("utf-8"))
    except OSError as exc:
        raise DualFlowError(f"{file}: cannot read ({exc.strerror})") from None
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise DualFlowError(
            f"{file}: not valid JSON ({str(exc)[:120]}); the file is damaged, re-export the checkpoint"
        ) from None
    if not isinstance(data, dict):
        raise DualFlowError(f"{file}: must hold a JSON object, got {type(data).__name__}; re-export the checkpoint")
    return data


def _model_config(section, file: Path) -> DualFlowConfig:
    """The ``model`` section as a DualFlowConfig, each field's JSON type checked against the
    dataclass's (ints are whole numbers, not booleans; floats finite; kernel sizes a list of
    whole numbers), so a damaged config is named here rather than failing deep in torch."""
    from dataclasses import fields as dataclass_fields

    if not isinstance(section, dict):
        raise DualFlowError(
            f"{file}, field 'model': must be an object of DualFlowConfig fields, got {type(section).__name__}"
        )
    defaults = DualFlowConfig()
    known = {f.name for f in dataclass_fields(DualFlowConfig)}
    for key, value in section.items():
        if key not in known:
            raise DualFlowError(
                f"{file}, field 'model.{key}': unknown (valid: {', '.join(sorted(known))}); "
                "the checkpoint is from another model version"
            )
        want = type(getattr(defaults, key))

        def is_int(v):
            return isinstance(v, int) and not isinstance(v, bool)

        if want is int:
            ok = is_int(value)
        elif want is float:
            ok = (is_int(value) or isinstance(value, float)) and np.isfinite(value)
        elif want is tuple:
            ok = isinstance(value, list) and len(value) <= 64 and all(is_int(v) for v in value)
        else:
            ok = isinstance(value, want)
        if not ok:
            raise DualFlowError(
                f"{file}, field 'model.{key}': expected {want.__name__}, got {value!r:.60}; the file is damaged"
            )
    try:
        return DualFlowConfig.from_dict(section)
    except (TypeError, ValueError) as exc:
        raise DualFlowError(f"{file}, field 'model': {exc}") from None


def _reference_state(config: DualFlowConfig) -> dict[str, torch.Tensor]:
    """The state_dict a model of ``config`` has (shapes and dtypes only: built on the meta
    device, nothing is allocated)."""
    with torch.device("meta"):
        return DualFlow(config).state_dict()


def _check_weights(state: dict[str, torch.Tensor], reference: dict[str, torch.Tensor], file: Path) -> None:
    """Weights that fit the model: the same names and shapes, floating point where the model's
    are, and finite; DualFlowError naming the file and the first offending tensor."""
    missing = [k for k in reference if k not in state]
    unexpected = [k for k in state if k not in reference]
    if missing or unexpected:
        raise DualFlowError(
            f"{file}: weights do not match the model in {CONFIG_FILE} (missing {missing[:3]}, unexpected "
            f"{unexpected[:3]}); the checkpoint is from another model version or damaged"
        )
    for key, ref in reference.items():
        value = state[key]
        if tuple(value.shape) != tuple(ref.shape):
            raise DualFlowError(
                f"{file}, tensor {key!r}: shape {tuple(value.shape)}, but the model in {CONFIG_FILE} has "
                f"{tuple(ref.shape)}; the config and the weights are from different models"
            )
        if ref.is_floating_point() and not value.is_floating_point():
            raise DualFlowError(
                f"{file}, tensor {key!r}: dtype {value.dtype}, expected floating point; the weights are "
                "damaged or converted wrongly, re-export the checkpoint"
            )
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise DualFlowError(
                f"{file}, tensor {key!r}: contains NaN or inf; the training diverged or the file is "
                "damaged, use an earlier checkpoint"
            )


def load_checkpoint(path: str | os.PathLike, *, resume: bool = False) -> Checkpoint:
    """Read a checkpoint directory (see the module docstring); ``resume`` also reads the
    optimizer and trainer state. Bad or missing files raise DualFlowError naming them."""
    path = Path(path)
    if not path.is_dir():
        raise DualFlowError(
            f"{path}: checkpoint directory not found; give a directory with {MODEL_FILE}, {CONFIG_FILE}, {STATS_FILE}"
        )
    for name in (MODEL_FILE, CONFIG_FILE, STATS_FILE):
        if not (path / name).is_file():
            raise DualFlowError(f"{path}: checkpoint lacks {name}; it is incomplete, re-export it")
    meta = _read_json(path / CONFIG_FILE)
    if meta.get("format") != FORMAT or "model" not in meta:
        raise DualFlowError(
            f"{path / CONFIG_FILE}: not a DualFlow checkpoint config (needs format={FORMAT!r} and 'model')"
        )
    version = meta.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise DualFlowError(
            f"{path / CONFIG_FILE}, field 'version': must be a whole number >= 1 (this code writes "
            f"{VERSION}), got {version!r}; the file is damaged"
        )
    if version > VERSION:
        raise DualFlowError(
            f"{path / CONFIG_FILE}: checkpoint version {version} is newer than this code ({VERSION}); "
            "update the package"
        )
    config = _model_config(meta["model"], path / CONFIG_FILE)
    state = _load_tensors(path / MODEL_FILE)
    converted = fuse_old_modulations(state)  # a checkpoint from before issue 28: same weights, fused
    reference = _reference_state(config)
    _check_weights(state, reference, path / MODEL_FILE)
    stats = NormStats.load(path / STATS_FILE)
    ema = _load_tensors(path / EMA_FILE) if (path / EMA_FILE).is_file() else None
    if ema is not None:
        fuse_old_modulations(ema)
        _check_weights(ema_module_state(ema), reference, path / EMA_FILE)
    ckpt = Checkpoint(
        config=config, state_dict=state, stats=stats, meta=meta, path=path, ema_state=ema, converted=converted
    )
    if resume:
        if not (path / TRAINER_STATE_FILE).is_file():
            raise DualFlowError(
                f"{path}: lacks {TRAINER_STATE_FILE}; this is an exported checkpoint and cannot be resumed"
            )
        if converted and (path / OPTIMIZER_FILE).is_file():
            raise DualFlowError(
                f"{path}: written before the fused adaptive-LayerNorm linear (issue 28); its optimizer "
                f"state has one entry per old linear and cannot be resumed. Start a new run from its "
                f"weights instead: --set init_from={path}"
            )
        ckpt.trainer_state = _read_json(path / TRAINER_STATE_FILE)
        if (path / OPTIMIZER_FILE).is_file():
            ckpt.optimizer_state = optimizer_from_tensors(
                _load_tensors(path / OPTIMIZER_FILE), ckpt.trainer_state.get("optimizer_param_groups", [])
            )
    return ckpt


def load_model(
    path: str | os.PathLike | None = None, device: str | torch.device = "cpu"
) -> tuple[DualFlow, Checkpoint]:
    """(model in eval mode, checkpoint) from ``path``, or the bundled checkpoint when None."""
    ckpt = load_checkpoint(bundled_checkpoint() if path is None else path)
    return ckpt.build_model(device), ckpt


def bundled_checkpoint() -> Path:
    """Path of the checkpoint shipped with the package; DualFlowError if it is missing."""
    if not (BUNDLED_CHECKPOINT / MODEL_FILE).is_file():
        raise DualFlowError(
            f"{BUNDLED_CHECKPOINT}: the bundled checkpoint is missing; reinstall the package or train one with "
            "`dualflow-bridge train --config dualflow/configs/small_synthetic.yaml`"
        )
    return BUNDLED_CHECKPOINT


def stats_arrays(stats: NormStats) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) float32 arrays of a NormStats, for building torch tensors."""
    return np.asarray(stats.mean, dtype=np.float32), np.asarray(stats.std, dtype=np.float32)
