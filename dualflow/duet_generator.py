"""The DualFlow inference entry point: any subset of (actor, text, music) in, a duet out.

Contract: :class:`DuetGenerator` (a model plus a matching :class:`ConditionBuilder`, usually
:meth:`DuetGenerator.from_checkpoint`) returns a :class:`~dualflow.motion.TwoPersonMotion`
(Z-up world, metres, the model's fps) and the :class:`GeneratorInputs` it used. Offline:
the whole clip at once; the live bridge streams with :mod:`dualflow.streaming` instead.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dualflow.conditioning import ConditionBuilder, GeneratorInputs
from dualflow.model import Conditions, DualFlow
from dualflow.motion.container import Motion, TwoPersonMotion
from dualflow.motion.features import decode_person


class DuetGenerator:
    """The generator the rest of the system calls: any subset of (actor, text, music) in,
    a :class:`TwoPersonMotion` (Z-up world, metres, ``builder.fps``) out.

    With an actor the result's actor is the given motion (resampled to fps) and the reactor is
    generated in the actor's world; otherwise both persons are generated in a canonical world
    (person A starts at the origin facing +X). clean: pass the generated reactor through
    :func:`dualflow.body.clean_positions` (constant bone lengths, planted feet, less jitter; its
    contacts are the cleaner's); False: the raw decoded features.
    """

    def __init__(self, model: DualFlow, builder: ConditionBuilder, clean: bool = True):
        self.model = model.eval()
        self.builder = builder
        self.clean = bool(clean)

    @classmethod
    def from_checkpoint(cls, path: str | Path | None = None, device: str = "cpu", **builder_kw) -> DuetGenerator:
        """The generator of a checkpoint folder (None: the bundled one); builder_kw override the
        :class:`ConditionBuilder`'s (e.g. text_encoder=...)."""
        from dualflow.checkpoint import load_model

        model, ckpt = load_model(path, device)
        return cls(model, ConditionBuilder.from_checkpoint(ckpt, **builder_kw))

    @torch.no_grad()
    def generate(
        self,
        *,
        actor: Motion | None = None,
        text: str | None = None,
        music=None,
        n_frames: int | None = None,
        steps: int = 20,
        cfg_scale: float = 1.0,
        seed: int = 0,
        method: str = "euler",
    ) -> tuple[TwoPersonMotion, GeneratorInputs]:
        """(duet, the inputs the network got). actor / text / music / n_frames: see
        :meth:`ConditionBuilder.build`; steps / method / cfg_scale / seed: the ODE sampler
        (:func:`dualflow.flow.generate`)."""
        from dualflow.flow import SamplingSettings, generate

        inputs = self.builder.build(actor=actor, text=text, music=music, n_frames=n_frames)
        param = next(self.model.parameters())
        cond = Conditions(
            **{
                name: None if getattr(inputs.cond, name) is None else getattr(inputs.cond, name).to(param)
                for name in ("text", "music", "retrieval")
            }
        )
        x_a, x_b = generate(
            self.model,
            inputs.n_frames,
            cond,
            mode=inputs.mode,
            x_actor=None if inputs.actor is None else inputs.actor.to(param),
            sampling=SamplingSettings(steps=steps, method=method, cfg_scale=cfg_scale, seed=seed),
        )
        fps = self.builder.fps
        stats = self.builder.stats
        a = stats.denormalize(x_a[0].cpu().numpy().astype(np.float64))
        b = stats.denormalize(x_b[0].cpu().numpy().astype(np.float64))
        reactor = decode_person(b, fps, inputs.canonical, append_last_frame=True, name="reactor")
        if self.clean:
            from dualflow.body import clean_positions

            pos, contacts = clean_positions(reactor.positions, fps)
            reactor = Motion(positions=pos, fps=fps, contacts=contacts, name="reactor")
        if actor is not None:
            actor_motion = actor if abs(actor.fps - fps) < 1e-6 else actor.resample(fps)
        else:
            actor_motion = decode_person(a, fps, None, append_last_frame=True, name="actor")
        return TwoPersonMotion(actor_motion, reactor, text or ""), inputs


__all__ = ["DuetGenerator"]
