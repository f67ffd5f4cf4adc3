"""How well a model reacts: reactor position error against the rule-generated follower.

For synthetic duets the right reactor is known (the follower rule), so a reactive
model can be scored directly:

    MPJPE = mean over clips, frames and the 22 joints of ‖p̂ − p‖ (metres),

with p̂ the position block of the generated, de-normalised reactor feature and p
the follower's positions, both in the actor's canonical frame. Two references
put the number in context:

* the same model with the actor masked out (the actor's normalised features set
  to 0, i.e. the training mean; text and everything else unchanged): what the
  model does without seeing the leader;
* a static pose: the training set's mean reactor pose (per joint, over every
  clip and frame), the best constant pose in the squared-error sense.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dualflow.datasets.training import DuetDataset, positions_from_normalized
from dualflow.flow import SamplingSettings, generate
from dualflow.model import Conditions, DualFlow


@dataclass(frozen=True)
class ReactorErrors:
    """Mean per-joint position errors in metres (see the module docstring)."""

    model: float
    actor_masked: float
    static_pose: float
    n_clips: int
    steps: int

    def summary(self) -> str:
        return (
            f"reactor MPJPE over {self.n_clips} clips, {self.steps} Euler steps: "
            f"model {self.model:.3f} m | same model, actor masked {self.actor_masked:.3f} m | "
            f"static mean pose {self.static_pose:.3f} m"
        )


@torch.no_grad()
def generate_reactor(
    model: DualFlow,
    dataset: DuetDataset,
    indices,
    *,
    steps: int = 20,
    seed: int = 0,
    mask_actor: bool = False,
    music: bool = False,
) -> torch.Tensor:
    """Reactive generation for dataset clips ``indices``: (B, T, 262) normalised reactor."""
    idx = torch.as_tensor(list(indices))
    batch = dataset.batch(idx)
    device = next(model.parameters()).device
    actor = batch["actor"].to(device)
    if mask_actor:
        actor = torch.zeros_like(actor)
    cond = Conditions(text=batch["text"].to(device), music=batch["beats"].to(device) if music else None)
    _, reactor = generate(
        model, dataset.n_frames, cond, mode="reactive", x_actor=actor, sampling=SamplingSettings(steps=steps, seed=seed)
    )
    return reactor.cpu()


def mpjpe(pred_positions: np.ndarray, true_positions: np.ndarray) -> float:
    """Mean per-joint position error (m) of (..., 22, 3) arrays."""
    return float(np.linalg.norm(pred_positions - true_positions, axis=-1).mean())


def reactor_errors(
    model: DualFlow,
    dataset: DuetDataset,
    train_set: DuetDataset,
    *,
    steps: int = 20,
    seed: int = 0,
    batch_size: int = 16,
    music: bool = False,
) -> ReactorErrors:
    """Score ``model`` on every clip of ``dataset`` against its rule follower (module docstring).

    train_set supplies the static mean reactor pose.
    """
    stats = dataset.stats
    truth = positions_from_normalized(dataset.reactor, stats)  # (N, T, 22, 3)
    mean_pose = positions_from_normalized(train_set.reactor, stats).mean(axis=(0, 1))
    errors = {}
    for masked in (False, True):
        preds = []
        for start in range(0, len(dataset), batch_size):
            idx = range(start, min(start + batch_size, len(dataset)))
            x = generate_reactor(model, dataset, idx, steps=steps, seed=seed + start, mask_actor=masked, music=music)
            preds.append(positions_from_normalized(x, stats))
        errors[masked] = mpjpe(np.concatenate(preds), truth)
    static = mpjpe(np.broadcast_to(mean_pose, truth.shape), truth)
    return ReactorErrors(errors[False], errors[True], static, len(dataset), steps)


def evaluate_checkpoint(
    path=None, *, n_clips: int = 32, steps: int = 20, seed: int = 0, mid_dance: bool = False
) -> ReactorErrors:
    """Reactor errors of a checkpoint (default: the bundled one) on ``n_clips`` synthetic
    validation clips of the checkpoint's own data config (seeds disjoint from training),
    normalised with the checkpoint's statistics; the static pose is the mean reactor pose of
    as many training clips. Music is the beat track when the checkpoint was trained with it.
    mid_dance: every validation clip is instead cut at a random offset (up to 6 s, real speed,
    not mirrored) from a longer clip of the same seed (``dualflow.datasets.synthetic.crop_draw``):
    the windows a live stream sees after its first seconds."""
    from dataclasses import replace

    from dualflow.checkpoint import load_model
    from dualflow.datasets.config import TrainingDataConfig
    from dualflow.datasets.synthetic import build_split

    model, ck = load_model(path)
    data = ck.meta.get("data")
    if not isinstance(data, dict):
        from dualflow.errors import DualFlowError

        raise DualFlowError(f"{ck.path}: config.json has no 'data' section; it was not trained on synthetic duets")
    cfg = replace(TrainingDataConfig.from_dict(data), n_clips=n_clips, val_clips=n_clips)
    if mid_dance:
        cfg = replace(cfg, crop=1.0, crop_max_s=6.0, crop_speed=0.0, crop_mirror=0.0)
    from dualflow.text import as_text_embedder

    embed = as_text_embedder(ck.make_text_encoder())
    val = DuetDataset(build_split(cfg, "val", crop_any_split=mid_dance), ck.stats, model.config.text_dim, embed)
    train = DuetDataset(build_split(cfg, "train"), ck.stats, model.config.text_dim, embed)
    return reactor_errors(model, val, train, steps=steps, seed=seed, music=ck.meta.get("music") == "beats")
