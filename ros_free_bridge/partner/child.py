"""The generator process's side: ``python -m ros_free_bridge.partner.child --fds R,W``.

Started by :class:`~ros_free_bridge.partner.process.GeneratorProcess`, never by hand. It
builds a :class:`~ros_free_bridge.partner.core.PartnerCore` from the C message, answers R,
then turns A messages into T and V messages, doing catch-up work in the gaps between them.
It never outlives its parent and ignores SIGINT/SIGTERM (docs/partner_pipeline.md).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import signal

from ros_free_bridge.errors import BridgeError
from ros_free_bridge.partner.process import GeneratorConfig
from ros_free_bridge.partner.wire import Channel, decode_actor, encode_target


def build_core(cfg: GeneratorConfig):
    """The child's PartnerCore: the reactor (torch) and the retargeter (CasADi)."""
    import torch

    from dualflow.streaming import StreamConfig
    from ros_free_bridge.partner.core import PartnerCore
    from ros_free_bridge.partner.reactor import Cues, ReactorStage
    from ros_free_bridge.partner.retarget_stage import RetargetStage
    from ros_free_bridge.robots import planning_robot

    torch.set_num_threads(max(1, int(cfg.threads)))
    incremental = cfg.incremental and cfg.device == "cpu"  # on CUDA full windows from CUDA graphs are faster
    stream = StreamConfig(window=cfg.window, steps=cfg.steps, hop=cfg.hop, seed=cfg.seed, incremental=incremental)
    # the model first: a bad checkpoint or condition fails before the slower retargeter build
    reactor = ReactorStage(
        cfg.fps,
        cfg.checkpoint,
        stream,
        Cues(cfg.text, cfg.music, cfg.music_frames),
        threads=cfg.threads,
        predict_next=cfg.predict_next,
        device=cfg.device,
    )
    retarget = RetargetStage(planning_robot(cfg.robot), cfg.fps, cfg.joint_names)
    return PartnerCore(reactor, retarget, cfg.max_lag)


def warm_up(core) -> tuple[float, float]:
    """Generate throw-away windows (allocator, kernels) on a separate stream, as a run starts:
    the first window (no context, L + hop frames) and then full-width ones. Returns the seconds
    of the first and of the last (full) window: this machine's generation speed right now."""
    import torch

    from dualflow.streaming import ReactiveStreamer

    r = core.reactor
    streamer = ReactiveStreamer(r.model, r.streamer.config, r.streamer.cond)
    cfg = streamer.config
    with torch.inference_mode():
        streamer.push(torch.zeros(r.look_ahead + cfg.hop, streamer.dim))
        streamer.push(torch.zeros(cfg.window, streamer.dim))
    windows = streamer.timing.windows
    return windows[0][2], windows[-1][2]


def _ready(chan: Channel) -> tuple[object, dict] | None:
    """Read the C message, build and warm up the core; (core, the R message's body), or None
    when the parent sent something else or went away."""
    msgs = []
    while not msgs and not chan.eof:
        msgs = chan.receive(None)
    if not msgs or msgs[0][0] != b"C":
        return None
    cfg = GeneratorConfig(**json.loads(msgs[0][1]))
    if cfg.nice > 0:
        os.nice(int(cfg.nice))
    core = build_core(cfg)
    first_s, window_s = warm_up(core) if cfg.warmup else (float("nan"), float("nan"))
    # the model, the retargeter and the warm-up leave ~200 000 objects that live as long as
    # the process; a full collection scanning them took ~150 ms, and a frame waited for it.
    # Frozen, the collector scans only what is allocated while streaming.
    gc.collect()
    gc.freeze()
    return core, {
        "delay_frames": core.delay_frames,
        "look_ahead": core.reactor.look_ahead,
        "gc_frozen_objects": gc.get_freeze_count(),
        "frames_ahead": core.reactor.frames_ahead,
        "max_lag": core.max_lag,
        "warmup_first_window_s": first_s,
        "warmup_window_s": window_s,
        "pid": os.getpid(),
    }


def _send(chan: Channel, targets, events) -> None:
    for e in events:
        chan.send_json(b"V", e)
    for t in targets:
        chan.send(b"T", encode_target(t))


def _serve(chan: Channel, core) -> int:
    """Actor frames in, targets out, until Q or EOF; catch-up work in the gaps."""
    while True:
        # more windows due: do not wait; catch-up work: wait only until a piece fits before
        # the next actor frame (partner.idle_slots), or for that frame
        msgs = chan.receive(0.0 if core.backlog else core.idle_wait())
        if (chan.eof and not msgs) or any(k == b"Q" for k, _ in msgs):
            return 0
        frames = [decode_actor(p) for k, p in msgs if k == b"A"]
        if not msgs and not core.backlog:
            if core.idle_ready():
                core.idle_step()  # one piece (a few ms), then look at the pipe again
            continue
        targets, events = core.feed(frames)
        _send(chan, targets, events)
        if targets and not core.backlog and core.idle_ready():
            # a busy CPU leaves little idle time: one piece of catch-up work per window, after
            # its targets went out and if it ends before the next frame, rather than all of
            # it in the window that needs it
            core.idle_step()
        if any(k == b"E" for k, _ in msgs):
            for targets, events in core.finish_stream():
                _send(chan, targets, events)
            chan.send(b"D")


def child_main(rfd: int, wfd: int) -> int:
    # Ctrl-C (or a SIGTERM to the group) reaches every process of the group; the parent
    # decides (e-stop, the signal as the reason), then ends this one
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    chan = Channel(rfd, wfd)
    try:
        ready = _ready(chan)
        if ready is None:
            return 2
        core, info = ready
        chan.send_json(b"R", info)
        return _serve(chan, core)
    except BrokenPipeError:
        return 0  # the parent is gone
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which stops the robot safely
        try:
            msg = str(exc) if isinstance(exc, BridgeError) else f"{type(exc).__name__}: {exc}"
            chan.send_json(b"X", {"type": type(exc).__name__, "message": msg})
        except OSError:
            pass
        return 1
    finally:
        chan.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="the bridge's generator process (started by the bridge, not by hand)")
    ap.add_argument("--fds", required=True, help="READ_FD,WRITE_FD inherited from the parent")
    ap.add_argument("--parent", type=int, help="the parent's process id: end when it ends")
    ap.add_argument("--pdeathsig", action="store_true", help="also ask the kernel to kill this process with the parent")
    args = ap.parse_args(argv)
    if args.parent is not None:
        from ros_free_bridge.lifeline import die_with_parent

        die_with_parent(args.parent, pdeathsig=args.pdeathsig)
    rfd, wfd = (int(x) for x in args.fds.split(","))
    return child_main(rfd, wfd)


if __name__ == "__main__":
    raise SystemExit(main())
