"""The physics check of a trajectory that starts with a lead-in (retarget.lead_in): its failures,
warnings and series are in clip time (the trajectory's time less the lead-in), and a failure
in the lead-in says so. Hand-made op3 trajectories played in real MuJoCo."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_cfg.registry import joint_names
from retarget import RobotTrajectory
from retarget.lead_in import LeadIn
from sim.check import check_trajectory
from sim.scene import Scene, SceneConfig

FPS = 30.0
LEAD_FRAMES = 24  # a 0.8 s lead-in


@pytest.fixture(scope="module")
def stand() -> np.ndarray:
    return Scene(SceneConfig(robot="op3")).stand_ctrl


def standing_with_a_burst(stand: np.ndarray, burst_at: float, duration: float = 2.0, lead: bool = True):
    """The op3 standing still for ``duration`` s of trajectory time, its right shoulder swung far
    beyond the servo's speed from trajectory time ``burst_at`` s on; with ``lead`` its meta says
    that the first LEAD_FRAMES frames are a lead-in (as retarget.lead_in.with_lead_in writes it)."""
    names = joint_names("op3")
    t = np.arange(int(round(duration * FPS)) + 1) / FPS
    q = np.repeat(stand[None], len(t), axis=0)
    j = names.index("r_sho_pitch")
    on = t >= burst_at
    q[on, j] = stand[j] - 0.8 * np.sin(2 * np.pi * 2.0 * (t[on] - burst_at)) ** 2  # peaks near 10 rad/s
    n = len(t)
    meta = {}
    if lead:
        info = LeadIn(LEAD_FRAMES, FPS, 0.0, ("left",), (), "the pelvis moves at 0.50 m/s")
        meta = {"lead_in": info.to_dict(), "t0_s": info.t0_s}
    return RobotTrajectory(
        names, q, np.tile([0.0, 0.0, 0.27], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)), FPS, "op3", meta
    )


def test_failure_times_are_clip_times_after_a_lead_in(stand):
    t0 = LEAD_FRAMES / FPS
    plain = check_trajectory(standing_with_a_burst(stand, 1.2, lead=False))
    led = check_trajectory(standing_with_a_burst(stand, 1.2))
    assert plain.reason == led.reason == "speed_limit"
    # the same tick, reported t0 earlier: in the clip's time, not the trajectory's
    assert led.first_failure_time == pytest.approx(plain.first_failure_time - t0, abs=1e-9)
    assert 0.0 <= led.first_failure_time < 1.2 - t0 + 0.2
    assert led.failures[0].phase == "clip"
    assert led.metrics["lead_in_s"] == pytest.approx(t0)
    # the series are on the same clock: the lead-in and the entry before it are negative
    t = led.series["t"]
    assert t[0] == pytest.approx(-t0 - led.entry_transition_s, abs=1e-9)
    assert np.all(np.diff(t) > 0)


def test_a_failure_in_the_lead_in_is_negative_and_named(stand):
    res = check_trajectory(standing_with_a_burst(stand, 0.3))
    f = res.failures[0]
    assert f.reason == "speed_limit"
    assert -LEAD_FRAMES / FPS < f.time < 0.0
    assert f.phase == "lead-in" and "lead-in" in f.detail
