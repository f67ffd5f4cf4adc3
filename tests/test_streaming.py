"""Streaming reactive inference: causality end to end, fixed delay, determinism, seams, timing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dualflow import DualFlowError
from dualflow.flow import SamplingSettings, generate
from dualflow.model import Conditions, DualFlow, DualFlowConfig
from dualflow.streaming import ReactiveStreamer, StreamConfig, seam_report, stream_noise

L = 3
N = 24


@pytest.fixture(scope="module")
def model() -> DualFlow:
    torch.manual_seed(0)
    m = DualFlow(DualFlowConfig.preset("tiny", look_ahead=L)).eval()
    for name, p in m.named_parameters():
        if name.startswith(("out_a", "out_b")) or ".modulation." in name:
            torch.nn.init.normal_(p, std=0.1)
    return m


def _actor(seed=0, n=N):
    return torch.randn(n, 262, generator=torch.Generator().manual_seed(seed))


def _run(model, actor, chunks=1, **cfg):
    config = StreamConfig(**{"window": 16, "steps": 3, "seed": 5, **cfg})
    s = ReactiveStreamer(model, config, Conditions(text=torch.ones(1, 384)))
    for k in range(0, actor.shape[0], chunks):
        s.push(actor[k : k + chunks])
    s.flush()
    return s


@pytest.mark.parametrize("hop,chunks", [(1, 1), (3, 1), (1, 5)])
def test_changing_actor_frames_after_i_plus_L_never_changes_emitted_frame_i(model, hop, chunks):
    actor = _actor()
    ref = _run(model, actor, chunks, hop=hop).emitted
    assert ref.shape == (N, 262)
    for cut in (6, 16):
        changed = actor.clone()
        changed[cut:] = _actor(seed=cut, n=N - cut) * 3.0
        out = _run(model, changed, chunks, hop=hop).emitted
        safe = cut - L  # frames i with i + L < cut
        assert torch.equal(out[:safe], ref[:safe]), f"frame < {safe} changed when actor frames >= {cut} changed"
        assert not torch.allclose(out[safe:], ref[safe:])  # and the later frames do react


def test_frame_i_is_emitted_when_actor_frame_i_plus_L_arrives(model):
    s = ReactiveStreamer(model, StreamConfig(window=16, steps=2))
    got = []
    s.on_frame = lambda i, f: got.append(i)
    for j, frame in enumerate(_actor().numpy()):  # numpy input, one frame at a time
        new = s.push(frame)
        assert s.emitted.shape[0] == max(0, j + 1 - L)
        assert new.shape[0] == (1 if j >= L else 0)
    assert s.delay_frames == L
    tail = s.flush()
    assert tail.shape[0] == L and s.emitted.shape[0] == N
    assert got == list(range(N))


def test_hop_batches_frames_and_bounds_the_delay(model):
    s = ReactiveStreamer(model, StreamConfig(window=16, steps=2, hop=4))
    for j, frame in enumerate(_actor()):
        s.push(frame)
        pending = max(0, j + 1 - L) - s.emitted.shape[0]
        assert 0 <= pending < 4
    assert s.delay_frames == L + 3
    assert all(n == 4 for _, n, _ in s.timing.windows)


def test_stream_is_deterministic_per_seed(model):
    actor = _actor()
    a = _run(model, actor, seed=1).emitted
    b = _run(model, actor, seed=1).emitted
    c = _run(model, actor, seed=2).emitted
    assert torch.equal(a, b)
    assert not torch.allclose(a, c)


def test_first_window_equals_the_offline_reactive_sampler(model):
    """Before any context exists, a window is exactly ``flow.generate`` in reactive mode."""
    actor = _actor()
    s = ReactiveStreamer(model, StreamConfig(window=16, steps=3, seed=9, max_new=5, hop=5))
    s.push(actor[: 5 + L])
    assert s.emitted.shape[0] == 5
    eps = stream_noise(9, 5 + L)
    _, offline = generate(
        model, 5 + L, mode="reactive", x_actor=actor[None, : 5 + L], noise=eps[None], sampling=SamplingSettings(steps=3)
    )
    torch.testing.assert_close(s.emitted, offline[0, :5])


@pytest.mark.parametrize("hop,chunks", [(1, 1), (4, 1), (2, 7)])
def test_stream_equals_single_pass_generation_while_it_fits_in_one_window(model, hop, chunks):
    """Trajectory context + the causal reactor: no seam at all, the stream is the offline sample."""
    actor = _actor()
    s = ReactiveStreamer(model, StreamConfig(window=N + 4, steps=3, seed=4, hop=hop))
    for k in range(0, N, chunks):
        s.push(actor[k : k + chunks])
    s.flush()
    assert len(s.timing.windows) > 2  # several windows, each with its own context
    _, offline = generate(
        model,
        N,
        mode="reactive",
        x_actor=actor[None],
        noise=stream_noise(4, N)[None],
        sampling=SamplingSettings(steps=3),
    )
    torch.testing.assert_close(s.emitted, offline[0], atol=1e-5, rtol=1e-5)
    # Straight-path re-noising of the context (classic inpainting) is only approximately so.
    p = ReactiveStreamer(model, StreamConfig(window=N + 4, steps=3, seed=4, hop=hop, context="path"))
    for k in range(0, N, chunks):
        p.push(actor[k : k + chunks])
    p.flush()
    assert not torch.allclose(p.emitted, offline[0], atol=1e-3)


def test_noise_does_not_depend_on_how_frames_are_pushed(model):
    a = ReactiveStreamer(model, StreamConfig(window=16, steps=1))
    a.push(_actor(n=70))
    b = ReactiveStreamer(model, StreamConfig(window=16, steps=1))
    for frame in _actor(n=70):
        b.push(frame)
    assert torch.equal(a._noise[:70], b._noise[:70])
    assert torch.equal(a._noise[:70], stream_noise(0, 70))


def test_context_frames_are_kept_fixed_inside_later_windows(model):
    """With inpainting, the known prefix sits exactly on the path: at t = 1 it equals the emitted frames,
    and later windows change nothing already emitted; without it, windows ignore their context."""
    actor = _actor()
    with_ctx = _run(model, actor, hop=4).emitted
    without = _run(model, actor, hop=4, inpaint=False).emitted
    first = 4  # the first window (no context) is the same in both
    torch.testing.assert_close(with_ctx[:first], without[:first])
    assert not torch.allclose(with_ctx[first:], without[first:])


def test_timing_is_reported_per_emitted_frame(model):
    s = _run(model, _actor(), hop=2)
    assert s.timing.frames == N
    assert s.timing.total_s > 0 and s.timing.per_frame_s == pytest.approx(s.timing.total_s / N)
    assert s.timing.max_window_s >= s.timing.per_frame_s


def test_seam_report_on_hand_made_tracks():
    t = np.arange(12, dtype=float)
    smooth = np.stack([0.1 * t, np.zeros_like(t), np.zeros_like(t)], -1)[:, None, :]  # constant velocity
    r = seam_report(smooth, [0, 4, 8])
    assert r.seam_mean == pytest.approx(0.0) and r.within_mean == pytest.approx(0.0)
    kinked = smooth.copy()
    kinked[4:, 0, 1] += 0.5  # a 0.5 m step at the seam of frame 4: jumps of 0.5 at i = 4 and i = 5
    r = seam_report(kinked, [0, 4, 8])
    assert r.n_seams == 4 and r.n_within == 6  # seams: i = 4, 5, 8, 9; within: 2, 3, 6, 7, 10, 11
    assert r.seam_mean == pytest.approx((0.5 + 0.5 + 0.0 + 0.0) / 4)
    assert r.within_mean == pytest.approx(0.0, abs=1e-12)
    bent = smooth.copy()
    bent[6:, 0, 2] += 0.2 * (t[6:] - 5)[:, None].squeeze(-1)  # velocity change of 0.2 inside window 1
    r = seam_report(bent, [0, 4, 8])
    assert r.seam_mean == pytest.approx(0.0, abs=1e-12) and r.within_mean == pytest.approx(0.2 / 6)


def test_bad_input_raises_clear_errors(model):
    s = ReactiveStreamer(model, StreamConfig(window=16))
    with pytest.raises(DualFlowError, match="actor frames"):
        s.push(torch.zeros(3, 100))
    with pytest.raises(DualFlowError, match="NaN"):
        s.push(torch.full((262,), float("nan")))
    with pytest.raises(DualFlowError, match="window"):
        ReactiveStreamer(model, StreamConfig(window=L + 1))
    short = ReactiveStreamer(model, StreamConfig(window=16, steps=1), Conditions(music=torch.zeros(1, 5, 35)))
    with pytest.raises(DualFlowError, match="music track"):
        short.push(_actor(n=10))


# -- per-window canonical frames ---------------------------------------------------------------

from dualflow.motion import REST_POSE  # noqa: E402
from dualflow.motion.features import FEATURE_SLICES  # noqa: E402
from dualflow.motion.normalization import NormStats  # noqa: E402
from dualflow.streaming import WindowFrame  # noqa: E402

REST_YUP = torch.tensor(np.asarray(REST_POSE)[:, [1, 2, 0]], dtype=torch.float64)
POS, VEL = FEATURE_SLICES["positions"], FEATURE_SLICES["velocities"]


def _yaw_shift(raw: torch.Tensor, angle: float, shift) -> torch.Tensor:
    """Rigid ground-plane motion of raw features: positions R p + s, velocities R v (Y-up)."""
    c, s_ = np.cos(angle), np.sin(angle)
    rot = torch.tensor([[c, 0.0, s_], [0.0, 1.0, 0.0], [-s_, 0.0, c]], dtype=raw.dtype)
    out = raw.clone()
    p = out[..., POS].reshape(*out.shape[:-1], 22, 3) @ rot.T + torch.tensor(shift, dtype=raw.dtype)
    v = out[..., VEL].reshape(*out.shape[:-1], 22, 3) @ rot.T
    out[..., POS] = p.reshape(*out.shape[:-1], 66)
    out[..., VEL] = v.reshape(*out.shape[:-1], 66)
    return out


def _raw_actor(n=N, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    raw = 0.3 * torch.randn(n, 262, generator=g, dtype=torch.float64)
    raw[:, POS] += REST_YUP.reshape(66)
    return raw


def test_window_frame_maps_a_turned_displaced_person_to_the_origin_facing_plus_z():
    rest = torch.zeros(262, dtype=torch.float64)
    rest[POS] = REST_YUP.reshape(66)
    rest[VEL] = torch.linspace(-0.1, 0.1, 66, dtype=torch.float64)
    moved = _yaw_shift(rest, 1.1, [2.0, 0.0, -3.0])
    frame = WindowFrame(moved)
    local = frame.to_local(moved)
    expected = rest.clone()
    expected[POS] = (REST_YUP - torch.tensor([REST_YUP[0, 0], 0.0, REST_YUP[0, 2]])).reshape(66)
    torch.testing.assert_close(local, expected)
    torch.testing.assert_close(frame.to_global(local), moved)


def test_streaming_with_window_frames_is_equivariant_to_moving_the_whole_scene(model):
    """Turning and shifting the actor's whole stream turns and shifts the reactor the same way."""
    g = torch.Generator().manual_seed(3)
    stats = NormStats(
        mean=0.1 * torch.randn(262, generator=g).double().numpy(),
        std=(0.5 + torch.rand(262, generator=g)).double().numpy(),
    )
    raw = _raw_actor()
    moved = _yaw_shift(raw, 2.0, [1.5, 0.0, -0.7])

    def run(raw_actor):
        s = ReactiveStreamer(model, StreamConfig(window=16, steps=3, hop=4, recanonicalize=True), stats=stats)
        s.push(torch.from_numpy(stats.normalize(raw_actor.numpy())).float())
        s.flush()
        return torch.from_numpy(stats.denormalize(s.emitted.double().numpy()))

    out, out_moved = run(raw), run(moved)
    torch.testing.assert_close(out_moved, _yaw_shift(out, 2.0, [1.5, 0.0, -0.7]), atol=2e-4, rtol=1e-4)
    # Without window frames, the same streams are not related by the motion (the test can fail).
    plain = ReactiveStreamer(model, StreamConfig(window=16, steps=3, hop=4))
    plain.push(torch.from_numpy(stats.normalize(moved.numpy())).float())
    plain.flush()
    assert not torch.allclose(
        torch.from_numpy(stats.denormalize(plain.emitted.double().numpy())),
        _yaw_shift(out, 2.0, [1.5, 0.0, -0.7]),
        atol=1e-2,
    )


def test_causality_holds_with_window_frames(model):
    stats = NormStats(mean=np.zeros(262), std=np.ones(262))
    actor = _raw_actor().float()

    def run(a):
        s = ReactiveStreamer(model, StreamConfig(window=16, steps=3, recanonicalize=True), stats=stats)
        for frame in a:
            s.push(frame)
        s.flush()
        return s.emitted

    ref = run(actor)
    changed = actor.clone()
    changed[14:] = _raw_actor(N - 14, seed=4).float()
    out = run(changed)
    assert torch.equal(out[: 14 - L], ref[: 14 - L])
    assert not torch.allclose(out[14 - L :], ref[14 - L :])
