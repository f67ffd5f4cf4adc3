"""Generated partners as the demo makes them, for the retargeting benches.

The bundled DualFlow checkpoint streams a partner to synthetic leaders (dualflow.synthetic.
make_leader_clip, each with its click track as the music cue) through the bridge's own
ReactorStage with the demo's settings (window 60, 2 Euler steps, hop 1, incremental), cleaned as
the live stream cleans it (dualflow.body). These are SYNTHETIC actors and GENERATED partners: the
robot's input in `dualflow-bridge demo`, not captured people.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from dualflow.motion import Motion


def demo_partners(leader_seeds=range(4), partner_seeds=(0, 1), seconds: float = 8.0, fps: float = 30.0) -> list[Motion]:
    """One partner per (leader seed, partner seed), named ``partner_l{leader}_s{seed}``."""
    from dualflow.streaming import StreamConfig
    from dualflow.synthetic import make_leader_clip
    from ros_free_bridge.commands.demo import click_track
    from ros_free_bridge.partner.reactor import Cues, ReactorStage

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for lead in leader_seeds:
            clip = make_leader_clip(seconds, fps, lead)
            leader = clip.body.positions
            music = str(click_track(clip.beat_times, seconds, Path(tmp) / f"click{lead}.wav"))
            for seed in partner_seeds:
                config = StreamConfig(window=60, steps=2, hop=1, incremental=True, seed=seed)
                stage = ReactorStage(fps, None, config, Cues(None, music, music_frames=len(leader) + 60))
                frames = []
                for k, p in enumerate(leader):
                    frames += stage.push(p, 0.0, k)
                frames += stage.flush(0.0, len(leader) - 1)
                pos = np.stack([f.positions for f in sorted(frames, key=lambda f: f.index)])
                out.append(Motion(pos, fps, name=f"partner_l{lead}_s{seed}"))
    return out
