"""The local engine of ``retarget-check``: clips in a pool of worker processes on this machine.

A clip whose worker process dies costs only its own row, an ``error`` (docs/retarget_check.md). The per-clip
function is looked up in :mod:`ros_free_bridge.batch.clip_check` when the pool starts.
"""

from __future__ import annotations

import os
import sys

from ros_free_bridge.batch import clip_check
from ros_free_bridge.batch.clips import Clip
from ros_free_bridge.batch.config import BatchConfig
from ros_free_bridge.batch.results import ClipResult


def run_local(clips: list[Clip], cfg: BatchConfig, jobs: int | None, done) -> None:
    """The local engine: ``jobs`` worker processes, ``done(clip, result)`` called as each clip ends. The
    clips a dead worker took down are re-run one per process; one that kills its process again gets an
    ``error`` row."""
    if not clips:
        return
    jobs = max(1, min(jobs or usable_cores(), len(clips)))
    pending = list(range(len(clips)))
    while pending:
        lost = _pool_pass(pending, clips, cfg, jobs, done)
        # the clips a dead worker took down: those that were in flight (the first submitted:
        # jobs, plus the one the pool had queued) run one per process, to find each one that
        # kills its process; the rest run again in a pool
        suspects, pending = lost[: jobs + 1], lost[jobs + 1 :]
        for i in suspects:
            if _pool_pass([i], clips, cfg, 1, done):
                reason = (
                    "the worker process died while checking this clip (a crash in a native library, or out "
                    f"of memory); retarget it alone with `dualflow-bridge retarget {clips[i].path}` to see "
                    "the crash"
                )
                done(clips[i], ClipResult(clips[i].name, status="error", reason=reason))


def _pool_pass(indices, clips: list[Clip], cfg: BatchConfig, jobs: int, done) -> list[int]:
    """Run ``indices`` in a pool of ``jobs`` processes, calling ``done(clip, result)`` as each ends;
    the indices whose result was lost because a worker process died."""
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    lost = []
    with ProcessPoolExecutor(jobs, mp_context=_pool_context(cfg)) as pool:
        try:
            futures = {
                pool.submit(clip_check.check_clip, clips[i].path, cfg, clips[i].name, actor=clips[i].actor): i
                for i in indices
            }
            for fut in as_completed(futures):
                i = futures[fut]
                try:
                    res = fut.result()
                except BrokenProcessPool:
                    lost.append(i)
                    continue
                except Exception as exc:  # noqa: BLE001 - e.g. a result that cannot be sent back
                    res = ClipResult(clips[i].name, status="error", reason=f"unexpected {type(exc).__name__}: {exc}")
                done(clips[i], res)
        except BaseException:  # Ctrl-C: no clip is started any more, and the running ones stop
            workers = list((getattr(pool, "_processes", None) or {}).values())
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in workers:
                proc.terminate()
            raise
    return sorted(lost)


def _pool_context(cfg: BatchConfig):
    """How the local engine's workers are made.

    ``fork`` starts them at once with everything this process imported (and, in tests,
    patched). It is not safe after this process used OpenGL (EGL: a forked worker that films a
    clip hangs creating its context) or loaded Ray (its gRPC threads and locks do not survive a
    fork): with videos, or with Ray loaded, a fork server started clean (this package and its
    solvers imported, no OpenGL context) makes the workers instead."""
    import multiprocessing as mp

    if not cfg.video and sys.modules.get("ray") is None:
        return mp.get_context("fork")
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["ros_free_bridge.batch.clip_check", "retarget.offline", "sim.check"])
    return ctx


def usable_cores() -> int:
    """Cores this process may run on (its affinity, where the OS has one), at least 1."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:
        return os.cpu_count() or 1
