"""One table for every benchmark: the ``Row`` type, the verdict rule, and the printers.

Each ``bench/<name>.py`` script exposes ``rows(quick=False, argv=()) -> list[Row]`` (run the
benchmark, return its figures) and a ``main()`` that prints them with :func:`print_table`;
``bench/run_all.py`` collects the rows of all of them into one table.

A row is one figure: what it is (with its unit), our value, the baseline measured in the same
run, the issue's target, and the verdict: ``met``, ``not met``, or ``n/a`` where the issue
gives no number to judge against. Values are kept as given (numbers or short strings); they
are formatted only when printed.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import os
import sys
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

Cell = str | int | float | None

MET, NOT_MET, NA = "met", "not met", "n/a"
VERDICTS = (MET, NOT_MET, NA)
COLUMNS = ("bench", "figure", "value", "baseline", "target", "verdict")
HEADERS = {
    "bench": "bench",
    "figure": "figure",
    "value": "our value",
    "baseline": "baseline (same run)",
    "target": "target",
    "verdict": "verdict",
}


def verdict(ok: bool | None) -> str:
    """``met`` for True, ``not met`` for False, ``n/a`` for None (no target to judge by)."""
    return NA if ok is None else (MET if ok else NOT_MET)


@dataclass(frozen=True)
class Row:
    """One benchmark figure.

    figure:   what is measured, with its unit, e.g. "check speed, 10 s clip (x real time)".
    value:    our figure.
    baseline: the baseline's figure measured in the same run ("" where the issue names none).
    target:   the issue's target as text, e.g. ">= 50" ("" where none).
    verdict:  "met", "not met" or "n/a".
    bench:    the script that measured it (filled in by run_all; "" standalone).
    """

    figure: str
    value: Cell
    baseline: Cell = ""
    target: str = ""
    verdict: str = NA
    bench: str = ""

    def __post_init__(self) -> None:
        if self.verdict not in VERDICTS:
            raise ValueError(f"Row {self.figure!r}: verdict {self.verdict!r} is not one of {VERDICTS}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> Row:
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


def cpu_counters() -> tuple[int, int] | None:
    """(steal, all) CPU time since boot in clock ticks, summed over the CPUs, from /proc/stat
    (Linux); None where it is not available. Steal is the time a virtual machine's CPUs were
    ready to run but the hypervisor ran something else: on a shared host it, not our code,
    sets the tail of timing figures."""
    try:
        with open("/proc/stat") as f:
            ticks = [int(v) for v in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    return (ticks[7] if len(ticks) > 7 else 0), sum(ticks)


def steal_percent(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float:
    """Share (%) of all CPU time between two :func:`cpu_counters` readings that was stolen
    by the hypervisor (NaN where not measured)."""
    if before is None or after is None or after[1] <= before[1]:
        return float("nan")
    return 100.0 * (after[0] - before[0]) / (after[1] - before[1])


def cell(value: Cell) -> str:
    """A value as table text: floats to 4 significant digits, None and NaN as "-"."""
    if value is None:
        return "-"
    if isinstance(value, float):
        if math.isnan(value):
            return "-"
        return f"{value:.4g}"
    return str(value)


def _columns(rows: Sequence[Row]) -> tuple[str, ...]:
    """The bench column only when some row names its bench."""
    return COLUMNS if any(r.bench for r in rows) else COLUMNS[1:]


def _cells(rows: Sequence[Row], cols: Sequence[str]) -> list[list[str]]:
    return [[cell(getattr(r, c)) for c in cols] for r in rows]


def format_table(rows: Sequence[Row]) -> str:
    """Plain-text table with aligned columns (what the terminal shows)."""
    cols = _columns(rows)
    body = _cells(rows, cols)
    head = [HEADERS[c] for c in cols]
    widths = [max(len(x) for x in col) for col in zip(head, *body)]
    lines = ["  ".join(x.ljust(w) for x, w in zip(line, widths)).rstrip() for line in [head, *body]]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_markdown(rows: Sequence[Row]) -> str:
    """GitHub-flavoured markdown table ("|" inside a cell escaped)."""
    cols = _columns(rows)
    esc = lambda s: s.replace("|", "\\|")  # noqa: E731
    lines = ["| " + " | ".join(HEADERS[c] for c in cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(esc(x) for x in line) + " |" for line in _cells(rows, cols)]
    return "\n".join(lines)


def format_csv(rows: Sequence[Row]) -> str:
    """CSV with a header of the column names in COLUMNS (always all six); numbers at full
    precision (for other programs), a missing value as an empty field."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    w.writerows([["" if v is None else v for v in (getattr(r, c) for c in COLUMNS)] for r in rows])
    return buf.getvalue()


def print_table(rows: Sequence[Row]) -> None:
    print(format_table(rows), flush=True)


def write_table(rows: Sequence[Row], path: str | os.PathLike, preamble: str = "") -> Path:
    """Write the table to ``path``: CSV for a ``.csv`` name, markdown otherwise (``preamble``
    above the table). Written to a temporary name in the same folder, then renamed, so the file
    is complete or absent."""
    path = Path(path)
    text = format_csv(rows) if path.suffix.lower() == ".csv" else (preamble + format_markdown(rows) + "\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def script_main(rows: Callable[..., list[Row]], argv: Sequence[str] | None = None) -> int:
    """A bench script's ``main``: run ``rows(argv=...)`` with the command line and print the table."""
    print_table(rows(argv=sys.argv[1:] if argv is None else list(argv)))
    return 0


def parse_args(
    parser: argparse.ArgumentParser, argv: Sequence[str], quick: bool, quick_args: Sequence[str]
) -> argparse.Namespace:
    """Parse a bench script's options, adding ``--quick``.

    With ``quick`` (or ``--quick`` on the command line) the script's ``quick_args`` (fewer
    repeats, shorter clips) are parsed first, so options given explicitly still win.
    """
    parser.add_argument(
        "--quick", action="store_true", help="short smoke run: " + (" ".join(quick_args) or "(same as the defaults)")
    )
    args = parser.parse_args(list(argv))
    if quick or args.quick:
        args = parser.parse_args([*quick_args, *argv])
        args.quick = True
    return args
