"""The evaluation run: generate for every test clip, embed, score, replicate (InterGen's protocol).

Contract: :func:`evaluate` gives one results-table row from an :class:`EvalSet` (test clips cut
into windows, with texts and beats) and a generator mapping (clip indices, seed) to raw
features (B, T, 2, 262): :class:`CheckpointGenerator` (interactive or reactive) or ``None``
(the ground truth scores itself: FID about 0, multimodality NaN). Each metric is the mean
± 1.96 σ/√n over seeded replications.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from dualflow.datasets.collection import DuetSet
from dualflow.datasets.windows import window_split
from dualflow.errors import DualFlowError
from dualflow.evaluation import metrics as M
from dualflow.evaluation.rhythm import beat_alignment_score, beat_echo_degree
from dualflow.motion.features import FEATURE_SLICES

#: Column keys of a result row, in table order.
METRIC_KEYS = ("r1", "r2", "r3", "fid", "mm_dist", "diversity", "multimodality", "bed", "bas")

Generator = Callable[[np.ndarray, int], np.ndarray]


@dataclass
class EvalSet:
    """Ground truth of an evaluation (module docstring). beats (N, T, 4) is the per-frame
    beat track used as the music condition of beat-conditioned checkpoints; music (N, T, D)
    the windows' own per-frame music features of kind ``music_kind`` (None when absent)."""

    features: np.ndarray
    texts: list[str]
    beat_frames: list[np.ndarray]
    beats: np.ndarray
    fps: float = 30.0
    names: list[str] = field(default_factory=list)
    music: np.ndarray | None = None
    music_kind: str | None = None

    def __len__(self) -> int:
        return len(self.features)

    @staticmethod
    def from_duet_set(dset: DuetSet, frames: int, stride: int | None = None) -> EvalSet:
        ws = window_split(dset, frames, stride)
        beat_frames = [np.flatnonzero(b[:, 0] > 0.5) for b in ws.beats]
        fps = dset[0].fps if len(dset) else 30.0
        return EvalSet(
            ws.features, list(ws.texts), beat_frames, ws.beats, fps, list(ws.sources), ws.music, ws.music_kind
        )

    def music_for(self, kind: str) -> np.ndarray:
        """(N, T, D) music condition of ``kind`` for every window: the beat track ("beats4"), the
        windows' own features, or, where the data has only a beat track (the synthetic duets),
        the spectral features of its rendered click track (:func:`dualflow.datasets.synthetic.click_track_music`,
        as in training)."""
        if kind == "beats4":
            return self.beats
        if self.music is not None and self.music_kind == kind:
            return self.music
        if kind in ("edge35", "duolando54") and self.music_kind in (None, "beats4"):
            from dualflow.datasets.synthetic import click_track_music

            self.music = np.stack([click_track_music(b, kind, self.fps) for b in self.beats]).astype(np.float32)
            self.music_kind = kind
            return self.music
        raise DualFlowError(
            f"the checkpoint was trained with {kind!r} music but this evaluation data has "
            f"{self.music_kind or 'only a beat track'}; evaluate on data that has it"
        )


@dataclass(frozen=True)
class ProtocolConfig:
    """InterGen's numbers by default; shrink them for quick runs and tests."""

    batch_size: int = M.R_PRECISION_BATCH
    diversity_times: int = M.DIVERSITY_TIMES
    mm_samples: int = M.MM_NUM_SAMPLES
    mm_repeats: int = M.MM_NUM_REPEATS
    mm_times: int = M.MM_NUM_TIMES
    replications: int = M.REPLICATIONS
    mode: str = "interactive"

    def __post_init__(self) -> None:
        if self.mode not in ("interactive", "reactive"):
            raise DualFlowError(f"evaluation mode must be interactive or reactive, got {self.mode!r}")
        if min(self.batch_size, self.diversity_times, self.replications) < 1 or self.mm_repeats < 0:
            raise DualFlowError("evaluation: batch_size, diversity_times and replications must be >= 1")


