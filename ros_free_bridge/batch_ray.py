"""The Ray engine of ``retarget-check``: each clip is one Ray task.

    dualflow-bridge retarget-check clips/ --engine ray                    # a local Ray instance
    dualflow-bridge retarget-check clips/ --engine ray --address auto     # the cluster this node belongs to
    dualflow-bridge retarget-check clips/ --engine ray --address ray://head:10001

Only this module imports Ray (``pip install -e ".[cluster]"``); the local engine never does.

The task runs the same per-clip function as the local engine (:func:`ros_free_bridge.batch.check_clip`)
and needs no shared filesystem: the clip's motion file(s) travel with the task (a worker reads
the original path where it exists on its node, so a single machine or a shared filesystem
gives the same messages as the local engine, and the shipped copy elsewhere), the outputs are
written to a scratch folder on the worker and come back as bytes, and the driver writes them
under ``OUT/clips/<clip>/`` before recording the row. What every node needs: this package
installed (the same version), the same Ray version, and for ``--robot DIR`` that folder at the
same path.

Failures: a task whose worker process dies (a crash in a native library, out of memory, a
lost node) is run once more (Ray's ``max_retries=1``); if it dies again the clip gets an
``error`` row and the batch goes on. Ctrl-C cancels the tasks in flight (``ray.cancel``,
force: their workers are killed), stops a Ray instance this run started (``ray.shutdown``;
on a cluster it only disconnects), and leaves every finished clip recorded for ``--resume``.

At most a few tasks per CPU are in flight at a time, so a dataset of any size keeps the
driver's memory and Ray's object store small, and Ctrl-C has little to cancel.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path

import ray

from ros_free_bridge import batch
from ros_free_bridge.batch import BatchConfig, Clip, ClipResult, _usable_cores, clip_dir

#: Object store of a Ray instance this engine starts (bytes): clips and their outputs are small.
LOCAL_OBJECT_STORE_BYTES = 256 * 1024 * 1024
#: Tasks in flight per CPU of the cluster (one running, one queued behind it).
IN_FLIGHT_PER_CPU = 2
#: Attempts after the first when a task's worker process dies.
MAX_RETRIES = 1


def start(jobs: int | None = None, address: str | None = None) -> bool:
    """Connect to the cluster at ``address`` or start a local Ray instance with ``jobs`` CPUs
    (default: every core this process may use), no dashboard and a small object store.
    True when this call connected (and so should shut down); False when Ray was already up."""
    if ray.is_initialized():
        return False
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    common = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING,
                  runtime_env={"env_vars": {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}})
    if address:
        ray.init(address=address, **common)
    else:
        ray.init(address="local", num_cpus=jobs or _usable_cores(), object_store_memory=LOCAL_OBJECT_STORE_BYTES,
                 **common)
    return True


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
            files = {p.relative_to(workdir).as_posix(): p.read_bytes() for p in sorted(workdir.rglob("*")) if p.is_file()}
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
    return ClipResult(clip.name, status="error",
                      reason=f"the Ray worker died while checking this clip, also when retried ({kind}: {first}); "
                             f"retarget it alone with `dualflow-bridge retarget {clip.path}` to see the crash "
                             "(the workers' logs are in the Ray session folder, /tmp/ray/session_latest/logs)")


def run_ray(clips: list[Clip], cfg: BatchConfig, done, jobs: int | None = None, address: str | None = None,
            work=None) -> None:
    """Run ``clips`` as Ray tasks, calling ``done(clip, result)`` in the driver as each ends (after
    its outputs are written under ``OUT``). ``work``: the per-clip function (default
    :func:`ros_free_bridge.batch.check_clip`), sent to the workers with the task."""
    if not clips:
        return
    work = work or batch.check_clip  # looked up now, as the local engine does
    owner = start(jobs, address)
    try:
        task = ray.remote(num_cpus=1, max_retries=MAX_RETRIES)(_run_clip)
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        limit = max(1, IN_FLIGHT_PER_CPU * (min(jobs, cpus) if jobs else cpus))
        queue = list(reversed(clips))
        running: dict = {}
        try:
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
                        res, files = ClipResult(clip.name, status="error",
                                                reason=f"unexpected {type(exc.cause).__name__}: {exc.cause}"), {}
                    except ray.exceptions.RayError as exc:  # the worker (or its node) died twice
                        res, files = _died(clip, exc), {}
                    _save_outputs(cfg, clip.name, files)
                    done(clip, res)
        except BaseException:  # Ctrl-C (or a failure in the driver): stop every task in flight
            for ref in running:
                ray.cancel(ref, force=True, recursive=True)
            raise
    finally:
        if owner:
            ray.shutdown()
