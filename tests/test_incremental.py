"""Incremental reactive inference (dualflow.incremental): cached windows equal the full network."""

from __future__ import annotations

import pytest
import torch

from dualflow import DualFlowError
from dualflow.incremental import IncrementalModel, WindowCache
from dualflow.model import Conditions, DualFlow, DualFlowConfig
from dualflow.streaming import ReactiveStreamer, StreamConfig

L = 3


@pytest.fixture(scope="module")
def model() -> DualFlow:
    torch.manual_seed(0)
    m = DualFlow(DualFlowConfig.preset("tiny", look_ahead=L)).eval()
    for name, p in m.named_parameters():  # zero-initialised layers made non-trivial
        if name.startswith(("out_a", "out_b")) or ".modulation." in name:
            torch.nn.init.normal_(p, std=0.1)
    return m


def _actor(n=40, seed=0):
    return torch.randn(n, 262, generator=torch.Generator().manual_seed(seed))


def _conds(model):
    text = torch.ones(1, 384)
    music = torch.randn(1, 60, model.config.music_dim, generator=torch.Generator().manual_seed(1))
    return {"text only (null music token)": Conditions(text=text), "text and music": Conditions(text=text, music=music)}


@pytest.mark.parametrize("which", ["text only (null music token)", "text and music"])
def test_rows_fed_in_chunks_equal_the_full_window_forward(model, which):
    cond = _conds(model)[which]
    actor = _actor()
    start, window = 5, 16
    cache = WindowCache(IncrementalModel(model), start, window, L, cond, [0.0, 0.5])
    cache.sync_actor(actor)
    x = torch.randn(1, window, 262, generator=torch.Generator().manual_seed(2))
    out = torch.cat([cache.reactor_rows(1, x[:, lo:hi]) for lo, hi in ((0, 4), (4, 5), (5, 9), (9, 13))], 1)
    with torch.no_grad():
        _, full = model(
            actor[None, start : start + window], x, 0.5, cond.slice_frames(start, start + window), mode="reactive"
        )
    torch.testing.assert_close(out, full[:, :13], atol=1e-5, rtol=1e-5)


def test_revised_actor_rows_are_recomputed(model):
    cond = _conds(model)["text and music"]
    inc = IncrementalModel(model)
    actor = _actor()
    cache = WindowCache(inc, 0, 16, L, cond, [0.0])
    cache.sync_actor(actor[:12])
    revised = actor.clone()
    revised[11] += 1.0
    cache.forget_actor(11)
    cache.sync_actor(revised[:12])
    fresh = WindowCache(inc, 0, 16, L, cond, [0.0])
    fresh.sync_actor(revised[:12])
    for a, b in zip(cache.motion_k, fresh.motion_k):
        torch.testing.assert_close(a, b)


def _stream(model, actor, prepare=False, **cfg):
    s = ReactiveStreamer(
        model,
        StreamConfig(**{"window": 16, "steps": 3, "seed": 5, "hop": 1, **cfg}),
        Conditions(text=torch.ones(1, 384)),
    )
    for k in range(actor.shape[0]):
        s.push(actor[k : k + 1])
        while prepare and s.prepare(1):
            pass
    s.flush()
    return s


def test_incremental_stream_equals_the_windowed_stream_while_it_fits_in_one_window(model):
    actor = _actor(12)  # 12 frames + L < window 16: no window ever slides, both are exact
    a = _stream(model, actor)
    b = _stream(model, actor, incremental=True)
    torch.testing.assert_close(b.emitted, a.emitted, atol=1e-5, rtol=1e-5)


def test_catch_up_in_idle_time_changes_nothing(model):
    actor = _actor(40)
    eager = _stream(model, actor, incremental=True)
    lazy = _stream(model, actor, prepare=True, incremental=True)
    assert eager.emitted.shape == (40, 262)
    torch.testing.assert_close(lazy.emitted, eager.emitted, atol=1e-5, rtol=1e-5)
    while lazy.prepare(1):  # the frames of the final flush, for the other window start
        pass
    assert not lazy.has_catch_up


