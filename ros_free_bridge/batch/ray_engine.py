"""The Ray engine of ``retarget-check``: each clip is one Ray task, on a cluster or a local instance.

The only module that imports Ray. A task carries the clip's motion files and returns its outputs as
bytes, which the driver writes under ``OUT/clips/<clip>/``: no shared filesystem needed. A task whose
worker dies is retried once, then gets an ``error`` row. Setup and failure handling: docs/retarget_check.md.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import tempfile
import time
from pathlib import Path

import ray

from ros_free_bridge.batch import clip_check
from ros_free_bridge.batch.clips import Clip
from ros_free_bridge.batch.config import BatchConfig, clip_dir
from ros_free_bridge.batch.local import usable_cores
from ros_free_bridge.batch.results import ClipResult

#: Object store of a Ray instance this engine starts (bytes): clips and their outputs are small.
LOCAL_OBJECT_STORE_BYTES = 256 * 1024 * 1024
#: Tasks in flight per CPU of the cluster (one running, one queued behind it).
IN_FLIGHT_PER_CPU = 2
#: Attempts after the first when a task's worker process dies.
MAX_RETRIES = 1
#: Seconds an interrupted batch in the caller's Ray waits for its cancelled tasks to end.
CANCEL_WAIT_S = 30.0


def start(jobs: int | None = None, address: str | None = None) -> bool:
    """Connect to the cluster at ``address`` or start a local Ray instance with ``jobs`` CPUs
    (default: every core this process may use), no dashboard and a small object store.
    True when this call connected (and so should shut down); False when Ray was already up."""
    if ray.is_initialized():
        return False
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    common = dict(
        include_dashboard=False,
        log_to_driver=False,
        logging_level=logging.WARNING,
        runtime_env={"env_vars": {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}},
    )
    if address:
        try:
            _reachable(address)
            ray.init(address=address, **common)
        except ConnectionError as exc:
            from ros_free_bridge.errors import BridgeError

            raise BridgeError(
                f"--address {address}: no Ray cluster answers there ({exc}); start one with "
                "`ray start --head` on its head node and give the address it prints (or 'auto' on a node "
                "of the cluster), or leave --address out to start Ray on this machine"
            ) from None
    else:
        ray.init(
            address="local", num_cpus=jobs or usable_cores(), object_store_memory=LOCAL_OBJECT_STORE_BYTES, **common
        )
    return True


def _reachable(address: str, timeout_s: float = 5.0) -> None:
    """Raise ConnectionError when a ``host:port`` address takes no TCP connection within
    ``timeout_s`` (Ray itself keeps retrying for minutes). Other forms ('auto', ray://) are left to Ray."""
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit() or "://" in address:
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ConnectionError(f"no answer at {host}:{port}: {exc}") from None


def _inputs(clip: Clip) -> dict[str, bytes]:
    """The clip's motion files as bytes, by their path as the driver names them."""
    return {str(p): Path(p).read_bytes() for p in (clip.path, clip.actor) if p is not None}


def _run_clip(work, clip: Clip, cfg: BatchConfig, inputs: dict[str, bytes]):
    """Body of one Ray task: (row, {relative path: bytes} of the clip's outputs)."""
    with tempfile.TemporaryDirectory(prefix="dualflow_clip_") as tmp:
        tmp = Path(tmp)

        def local(path, slot: str):
            if path is None or Path(path).is_file():
                return path
            copy = tmp / "in" / slot / Path(path).name  # the same file name: it names the motion
            copy.parent.mkdir(parents=True, exist_ok=True)
            copy.write_bytes(inputs[str(path)])
            return copy

        workdir = tmp / "out"
        res = work(local(clip.path, "reactor"), cfg, clip.name, actor=local(clip.actor, "actor"), workdir=workdir)
        files = {}
        if workdir.is_dir():
            files = {
                p.relative_to(workdir).as_posix(): p.read_bytes() for p in sorted(workdir.rglob("*")) if p.is_file()
            }
        return res, files


def _save_outputs(cfg: BatchConfig, name: str, files: dict[str, bytes]) -> None:
    """Write a clip's outputs where the local engine would have written them."""
    folder = clip_dir(cfg, name)
    shutil.rmtree(folder, ignore_errors=True)
    for rel, data in files.items():
        path = folder / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def _died(clip: Clip, exc: Exception) -> ClipResult:
    kind = type(exc).__name__
    first = (str(exc).strip().splitlines() or [""])[0][:200]
    return ClipResult(
        clip.name,
        status="error",
        reason=f"the Ray worker died while checking this clip, also when retried ({kind}: {first}); "
        f"retarget it alone with `dualflow-bridge retarget {clip.path}` to see the crash "
        "(the workers' logs are in the Ray session folder, /tmp/ray/session_latest/logs)",
    )


def run_ray(
    clips: list[Clip], cfg: BatchConfig, done, jobs: int | None = None, address: str | None = None, work=None
) -> None:
    """Run ``clips`` as Ray tasks, calling ``done(clip, result)`` in the driver as each ends (after
    its outputs are written under ``OUT``). ``work``: the per-clip function (default
    :func:`ros_free_bridge.batch.clip_check.check_clip`), sent to the workers with the task."""
    if not clips:
        return
    work = work or clip_check.check_clip  # looked up now, as the local engine does
    owner = start(jobs, address)
    try:
        task = ray.remote(num_cpus=1, max_retries=MAX_RETRIES)(_run_clip)
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        limit = max(1, IN_FLIGHT_PER_CPU * (min(jobs, cpus) if jobs else cpus))
        queue = list(reversed(clips))
        running: dict = {}
        try:
            _drain(task, work, cfg, queue, running, limit, done)
        except BaseException:  # Ctrl-C, or a failure in the driver
            if not owner:  # the caller's Ray stays up: stop this batch's tasks in it
                _cancel(list(running))
            raise
    finally:
        # Shutting down ends this driver's job, and Ray stops the job's tasks with it (a local
        # instance this call started stops altogether). No ray.cancel first: cancelling a task
        # whose result is already on its way back trips a check in Ray's task manager ("Tried
        # to complete task that was not pending") that ends the driver with exit code 1 before
        # the tables are written; it did so in 1 of 40 Ctrl-C's at random moments of a batch.
        if owner:
            ray.shutdown()


def _cancel(refs: list, wait_s: float = CANCEL_WAIT_S) -> None:
    """Force-cancel the tasks ``refs`` and wait up to ``wait_s`` for them to end, cancelling again
    each second those still running. One cancel was not always enough: on a loaded machine the
    test's slow task kept its CPU for over a minute in 2 of 6 runs; cancelling again, in none of 12."""
    pending, deadline = list(refs), time.monotonic() + wait_s
    while pending and time.monotonic() < deadline:
        for ref in pending:
            ray.cancel(ref, force=True, recursive=True)
        _, pending = ray.wait(pending, num_returns=len(pending), timeout=1.0, fetch_local=False)


def _drain(task, work, cfg: BatchConfig, queue: list[Clip], running: dict, limit: int, done) -> None:
    """Keep ``limit`` tasks in flight until ``queue`` and ``running`` (ref -> clip) are empty."""
    while queue or running:
        while queue and len(running) < limit:
            clip = queue.pop()
            running[task.remote(work, clip, cfg, _inputs(clip))] = clip
        ready, _ = ray.wait(list(running), num_returns=1)
        for ref in ready:
            clip = running.pop(ref)
            try:
                res, files = ray.get(ref)
            except ray.exceptions.RayTaskError as exc:  # the per-clip function raised (it should not)
                res, files = (
                    ClipResult(clip.name, status="error", reason=f"unexpected {type(exc.cause).__name__}: {exc.cause}"),
                    {},
                )
            except ray.exceptions.RayError as exc:  # the worker (or its node) died twice
                res, files = _died(clip, exc), {}
            _save_outputs(cfg, clip.name, files)
            done(clip, res)
