"""retarget-check --engine ray: the clips as Ray tasks on a real local Ray instance give the same
rows and files as the local engine; a worker process that dies (SIGKILL) costs its clip one
retry, and a clip whose worker dies again gets an error row; Ctrl-C (SIGINT to the batch's
process group) exits 130 and stops the Ray instance the batch started (its tasks with it), keeps
the finished rows, and --resume completes the table; in a Ray the caller started, an interrupted
batch cancels its own tasks and leaves that Ray up. Skips where Ray is not installed
(`pip install -e ".[cluster]"` installs it; CI does).

Ray runs in child processes only, never in the test process: its gRPC threads do not survive
a fork, and later tests fork worker pools from this process."""

import csv
import importlib.util
import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from dualflow.motion import REST_POSE, Motion
from dualflow.motion.io import save_motion
from dualflow.synthetic import make_duet, make_leader
from ros_free_bridge.batch.results import TIMING_COLUMNS
from ros_free_bridge.cli import main

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        importlib.util.find_spec("ray") is None,
        reason='Ray is not installed: pip install -e ".[cluster]" (CI installs it)',
    ),
]

FAST = ["--robot", "ub14", "--no-compile", "--no-video"]
ENV = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))


def table(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as fh:
        return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS} for row in csv.DictReader(fh)]


def outputs(out: Path) -> dict[str, list[str]]:
    """Each clip's output files (the page and marker aside), by clip."""
    clips = out / "clips"
    return {
        d.relative_to(clips).as_posix(): sorted(f.name for f in d.iterdir() if f.is_file())
        for d in sorted(clips.rglob("*"))
        if (d / "result.json").is_file()
    }


def standing(path: Path, frames: int = 20) -> Path:
    save_motion(Motion(np.repeat(REST_POSE[None], frames, 0), 30.0), path)
    return path


def test_ray_gives_the_local_engines_rows_and_files(tmp_path):
    clips = tmp_path / "clips"
    clips.mkdir()
    standing(clips / "stand.npz")
    save_motion(Motion(make_leader(1.0, 30.0, 1).positions, 30.0), clips / "dance.npz")
    (clips / "broken.bvh").write_text("HIERARCHY\n")
    duet = make_duet("mirror", 1.0, 30.0, 0)  # the two people of one capture, as two files
    save_motion(duet.actor, clips / "mirror_S1.npz")
    save_motion(duet.reactor, clips / "mirror_S2.npz")
    common = [str(clips), "--jobs", "2", "--pairs", "{name}_S1.npz,{name}_S2.npz", *FAST]
    assert main(["retarget-check", *common, "-o", str(tmp_path / "local")]) == 1
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "ros_free_bridge.cli",
            "retarget-check",
            *common,
            "-o",
            str(tmp_path / "ray"),
            "--engine",
            "ray",
        ],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 1, done.stderr[-3000:]
    local, remote = table(tmp_path / "local"), table(tmp_path / "ray")
    assert [r["clip"] for r in remote] == ["broken.bvh", "dance.npz", "mirror_S2.npz", "stand.npz"]
    assert remote == local
    assert remote[2]["actor"] == "mirror_S1.npz" and remote[3]["status"] == "pass"
    assert outputs(tmp_path / "ray") == outputs(tmp_path / "local")
    assert "check.md" in outputs(tmp_path / "ray")["stand.npz"]


#: The driver of a batch whose per-clip function kills its Ray worker: the real check, except
#: that the worker checking ``once`` dies the first time (as a crash in a native library would
#: kill it) and the one checking ``always`` dies every time. The function lives in the driver's
#: ``__main__``, so Ray sends it to the workers by value; there ``clip_check.check_clip`` is the real one.
DYING_WORKERS = textwrap.dedent("""
    import json, os, signal, sys
    from pathlib import Path
    import ray
    from ros_free_bridge.batch import clip_check
    from ros_free_bridge.batch.config import BatchConfig
    from ros_free_bridge.batch.run import run_batch

    def check_clip_with_dying_workers(path, cfg, name=None, **kw):
        path = Path(path)
        flag = path.with_name(path.name + ".died")
        if path.stem == "always" or (path.stem == "once" and not flag.exists()):
            flag.touch()
            os.kill(os.getpid(), signal.SIGKILL)
        return clip_check.check_clip(path, cfg, name, **kw)

    folder, out = Path(sys.argv[1]), Path(sys.argv[2])
    clip_check.check_clip = check_clip_with_dying_workers  # what the engine sends to the workers
    files = sorted(folder.glob("*.npz"))
    cfg = BatchConfig(robot="ub14", out=out, compile=False, video=False)
    rows = run_batch(files, cfg, jobs=2, progress=False, engine="ray")
    print(json.dumps({"rows": [r.row() for r in rows], "ray_still_up": ray.is_initialized()}))
""")