def test_incremental_stream_is_causal_across_window_starts(model):
    actor = _actor(40)
    base = _stream(model, actor, incremental=True).emitted
    i = 25  # generated long after the first window start was given up
    changed = actor.clone()
    changed[i + L + 1 :] = torch.randn(40 - i - L - 1, 262)
    other = _stream(model, changed, incremental=True).emitted
    torch.testing.assert_close(other[: i + 1], base[: i + 1])
    assert not torch.allclose(other[i + 1 :], base[i + 1 :])


def test_incremental_keeps_context_across_window_starts(model):
    """Each frame is generated in a window start that has seen at least P - P / bases frames
    before it (P = window - L); a stream without context (fresh noise per window) differs."""
    actor = _actor(40)
    s = _stream(model, actor, incremental=True, bases=2)
    assert [b.start for b in s._bases][-1] > 0  # the stream did move to later starts
    no_ctx = _stream(model, actor, inpaint=False)
    assert not torch.allclose(s.emitted[20:], no_ctx.emitted[20:], atol=1e-3)


def test_unsupported_incremental_settings_are_refused(model):
    for bad in (dict(method="heun"), dict(cfg_scale=2.0), dict(context="path"), dict(inpaint=False)):
        with pytest.raises(DualFlowError, match="incremental"):
            ReactiveStreamer(model, StreamConfig(window=16, incremental=True, **bad))
    with pytest.raises(DualFlowError, match="hop"):
        ReactiveStreamer(model, StreamConfig(window=16, hop=9, incremental=True))


def _record_passes(monkeypatch):
    """Record every network pass of a WindowCache: per reactor stream in it, (in prepare,
    need_output, step, rows, takeover, streams in the pass); ``takeover``: the generating
    start runs out within TAKEOVER_FRAMES frames."""
    calls, state = [], {"in_prepare": False, "streamer": None}
    orig_rows, orig_prepare = WindowCache._rows, ReactiveStreamer.prepare

    def rows(self, x_a, reactor, need_output):
        s = state["streamer"]
        takeover = not s._bases[0].can_generate(s.emitted.shape[0] + s.TAKEOVER_FRAMES - 1)
        calls.extend(
            (state["in_prepare"], need_output, step, x.shape[1], takeover, len(reactor)) for step, x in reactor
        )
        return orig_rows(self, x_a, reactor, need_output)

    def prepare(self, max_passes=1, kinds=None):
        state["in_prepare"], state["streamer"] = True, self
        try:
            return orig_prepare(self, max_passes, kinds)
        finally:
            state["in_prepare"] = False

    monkeypatch.setattr(WindowCache, "_rows", rows)
    monkeypatch.setattr(ReactiveStreamer, "prepare", prepare)
    return calls, state


def _stream_with_prepare(model, actor, cfg, state, passes_per_frame):
    s = ReactiveStreamer(model, StreamConfig(seed=5, hop=1, steps=3, **cfg), Conditions(text=torch.ones(1, 384)))
    state["streamer"] = s
    for k in range(actor.shape[0]):
        s.push(actor[k : k + 1])
        if passes_per_frame:
            s.prepare(passes_per_frame)
        else:  # idle time: everything due
            while s.prepare(1):
                pass
    s.flush()
    return s


def _recorded_stream(model, monkeypatch, passes_per_frame):
    """Stream 90 actor frames (window 40, two incremental starts) with ``passes_per_frame``
    catch-up passes per frame (0: idle time, everything due), recording every pass; the
    emitted stream must equal the eager one. Returns the streamer and the recorded passes."""
    actor = _actor(90)
    cfg = {"window": 40, "incremental": True, "bases": 2}
    eager = _stream(model, actor, **cfg)
    calls, state = _record_passes(monkeypatch)
    s = _stream_with_prepare(model, actor, cfg, state, passes_per_frame)
    torch.testing.assert_close(s.emitted, eager.emitted, atol=1e-5, rtol=1e-5)
    return s, calls


