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

from dualflow.motion import Motion


def demo_partners(leader_seeds=range(4), partner_seeds=(0, 1), seconds: float = 8.0) -> list[Motion]:
    """One partner per (leader seed, partner seed), named ``partner_l{leader}_s{seed}`` (30 fps)."""
    from bench.partner_motion import stream_partner
    from dualflow.synthetic import make_leader_clip
    from ros_free_bridge.commands.demo import click_track

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for lead in leader_seeds:
            clip = make_leader_clip(seconds, 30.0, lead)
            music = str(click_track(clip.beat_times, seconds, Path(tmp) / f"click{lead}.wav"))
            for seed in partner_seeds:
                pos = stream_partner(None, clip.body.positions, music, None, window=60, seed=seed)
                out.append(Motion(pos, 30.0, name=f"partner_l{lead}_s{seed}"))
    return out