def run_driver(tmp_path: Path, source: str, clips: tuple[str, ...]) -> dict:
    """Run ``source`` as a Python script (its own process: Ray never starts in this one) with a
    folder of standing clips named ``clips`` and an output folder; the JSON it printed last."""
    folder = tmp_path / "clips"
    folder.mkdir()
    for n in clips:
        standing(folder / f"{n}.npz")
    script = tmp_path / "driver.py"
    script.write_text(source)
    done = subprocess.run(
        [sys.executable, str(script), str(folder), str(tmp_path / "out")],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_a_dead_worker_gets_one_retry_then_an_error_row(tmp_path):
    report = run_driver(tmp_path, DYING_WORKERS, ("always", "fine", "once"))
    folder = tmp_path / "clips"
    by = {r["clip"]: r for r in report["rows"]}
    assert by["once.npz"]["status"] == "pass"  # died once, passed when retried
    assert by["fine.npz"]["status"] == "pass"
    assert by["always.npz"]["status"] == "error" and "worker died" in by["always.npz"]["reason"]
    assert [r["status"] for r in table(tmp_path / "out")] == ["error", "pass", "pass"]
    assert (folder / "once.npz.died").exists() and not report["ray_still_up"]  # the batch stopped its Ray


#: A caller that started Ray itself and runs a batch in it: one clip ends at once, the other would
#: hold its CPU for ten minutes; the caller's ``done`` is interrupted when the first row comes.
CALLERS_RAY = textwrap.dedent("""
    import json, sys, time
    import ray
    from ros_free_bridge.batch.clips import as_clips
    from ros_free_bridge.batch.config import BatchConfig
    from ros_free_bridge.batch.ray_engine import run_ray
    from ros_free_bridge.batch.results import ClipResult

    def work(path, cfg, name=None, **kw):
        if "slow" in str(path):
            time.sleep(600)
        return ClipResult(name, status="pass")

    def done(clip, res):
        raise KeyboardInterrupt

    ray.init(address="local", num_cpus=1, include_dashboard=False, log_to_driver=False)
    cfg = BatchConfig(robot="ub14", out=sys.argv[2], compile=False, video=False)
    clips = as_clips([f"{sys.argv[1]}/quick.npz", f"{sys.argv[1]}/slow.npz"], None)
    try:
        run_ray(clips, cfg, done, work=work)
    except KeyboardInterrupt:
        pass
    deadline = time.monotonic() + 60  # the cancelled task's worker is being killed
    while ray.available_resources().get("CPU", 0) < 1 and time.monotonic() < deadline:
        time.sleep(0.2)
    print(json.dumps({"cpu_free": ray.available_resources().get("CPU", 0), "ray_up": ray.is_initialized()}))
""")


def test_an_interrupted_batch_in_the_callers_ray_cancels_its_tasks_and_leaves_ray_up(tmp_path):
    report = run_driver(tmp_path, CALLERS_RAY, ("quick", "slow"))
    assert report == {"cpu_free": 1.0, "ray_up": True}  # the slow clip's task no longer holds the CPU


def _session_processes(sid: int) -> list[str]:
    """Command lines of the processes still alive in session ``sid``."""
    found = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[3]) == sid:
                    found.append((d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:120])
            except (OSError, IndexError, ValueError):
                pass
    return found


def test_ctrl_c_stops_the_batchs_ray_and_resume_completes(tmp_path):
    clips = tmp_path / "clips"
    clips.mkdir()
    for k in range(8):
        standing(clips / f"s{k}.npz", 20 + k)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "ros_free_bridge.cli",
            "retarget-check",
            str(clips),
            "-o",
            str(out),
            "--engine",
            "ray",
            "--jobs",
            "2",
            *FAST,
        ],
        env=ENV,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    t0 = time.monotonic()
    while not ((out / "results.jsonl").is_file() and (out / "results.jsonl").read_text().count("\n") >= 1):
        if proc.poll() is not None or time.monotonic() - t0 > 180:
            os.killpg(proc.pid, signal.SIGKILL) if proc.poll() is None else None
            pytest.fail(f"no first row (exit {proc.returncode}): {proc.stderr.read()[-2000:]}")
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does: the whole foreground group
    t1 = time.monotonic()
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail("the batch did not stop within 60 s of Ctrl-C")
    assert proc.returncode == 130, err[-2000:]
    assert time.monotonic() - t1 < 30 and "--resume" in err
    deadline = time.monotonic() + 15  # Ray's processes (GCS, raylet, workers) are ending
    while _session_processes(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _session_processes(proc.pid) == []
    done = table(out)
    assert 1 <= len(done) < 8 and "interrupted" in (out / "index.html").read_text()

    assert main(["retarget-check", str(clips), "-o", str(out), "--resume", "--jobs", "2", *FAST]) == 0
    assert [r["clip"] for r in table(out)] == [f"s{k}.npz" for k in range(8)]
    assert {r["status"] for r in table(out)} == {"pass"}
    assert (out / "results.jsonl").read_text().count("\n") == 8  # no clip recorded twice


def test_an_address_where_no_cluster_answers_is_one_error_naming_it(tmp_path):
    clips = tmp_path / "clips"
    clips.mkdir()
    standing(clips / "s.npz")
    with socket.socket() as s:  # a port nothing listens on once this closes
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    done = subprocess.run(
        [sys.executable, "-m", "ros_free_bridge.cli", "retarget-check", str(clips), "-o", str(tmp_path / "out")]
        + ["--engine", "ray", "--address", f"127.0.0.1:{port}", *FAST],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr[-2000:]
    last = done.stderr.strip().splitlines()[-1]
    assert (
        last.startswith(f"error: --address 127.0.0.1:{port}: no Ray cluster answers there")
        and "ray start --head" in last
    )
    assert "Traceback" not in done.stderr