def test_one_catch_up_pass_per_frame_feeds_every_step_in_batches(model, monkeypatch):
    """A busy generator does one ``prepare`` piece per frame: the background start must then
    be fed FEED_BATCH rows at a time, every grid step in the same pass - except the start
    about to take over, which gets everything it lacks - and the stream is unchanged."""
    s, calls = _recorded_stream(model, monkeypatch, passes_per_frame=1)
    background = [c for c in calls if c[0]]
    assert {step for _, _, step, *_ in background} == {0, 1, 2}
    assert all(streams == 3 for *_, streams in background)  # the three grid steps in one pass
    assert all(n >= ReactiveStreamer.FEED_BATCH for _, _, _, n, takeover, _ in background if not takeover)
    assert any(takeover for *_, takeover, _ in background)


def test_with_idle_time_the_generating_window_has_only_its_own_passes(model, monkeypatch):
    """Catch-up work done in idle time (the next start made and fed before it takes over):
    generating a frame never feeds another start's recorded states, even at a takeover."""
    s, calls = _recorded_stream(model, monkeypatch, passes_per_frame=0)
    assert len(s._bases) >= 2 and s._bases[0].start > 0  # took over at least once
    in_window = [c for c in calls if not c[0]]
    assert in_window and all(need_output for _, need_output, *_ in in_window)