def positions_of(features: np.ndarray) -> np.ndarray:
    """(..., T, 262) raw features -> (..., T, 22, 3) positions (canonical frame, metres)."""
    pos = np.asarray(features)[..., FEATURE_SLICES["positions"]]
    return pos.reshape(pos.shape[:-1] + (22, 3))


def rhythm_scores(features: np.ndarray, beat_frames: Sequence[np.ndarray], mode: str) -> tuple[float, float]:
    """(BAS, BED) means over clips; BAS over both people (interactive) or the reactor (reactive)."""
    bas, bed = [], []
    for f, beats in zip(features, beat_frames):
        actor, reactor = positions_of(f[:, 0]), positions_of(f[:, 1])
        people = [reactor] if mode == "reactive" else [actor, reactor]
        if len(beats):
            bas.extend(beat_alignment_score(p, beats) for p in people)
        bed.append(beat_echo_degree(actor, reactor))
    clean = lambda v: float(np.nanmean(v)) if len(v) and not np.all(np.isnan(v)) else float("nan")  # noqa: E731
    return clean(bas), clean(bed)


def evaluate(
    generator: Generator | None,
    data: EvalSet,
    evaluator,
    config: ProtocolConfig = ProtocolConfig(),
    gen_batch: int = 64,
) -> dict[str, M.Estimate]:
    """Score ``generator`` (None = the ground truth) on ``data`` (module docstring)."""
    n = len(data)
    if n < 2:
        raise DualFlowError("evaluation needs at least 2 test clips")
    gt_motion, text_emb = evaluator.embed(data.features, data.texts)
    all_idx = np.arange(n)

    def run(indices: np.ndarray, seed: int) -> np.ndarray:
        if generator is None:
            return data.features[indices]
        parts = [generator(indices[i : i + gen_batch], seed * 100_003 + i) for i in range(0, len(indices), gen_batch)]
        return np.concatenate(parts).astype(np.float32)

    values: dict[str, list[float]] = {k: [] for k in METRIC_KEYS}
    for rep in range(config.replications):
        rng = np.random.default_rng(rep)
        gen = run(all_idx, rep)
        motion_emb, _ = evaluator.embed(gen)
        rprec, mm = M.r_precision(text_emb, motion_emb, 3, config.batch_size, rng)
        for k in range(3):
            values[f"r{k + 1}"].append(float(rprec[k]))
        values["mm_dist"].append(mm)
        values["fid"].append(M.fid(motion_emb, gt_motion))
        values["diversity"].append(M.diversity(motion_emb, config.diversity_times, rng))
        if generator is not None and config.mm_repeats >= 2 and config.mm_samples >= 1:
            chosen = rng.choice(n, min(config.mm_samples, n), replace=False)
            reps = [
                evaluator.embed(run(chosen, 1_000 + rep * config.mm_repeats + j))[0] for j in range(config.mm_repeats)
            ]
            values["multimodality"].append(M.multimodality(np.stack(reps, axis=1), config.mm_times, rng))
        bas, bed = rhythm_scores(gen, data.beat_frames, config.mode)
        values["bas"].append(bas)
        values["bed"].append(bed)
    return {k: M.Estimate.of([x for x in v if not np.isnan(x)]) for k, v in values.items()}


