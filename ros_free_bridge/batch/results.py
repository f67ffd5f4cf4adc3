"""The rows of a ``retarget-check`` batch: :class:`ClipResult`, the result log on disk and the tables.

Contract: a clip's marker ``OUT/clips/<clip>/result.json`` is written after its other outputs and
before its lines in ``results.jsonl``/``results.csv``; every write is whole (renamed or one synced
append), so a kill leaves each clip complete or to be run again (docs/retarget_check.md).
"""

from __future__ import annotations

import csv
import json
import os
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from ros_free_bridge.batch.clips import Clip
from ros_free_bridge.batch.config import BatchConfig, clip_dir

COLUMNS = (
    "clip",
    "actor",
    "status",
    "stage",
    "reason",
    "first_failure_s",
    "frames",
    "duration_s",
    "retime",
    "keypoint_error_mm",
    "skate_share",
    "jerk_ratio",
    "limit_violations",
    "check_reason",
    "changed",
    "seconds",
)
#: Columns that depend on the machine and its load, not on the clip (left out when two tables are compared).
TIMING_COLUMNS = ("seconds",)
#: The marker a clip's output folder gets last: its row, once every other output is written.
MARKER = "result.json"
RESULTS_JSONL, RESULTS_CSV, RESULTS_MD, SETTINGS = "results.jsonl", "results.csv", "results.md", "batch.json"


@dataclass
class ClipResult:
    """One clip's row (:data:`COLUMNS`) and the outputs it wrote (``files``)."""

    clip: str
    status: str = "error"  #: pass | fail | error
    stage: str = ""  #: load | retarget | check
    reason: str = ""
    first_failure_s: float | None = None  #: seconds into the motion file (not the re-timed trajectory)
    frames: int = 0
    duration_s: float = 0.0
    retime: float = 1.0
    keypoint_error_mm: float | None = None
    skate_share: float | None = None
    jerk_ratio: float | None = None
    limit_violations: int | None = None
    check_reason: str = ""
    #: what the robot plays differently from the person (retarget.schedule's changes: a jump kept on
    #: the ground, a spin on one foot, ...): "what start-end s (keypoint error there)", seconds
    #: into the motion file; "" when nothing was changed
    changed: str = ""
    seconds: float = 0.0
    actor: str = ""  #: a pair's actor file (relative to the folder, like ``clip``); "" for one person
    files: dict = field(default_factory=dict)  #: output name -> file name in the clip's folder (not a column)

    def row(self) -> dict:
        d = asdict(self)
        return {k: d[k] for k in COLUMNS}

    @classmethod
    def from_row(cls, row: dict) -> ClipResult:
        known = {f.name for f in fields(cls)} - {"files"}
        return cls(**{k: v for k, v in row.items() if k in known})


def _append_line(path: Path, text: str) -> None:
    """Append one line with a single write, then flush and fsync: after a kill the file ends
    with this whole line or without it (at worst a torn tail that :func:`_complete_lines` drops)."""
    data = (text.rstrip("\n") + "\n").encode()
    with open(path, "ab") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def atomic_write(path: Path, text: str, sync: bool = True) -> None:
    """Write under a temporary name and rename: the file is whole or absent. ``sync``: on
    disk before the rename (records); pages that can be made again skip it."""
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "w", newline="") as fh:
        fh.write(text)
        if sync:
            fh.flush()
            os.fsync(fh.fileno())
    tmp.replace(path)


def _complete_lines(path: Path) -> list[str]:
    """The whole lines of ``path`` (a torn last line, from a kill in mid-write, is left out)."""
    if not path.is_file():
        return []
    data = path.read_bytes()
    end = data.rfind(b"\n") + 1
    return data[:end].decode(errors="replace").splitlines()


def _csv_text(rows: list[dict], header: bool = True) -> str:
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    if header:
        w.writeheader()
    for r in rows:
        w.writerow(r)
    return buf.getvalue()


def _row_json(row: dict) -> str:
    return json.dumps(row, allow_nan=False, separators=(",", ":"))


def input_stamp(clip: Clip) -> list:
    """What a clip was made from: [file name, size in bytes, modification time in ns] of its
    motion file (and of a pair's actor file). A changed file changes it."""
    stamp = []
    for path in (clip.path, clip.actor):
        if path is not None:
            try:
                st = Path(path).stat()
                stamp.append([Path(path).name, st.st_size, st.st_mtime_ns])
            except OSError:
                stamp.append([Path(path).name, None, None])
    return stamp


