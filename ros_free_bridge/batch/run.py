"""Run a ``retarget-check`` batch: clips to rows on disk, with the local or the Ray engine.

Rows are recorded as each clip ends (:class:`ResultLog`); the tables and the HTML report are
written when the batch ends or is interrupted. Ray is imported only for ``engine="ray"``.
"""

from __future__ import annotations

from pathlib import Path

from ros_free_bridge.batch.clips import Clip, as_clips
from ros_free_bridge.batch.config import BatchConfig, clip_dir
from ros_free_bridge.batch.local import run_local
from ros_free_bridge.batch.report_html import write_html_report
from ros_free_bridge.batch.results import ClipResult, ResultLog, read_results, write_results


def run_batch(
    files,
    cfg: BatchConfig,
    jobs: int | None = None,
    progress: bool = True,
    folder=None,
    engine: str = "local",
    address: str | None = None,
    resume: bool = False,
) -> list[ClipResult]:
    """Check every clip; rows in clip order. Each row is written to disk as its clip ends
    (:class:`ResultLog`); at the end (or on Ctrl-C) the tables and the HTML report are written.

    files:   :class:`Clip` objects or motion files (named relative to ``folder``, default by file name).
    jobs:    local engine: worker processes (default: every core this process may use); ray: the
             CPUs of the Ray instance it starts, or at most this many clips at once on a cluster.
    engine:  "local" or "ray" (``address``: a Ray cluster to join; None starts a local instance).
    resume:  skip the clips a previous run in ``cfg.out`` completed with the same settings.
    """
    from tqdm import tqdm

    from ros_free_bridge.errors import BridgeError

    if engine not in ("local", "ray"):
        raise BridgeError(f"engine {engine!r}: use 'local' or 'ray'")
    clips = as_clips(files, folder)
    names = [c.name for c in clips]
    if len(set(names)) != len(names):
        raise BridgeError(
            f"two clips share a name ({sorted(n for n in names if names.count(n) > 1)[0]}); give files from one folder"
        )
    for n in names:
        clip_dir(cfg, n)  # each name stays inside OUT/clips (raises otherwise)
    if engine == "ray":
        try:
            from ros_free_bridge.batch.ray_engine import run_ray
        except ImportError as exc:
            raise BridgeError(
                f'--engine ray needs Ray ({exc}); install it with `pip install -e ".[cluster]"` '
                "(or `pip install 'ray>=2.40,<3'`), or use the local engine"
            ) from None
    log = ResultLog(cfg, clips, resume=resume)
    wanted = set(names)
    results: dict[str, ClipResult] = {n: r for n, r in log.complete().items() if n in wanted}
    todo = [c for c in clips if c.name not in results]
    if resume and progress and results:
        print(f"resuming: {len(results)} of {len(clips)} clips already complete in {cfg.out}")
    try:
        with tqdm(total=len(todo), desc="retarget-check", unit="clip", disable=not progress) as bar:

            def done(clip: Clip, res: ClipResult) -> None:
                res.actor = clip.actor_name
                log.add(clip, res)
                results[clip.name] = res
                bar.update()
                bar.set_postfix_str(f"{res.clip}: {res.status}", refresh=True)

            runnable = []
            for c in todo:
                if c.problem:
                    done(c, ClipResult(c.name, status="error", stage="load", reason=c.problem))
                else:
                    runnable.append(c)
            if engine == "ray":
                run_ray(runnable, cfg, done, jobs=jobs, address=address)
            else:
                run_local(runnable, cfg, jobs, done)
    finally:
        # a row whose line was written as the interrupt came (between log.add and results) is
        # on disk, so it is in the tables too; they once lacked it while --resume kept the clip
        for row in read_results(cfg.out):
            if row["clip"] in wanted:
                results.setdefault(row["clip"], ClipResult.from_row(row))
        finish(cfg, clips, [results[c.name] for c in clips if c.name in results])
    return [results[n] for n in names]


def finish(cfg: BatchConfig, clips: list[Clip], results: list[ClipResult]) -> dict[str, Path]:
    """The tables (``results.csv`` in clip order, ``results.md``) and the HTML report, from the rows."""
    paths = write_results(results, cfg.out)
    paths["html"] = write_html_report(cfg.out, results, total=len(clips))
    return paths