def test_actor_rows_in_the_reactor_pass_equal_a_separate_sync(model):
    """reactor_rows(actor=...) runs the new actor rows and the reactor rows through the blocks
    together (stacked products); the velocity and every cache equal sync_actor + reactor_rows."""
    cond = _conds(model)["text and music"]
    inc = IncrementalModel(model)
    actor = _actor()
    x = torch.randn(1, 3, 262, generator=torch.Generator().manual_seed(4))
    caches = []
    for fused in (False, True):
        c = WindowCache(inc, 2, 20, L, cond, [0.0, 0.5])
        c.sync_actor(actor[:10])
        c.reactor_rows(0, x[:, :2] * 0.5)  # some cached reactor rows first
        if fused:
            v = c.reactor_rows(0, x, actor=actor[:16])
        else:
            c.sync_actor(actor[:16])
            v = c.reactor_rows(0, x)
        caches.append((c, v))
    (a, va), (b, vb) = caches
    assert b.actor.n == a.actor.n == 14
    torch.testing.assert_close(vb, va, atol=1e-5, rtol=1e-5)
    for j in range(a.n_blocks):
        torch.testing.assert_close(b.motion_k[j], a.motion_k[j], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(b.actor.k[j], a.actor.k[j], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(b.reactor[0].v[j], a.reactor[0].v[j], atol=1e-5, rtol=1e-5)


def test_feeding_several_grid_steps_in_one_pass_equals_a_pass_per_step(model):
    """WindowCache.feed stacks the grid steps' rows (and new actor rows) in one pass; every
    step's cache, the actor keys and the next generated velocity equal one teacher-forcing
    pass per step. A step given twice is refused."""
    cond = _conds(model)["text and music"]
    inc = IncrementalModel(model)
    actor = _actor()
    g = torch.Generator().manual_seed(7)
    x0, x1 = torch.randn(1, 5, 262, generator=g), torch.randn(1, 5, 262, generator=g)
    nxt = torch.randn(1, 1, 262, generator=g)
    caches = []
    for together in (False, True):
        c = WindowCache(inc, 2, 20, L, cond, [0.0, 0.5])
        c.sync_actor(actor[:8])
        if together:
            c.feed([(0, x0[:, :2]), (1, x1)], actor=actor[:16])  # the steps may lag differently
        else:
            c.reactor_rows(0, x0[:, :2], need_output=False, actor=actor[:16])
            c.reactor_rows(1, x1, need_output=False)
        v = c.reactor_rows(1, nxt)
        caches.append((c, v))
    (a, va), (b, vb) = caches
    assert [r.n for r in b.reactor] == [r.n for r in a.reactor] == [2, 6] and b.actor.n == a.actor.n == 14
    torch.testing.assert_close(vb, va, atol=1e-5, rtol=1e-5)
    for j in range(a.n_blocks):
        torch.testing.assert_close(b.motion_k[j], a.motion_k[j], atol=1e-5, rtol=1e-5)
        for step in (0, 1):
            torch.testing.assert_close(b.reactor[step].k[j], a.reactor[step].k[j], atol=1e-5, rtol=1e-5)
            torch.testing.assert_close(b.reactor[step].z_in[j], a.reactor[step].z_in[j], atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="grid step given twice"):
        a.feed([(0, x0[:, :1]), (0, x0[:, 1:2])])


@pytest.mark.parametrize("incremental", [False, True])
def test_a_music_track_shorter_than_the_stream_is_one_clear_error(model, incremental):
    """Both generation paths stop at the first frame the track does not cover, with the
    streamer's error (incremental windows used to run on with truncated music, then fail
    deep inside attention)."""
    music = torch.randn(1, 20, model.config.music_dim, generator=torch.Generator().manual_seed(2))
    s = ReactiveStreamer(
        model,
        StreamConfig(window=16, hop=1, steps=2, incremental=incremental),
        Conditions(text=torch.ones(1, 384), music=music),
    )
    with pytest.raises(DualFlowError, match="music track has 20 frames"):
        for row in _actor(40):
            s.push(row)
    assert s.emitted.shape[0] <= 20


def _count_prefetched_passes(monkeypatch) -> list[int]:
    """Record m of every block pass that used the prefetched convolution sums (m: taps left)."""
    used = []
    orig = IncrementalModel.last_taps

    def last_taps(self, j, m):
        used.append(m)
        return orig(self, j, m)

    monkeypatch.setattr(IncrementalModel, "last_taps", last_taps)
    return used


def _revising_stream(model, actor, prefetch: bool) -> ReactiveStreamer:
    """The live generator's pattern: each push revises the previous (provisional) actor row
    and adds a provisional one, with idle time (``prepare``) between pushes."""
    s = ReactiveStreamer(
        model,
        StreamConfig(window=24, steps=2, seed=5, hop=1, incremental=True, bases=2, prefetch=prefetch),
        Conditions(text=torch.ones(1, 384)),
    )
    s.push(actor[0:1] * 0.5)
    for k in range(1, actor.shape[0]):
        s.push(torch.stack([actor[k - 1], actor[k] * 0.5]), revise=1)  # row k - 1 final, row k provisional
        while s.prepare(1):
            pass
    s.flush()
    return s


def test_prefetched_convolution_sums_change_nothing_and_are_used(model, monkeypatch):
    """Idle-time prefetch (WindowCache.prefetch) splits each convolution into the sums over
    older frames, made before the frame, and the newest taps: with revised actor rows and
    window-start takeovers the stream equals the one without prefetch, and the generating
    passes do take the short path (one or two taps left per kernel). (Against a stream
    without idle time it would differ: with revisions, when a background start is fed
    matters; ``WindowCache.forget_actor``.)"""
    actor = _actor(60)
    plain = _revising_stream(model, actor, prefetch=False)
    used = _count_prefetched_passes(monkeypatch)
    lazy = _revising_stream(model, actor, prefetch=True)
    torch.testing.assert_close(lazy.emitted, plain.emitted, atol=1e-5, rtol=1e-5)
    assert lazy._bases[0].start > 0  # a later start took over, with its own prefetch
    n_blocks = len(model.blocks)
    # every emitted frame's 2 grid steps, bar those before the first idle time and at takeovers
    assert len(used) >= n_blocks * 2 * (60 - 6) and set(used) <= {1, 2}


def test_a_revision_before_the_prefetched_rows_drops_their_sums(model):
    """Revising actor rows older than a prefetch's first row invalidates its sums (they read
    the old rows): the next pass takes the full products and equals a cache never prefetched."""
    cond = _conds(model)["text and music"]
    inc = IncrementalModel(model)
    actor = _actor()
    revised = actor.clone()
    revised[7:12] += 1.0
    caches = []
    for prefetch in (False, True):
        c = WindowCache(inc, 0, 20, L, cond, [0.0])
        c.sync_actor(actor[:12])
        if prefetch:
            c.prefetch()
            assert c.actor.pre_base == 11 and not c.prefetch_due()
        c.forget_actor(7)
        assert c.actor.pre_base is None if prefetch else True
        c.sync_actor(revised[:12])
        caches.append(c)
    a, b = caches
    for j in range(a.n_blocks):
        torch.testing.assert_close(b.motion_k[j], a.motion_k[j], atol=1e-5, rtol=1e-5)
