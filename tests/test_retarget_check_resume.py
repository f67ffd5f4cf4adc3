"""retarget-check writes each row as its clip ends and resumes where it stopped: a batch
really killed (SIGKILL to the whole process group, workers included) twice in mid-run and then
resumed ends with the same table as a run that was never interrupted. Plus the cases a kill can
leave on disk: a torn last line, a marker without its line, a line without its marker.
Real worker processes, real CasADi and MuJoCo (the small ub14 robot, uncompiled, no videos)."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dualflow.motion import REST_POSE, Motion
from dualflow.motion.io import save_motion
from dualflow.synthetic import make_leader
from ros_free_bridge.batch.clips import Clip
from ros_free_bridge.batch.config import BatchConfig
from ros_free_bridge.batch.results import MARKER, TIMING_COLUMNS, ClipResult, ResultLog
from ros_free_bridge.cli import main
from ros_free_bridge.errors import BridgeError

ROBOT = "ub14"
FAST = ["--robot", ROBOT, "--no-compile", "--no-video"]


def make_clips(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(5):  # standing, of different lengths: each row its own
        save_motion(Motion(np.repeat(REST_POSE[None], 20 + 5 * k, 0), 30.0), folder / f"stand{k}.npz")
    save_motion(Motion(make_leader(1.0, 30.0, 1).positions, 30.0), folder / "dance.npz")
    (folder / "broken.bvh").write_text("HIERARCHY\nROOT Hips\n{\n")
    return folder


def table(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as fh:
        return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS} for row in csv.DictReader(fh)]


def jsonl_rows(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]


def start(folder: Path, out: Path, *extra: str) -> subprocess.Popen:
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "ros_free_bridge.cli",
            "retarget-check",
            str(folder),
            "-o",
            str(out),
            "--jobs",
            "2",
            *FAST,
            *extra,
        ],
        env=env,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def kill_after_rows(proc: subprocess.Popen, out: Path, rows: int, timeout_s: float = 120.0) -> int:
    """SIGKILL the batch (its whole process group: the pool's workers too) once results.jsonl
    holds at least ``rows`` lines; the lines it held just before."""
    t0 = time.monotonic()
    path = out / "results.jsonl"
    while time.monotonic() - t0 < timeout_s:
        if proc.poll() is not None:
            pytest.fail(
                f"the batch ended before it could be killed (exit {proc.returncode}): {proc.stderr.read()[-2000:]}"
            )
        n = path.read_bytes().count(b"\n") if path.is_file() else 0
        if n >= rows:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)
            return n
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    pytest.fail(f"no {rows} rows in {timeout_s:g} s")


@pytest.mark.slow
def test_a_batch_killed_twice_and_resumed_gives_the_uninterrupted_table(tmp_path):
    folder = make_clips(tmp_path / "clips")
    whole = tmp_path / "whole"
    assert main(["retarget-check", str(folder), "-o", str(whole), "--jobs", "2", *FAST]) == 1
    expected = table(whole)
    assert [r["clip"] for r in expected] == sorted(p.name for p in folder.iterdir())
    assert {r["status"] for r in expected} >= {"pass", "error"}

    out = tmp_path / "killed"
    first = kill_after_rows(start(folder, out), out, rows=1)
    assert first < len(expected)
    second = kill_after_rows(start(folder, out, "--resume"), out, rows=first + 2)
    assert second < len(expected), "the second run finished before the kill: nothing left to resume"
    # what the kills left: whole lines only, each one a complete clip
    kept = jsonl_rows(out)
    for row in kept:
        assert json.loads((out / "clips" / row["clip"] / MARKER).read_text())["row"] == row

    assert main(["retarget-check", str(folder), "-o", str(out), "--jobs", "2", "--resume", *FAST]) == 1
    assert table(out) == expected
    rows = jsonl_rows(out)
    assert sorted(r["clip"] for r in rows) == [r["clip"] for r in expected]  # each clip once
    resumed = {r["clip"]: r for r in rows}
    for row in kept:  # the clips finished before the kills were not run again
        assert resumed[row["clip"]] == row
    assert f"of {len(expected)} clips pass" in (out / "results.md").read_text() and (out / "index.html").is_file()


def _cfg(tmp_path, **kw) -> BatchConfig:
    return BatchConfig(robot=ROBOT, out=tmp_path / "out", compile=False, video=False, **kw)


def _clip(tmp_path, name: str) -> Clip:
    """A clip with a real (small) input file, as the log stamps its inputs."""
    path = tmp_path / "in" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists():
        path.write_bytes(b"motion " + name.encode())
    return Clip(name, path)


def _record(log: ResultLog, clip: Clip, status: str = "pass") -> dict:
    res = ClipResult(clip.name, status=status, frames=30, duration_s=1.0, keypoint_error_mm=12.5, seconds=0.4)
    log.add(clip, res)
    return res.row()


def test_resume_keeps_complete_clips_and_drops_what_a_kill_left_half_written(tmp_path):
    cfg = _cfg(tmp_path)
    clips = {n: _clip(tmp_path, n) for n in ("a.npz", "sub/b.npz", "c.npz", "d.npz", "e.npz")}
    log = ResultLog(cfg, list(clips.values()))
    a, b = _record(log, clips["a.npz"]), _record(log, clips["sub/b.npz"], "fail")
    out = cfg.out
    # c: killed after its marker, before its line; d: a torn line (killed inside the write);
    # e: a line whose marker is gone (its folder was being rewritten by a later run of the clip)
    (out / "clips" / "c.npz").mkdir(parents=True)
    (out / "clips" / "c.npz" / MARKER).write_text(
        json.dumps({"row": ClipResult("c.npz", status="pass").row(), "inputs": []})
    )
    _record(log, clips["e.npz"])
    (out / "clips" / "e.npz" / MARKER).unlink()
    with open(out / "results.jsonl", "ab") as fh:
        fh.write(b'{"clip":"d.npz","status":"pa')
    with open(out / "results.csv", "ab") as fh:
        fh.write(b"d.npz,,pa")

    resumed = ResultLog(cfg, list(clips.values()), resume=True)
    assert set(resumed.complete()) == {"a.npz", "sub/b.npz"}
    assert resumed.complete()["sub/b.npz"].row() == b
    assert jsonl_rows(out) == [a, b]  # rewritten: whole lines of complete clips only
    lines = (out / "results.csv").read_text().splitlines()
    assert len(lines) == 3 and lines[0].startswith("clip,actor,status")
    # appending goes on after the kept lines
    _record(resumed, clips["d.npz"])
    assert [r["clip"] for r in jsonl_rows(out)] == ["a.npz", "sub/b.npz", "d.npz"]
    assert list(csv.DictReader(open(out / "results.csv", newline="")))[-1]["clip"] == "d.npz"


def test_a_changed_input_file_or_a_new_partner_makes_a_clip_run_again(tmp_path):
    cfg = _cfg(tmp_path)
    a, b = _clip(tmp_path, "a.npz"), _clip(tmp_path, "take_S2.bvh")
    log = ResultLog(cfg, [a, b])
    _record(log, a)
    _record(log, b, "error")  # its actor file was missing
    assert set(ResultLog(cfg, [a, b], resume=True).complete()) == {"a.npz", "take_S2.bvh"}
    a.path.write_bytes(b"another take, longer than the first")
    actor = _clip(tmp_path, "take_S1.bvh").path
    paired = Clip(b.name, b.path, actor, "take_S1.bvh")  # the actor's file is there now
    assert ResultLog(cfg, [a, paired], resume=True).complete() == {}


def test_an_interrupt_right_after_a_row_is_written_keeps_it_in_the_tables(tmp_path, monkeypatch):
    """Ctrl-C landing after a clip's line reached results.jsonl but before the batch counted
    it: results.csv, results.md and the report still list it (they are written from the lines
    on disk too); they once lacked it while --resume kept the clip (seen in the Ray Ctrl-C test
    under load)."""
    from ros_free_bridge.batch.run import run_batch

    folder = tmp_path / "clips"
    folder.mkdir()
    save_motion(Motion(np.repeat(REST_POSE[None], 20, 0), 30.0), folder / "stand.npz")
    real_add = ResultLog.add

    def add_then_interrupt(self, clip, res):
        real_add(self, clip, res)
        raise KeyboardInterrupt

    monkeypatch.setattr(ResultLog, "add", add_then_interrupt)
    cfg = _cfg(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        run_batch([Clip("stand.npz", folder / "stand.npz")], cfg, jobs=1)
    assert [row["clip"] for row in table(cfg.out)] == ["stand.npz"]
    assert "stand.npz" in (cfg.out / "results.md").read_text()


def test_without_resume_a_batch_starts_afresh(tmp_path):
    cfg = _cfg(tmp_path)
    a = _clip(tmp_path, "a.npz")
    _record(ResultLog(cfg, [a]), a)
    assert ResultLog(cfg, [a]).complete() == {}
    assert (cfg.out / "results.jsonl").read_text() == ""


def test_resume_with_other_settings_is_refused(tmp_path):
    a = _clip(tmp_path, "a.npz")
    _record(ResultLog(_cfg(tmp_path), [a]), a)
    with pytest.raises(BridgeError, match="retargeter"):
        ResultLog(_cfg(tmp_path, retargeter="streaming"), [a], resume=True)
    with pytest.raises(BridgeError, match="robot"):
        ResultLog(BatchConfig(robot="op3", out=tmp_path / "out"), [a], resume=True)
    assert set(ResultLog(_cfg(tmp_path), [a], resume=True).complete()) == {"a.npz"}  # the same settings resume


def test_resume_with_other_settings_exits_2_with_one_line(tmp_path, capsys):
    folder = tmp_path / "clips"
    folder.mkdir()
    save_motion(Motion(np.repeat(REST_POSE[None], 20, 0), 30.0), folder / "a.npz")
    a = Clip("a.npz", folder / "a.npz")
    _record(ResultLog(_cfg(tmp_path), [a]), a)
    assert main(["retarget-check", str(folder), "-o", str(tmp_path / "out"), "--resume", "--no-balance", *FAST]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "balance" in err[0] and "--resume" in err[0]


def test_the_local_engine_never_imports_ray(tmp_path):
    """Ray is an optional extra: a whole local batch (discovery, pool, log, report) runs without it."""
    (tmp_path / "clips").mkdir()
    (tmp_path / "clips" / "broken.bvh").write_text("HIERARCHY\n")
    script = (
        "import sys; from ros_free_bridge.cli import main; "
        f"code = main(['retarget-check', {str(tmp_path / 'clips')!r}, '-o', {str(tmp_path / 'out')!r}, '--no-video']); "
        "assert code == 1, code; assert 'ray' not in sys.modules, 'ray was imported'"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "out" / "index.html").is_file()