class CheckpointGenerator:
    """A DualFlow checkpoint as a :data:`Generator` over an :class:`EvalSet` (module docstring).

    mode: "interactive" | "reactive"; steps: Euler steps (paper: 20); cfg_scale; look_ahead
    (None: the model's default L). Text is embedded with the checkpoint's text encoder id.
    """

    def __init__(
        self,
        checkpoint,
        data: EvalSet,
        *,
        mode: str = "interactive",
        steps: int = 20,
        cfg_scale: float = 1.0,
        look_ahead: int | None = None,
        device: str = "cpu",
    ):
        import torch

        from dualflow.checkpoint import load_checkpoint

        self.torch = torch
        self.ckpt = load_checkpoint(checkpoint)
        self.model = self.ckpt.build_model(device)
        self.device = device
        self.data, self.mode, self.steps, self.cfg_scale, self.look_ahead = data, mode, steps, cfg_scale, look_ahead
        self.stats = self.ckpt.stats
        self.text = torch.from_numpy(text_embedding(self.ckpt.text_encoder, data.texts, self.ckpt.config.text_dim))
        from dualflow.conditioning import MUSIC_FROM_META

        music_kind = MUSIC_FROM_META.get(str(self.ckpt.meta.get("music", "none")))
        music = None if music_kind is None else np.ascontiguousarray(data.music_for(music_kind), dtype=np.float32)
        self.music = None if music is None else torch.from_numpy(music)
        actor = self.stats.normalize(data.features[:, :, 0].astype(np.float64)).astype(np.float32)
        self.actor = torch.from_numpy(actor)
        self.retriever = self.retrieval_encoder = None
        from dualflow.retrieval import load_rag

        rag = load_rag(self.ckpt, device)
        if rag is not None:
            from dualflow.conditioning import text_encoder_for
            from dualflow.retrieval import NeighbourTable, RetrievalConditioner, cue_queries

            encoder = text_encoder_for(self.ckpt.text_encoder, self.ckpt.config.text_dim)
            queries = cue_queries(rag.db, data.texts, music, encoder)
            table = NeighbourTable.compute(
                rag.db, queries, data.features.shape[1], rag.config.max_depth, rag.config.lam
            )
            self.retriever = RetrievalConditioner(rag.db, table, rag.config)
            self.retrieval_encoder = rag.encoder

    def __call__(self, indices: np.ndarray, seed: int) -> np.ndarray:
        from dualflow.flow import SamplingSettings, generate
        from dualflow.model import Conditions

        torch = self.torch
        idx = torch.as_tensor(np.asarray(indices))
        t = self.data.features.shape[1]
        with torch.no_grad():
            retrieval = None
            if self.retriever is not None:
                retrieval = self.retriever.tokens(self.retrieval_encoder, np.asarray(indices), self.mode, self.device)
            cond = Conditions(
                text=self.text[idx].to(self.device),
                music=None if self.music is None else self.music[idx].to(self.device),
                retrieval=retrieval,
            )
            if self.mode == "reactive":
                xa, xb = generate(
                    self.model,
                    t,
                    cond,
                    mode="reactive",
                    x_actor=self.actor[idx],
                    sampling=SamplingSettings(
                        steps=self.steps, cfg_scale=self.cfg_scale, look_ahead=self.look_ahead, seed=seed
                    ),
                )
            else:
                xa, xb = generate(
                    self.model,
                    t,
                    cond,
                    mode="interactive",
                    batch=len(idx),
                    sampling=SamplingSettings(steps=self.steps, cfg_scale=self.cfg_scale, seed=seed),
                )
        x = torch.stack([xa, xb], dim=2).float().cpu().numpy()
        return self.stats.denormalize(x.astype(np.float64)).astype(np.float32)


def text_embedding(encoder_id: str, texts: Sequence[str], dim: int) -> np.ndarray:
    """Embed ``texts`` the way a checkpoint with ``encoder_id`` was trained."""
    from dualflow.text import TEXT_ENCODER_ID, template_text_embedding

    if encoder_id in ("", TEXT_ENCODER_ID) or encoder_id.startswith(TEXT_ENCODER_ID):
        return template_text_embedding(list(texts), dim)
    if "minilm" in encoder_id.lower():
        from dualflow.text import make_text_encoder

        emb = np.asarray(make_text_encoder("minilm").encode(list(texts)), dtype=np.float32)
        if emb.shape[1] != dim:
            raise DualFlowError(f"checkpoint text_dim {dim} does not match the MiniLM encoder's {emb.shape[1]}")
        return emb
    raise DualFlowError(
        f"checkpoint text encoder {encoder_id!r} is not known to the evaluation; "
        f"expected {TEXT_ENCODER_ID!r} or a MiniLM encoder"
    )