class ResultLog:
    """``OUT/results.jsonl`` and ``OUT/results.csv``, one line per clip as it ends, and each
    clip's marker ``OUT/clips/<clip>/result.json``: ``{"row": the row, "inputs": input_stamp}``.

    A clip is *complete* when its marker exists, ``results.jsonl`` holds a line for it equal to
    the marker's row, and its input files (the same ones: a pair's actor too) have the size and
    modification time the marker recorded. The marker is written after every other output of
    the clip and before its lines, each write whole (a temporary file renamed, or one synced
    append), so a kill at any moment leaves a clip either complete or to be run again.

    ``resume=False`` starts both files afresh; ``resume=True`` keeps the rows of the complete
    clips among ``clips`` (both files are rewritten with just those, atomically, which also
    drops a torn last line) and refuses an output folder made with other settings
    (``OUT/batch.json``)."""

    def __init__(self, cfg: BatchConfig, clips: list[Clip] = (), resume: bool = False):
        from ros_free_bridge.errors import BridgeError

        self.cfg, self.out = cfg, Path(cfg.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.jsonl, self.csv = self.out / RESULTS_JSONL, self.out / RESULTS_CSV
        settings = cfg.settings()
        self.rows: dict[str, dict] = {}
        saved = self.out / SETTINGS
        if resume and saved.is_file():
            try:
                before = json.loads(saved.read_text())
            except ValueError:
                before = None
            if before != settings:
                diff = sorted(k for k in settings if not isinstance(before, dict) or before.get(k) != settings[k])
                raise BridgeError(
                    f"--resume: {self.out} was made with other settings ({', '.join(diff) or SETTINGS}: "
                    f"{SETTINGS} there says {before!r}); resume with the same options and robot files, "
                    "or write to another -o folder (or drop --resume to start afresh)"
                )
            self.rows = self._complete_rows(clips)
        atomic_write(saved, json.dumps(settings, indent=1) + "\n")
        rows = list(self.rows.values())
        atomic_write(self.jsonl, "".join(_row_json(r) + "\n" for r in rows))
        atomic_write(self.csv, _csv_text(rows))

    def _complete_rows(self, clips: list[Clip]) -> dict[str, dict]:
        lines = {}
        for line in _complete_lines(self.jsonl):
            try:
                row = json.loads(line)
            except ValueError:
                continue
            if isinstance(row, dict) and isinstance(row.get("clip"), str):
                lines[row["clip"]] = row  # the last line of a clip wins
        rows = {}
        for clip in clips:
            row = lines.get(clip.name)
            if row is not None and self._marker(clip.name) == {"row": row, "inputs": input_stamp(clip)}:
                rows[clip.name] = row
        return rows

    def _marker(self, name: str) -> dict | None:
        try:
            return json.loads((clip_dir(self.cfg, name) / MARKER).read_text())
        except (OSError, ValueError):
            return None

    def complete(self) -> dict[str, ClipResult]:
        """The clips already complete (by name)."""
        return {name: ClipResult.from_row(row) for name, row in self.rows.items()}

    def add(self, clip: Clip, res: ClipResult) -> None:
        """Record a clip whose outputs are all written: its marker, then its lines."""
        row = res.row()
        folder = clip_dir(self.cfg, res.clip)
        folder.mkdir(parents=True, exist_ok=True)
        marker = {"row": row, "inputs": input_stamp(clip)}
        atomic_write(folder / MARKER, json.dumps(marker, allow_nan=False, separators=(",", ":")) + "\n")
        _append_line(self.jsonl, _row_json(row))
        _append_line(self.csv, _csv_text([row], header=False))
        self.rows[res.clip] = row


def read_results(out) -> list[dict]:
    """The rows of ``OUT/results.jsonl`` in clip order (the last line per clip, whole lines
    only): what the tables and the HTML report are made from."""
    rows = {}
    for line in _complete_lines(Path(out) / RESULTS_JSONL):
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("clip"), str):
            rows[row["clip"]] = row
    return [rows[name] for name in sorted(rows)]


def write_results(results: list[ClipResult], out: Path) -> dict[str, Path]:
    """results.csv and results.md in the order given (complete or absent: written under a
    temporary name and renamed)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    csv_path, md_path = out / RESULTS_CSV, out / RESULTS_MD
    atomic_write(csv_path, _csv_text([r.row() for r in results]))
    atomic_write(md_path, markdown_table(results))
    return {"csv": csv_path, "markdown": md_path}


def markdown_table(results: list[ClipResult]) -> str:
    n_pass = sum(r.status == "pass" for r in results)
    lines = [
        f"# Retarget-and-check: {n_pass} of {len(results)} clips pass",
        "",
        "| clip | status | stage | first failure (s) | frames | retime | kp err (mm) | skate | jerk ratio "
        "| reason | changed from the person |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        cells = [
            r.clip,
            r.status.upper(),
            r.stage or "-",
            _fmt(r.first_failure_s),
            str(r.frames),
            _fmt(r.retime),
            _fmt(r.keypoint_error_mm),
            _fmt(r.skate_share),
            _fmt(r.jerk_ratio),
            (r.reason or "-").replace("|", "/"),
            (r.changed or "-").replace("|", "/"),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _fmt(v) -> str:
    return "-" if v is None else f"{v:g}" if isinstance(v, float) else str(v)
