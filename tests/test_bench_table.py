"""bench/table.py (the one table every benchmark prints) and bench/run_all.py (each benchmark in
its own process; a crash or timeout becomes a row). Uses tiny fake benchmark modules written to
tmp_path, never the real benchmarks (those are timings, not tests)."""

from __future__ import annotations

import csv
import io
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import run_all  # noqa: E402
from bench.table import (  # noqa: E402
    COLUMNS,
    Row,
    cpu_counters,
    format_csv,
    format_markdown,
    format_table,
    parse_args,
    steal_percent,
    verdict,
    write_table,
)

ROWS = [
    Row("check speed (x real time)", 61.234567, 80.0, ">= 50", verdict(61.2 >= 50)),
    Row("host overhead | per cycle (ms)", 0.41, None, "< 0.3", verdict(False)),
    Row("skipped ticks", "0 / 500", "0 / 500", "", verdict(None)),
]


def test_verdict_and_row_validation():
    assert (verdict(True), verdict(False), verdict(None)) == ("met", "not met", "n/a")
    with pytest.raises(ValueError, match="verdict"):
        Row("x", 1.0, verdict="ok")
    assert Row.from_dict({**ROWS[0].to_dict(), "extra": 1}) == ROWS[0]


def test_steal_share_is_the_stolen_part_of_all_cpu_time_between_two_readings():
    assert steal_percent((10, 1000), (30, 2000)) == pytest.approx(2.0)
    assert steal_percent((10, 1000), (10, 3000)) == 0.0
    for missing in ((None, (1, 2)), ((1, 2), None), ((5, 100), (5, 100))):  # not measured, or no time passed
        assert steal_percent(*missing) != steal_percent(*missing)  # NaN
    now = cpu_counters()
    if now is not None:  # Linux: steal is part of all CPU time, and both only grow
        later = cpu_counters()
        assert 0 <= now[0] <= now[1] and later[0] >= now[0] and later[1] >= now[1]


def test_text_table_aligns_and_formats_cells():
    lines = format_table(ROWS).splitlines()
    assert lines[0].split()[:3] == ["figure", "our", "value"]
    assert "bench" not in lines[0]  # standalone rows carry no bench name
    assert set(lines[1]) <= {"-", " "}
    assert len(lines) == 2 + len(ROWS)
    assert "61.23 " in lines[2] and "61.2345" not in lines[2]  # 4 significant digits
    col = lines[0].index("verdict")
    assert [ln[col:].strip() for ln in lines[2:]] == ["met", "not met", "n/a"]
    assert " - " in lines[3]  # None baseline


def test_markdown_escapes_pipes_and_has_one_line_per_row():
    md = format_markdown(ROWS).splitlines()
    assert md[0].startswith("| figure | our value |") and md[1].startswith("|---|")
    assert len(md) == 2 + len(ROWS)
    assert "host overhead \\| per cycle" in md[3]
    assert md[3].count(" | ") == md[0].count(" | ")


def test_csv_round_trips_every_column(tmp_path):
    rows = [Row(**{**r.to_dict(), "bench": "#3 sim"}) for r in ROWS]
    parsed = list(csv.DictReader(io.StringIO(format_csv(rows))))
    assert tuple(parsed[0]) == COLUMNS
    assert [p["verdict"] for p in parsed] == ["met", "not met", "n/a"]
    assert parsed[1]["figure"] == "host overhead | per cycle (ms)" and parsed[1]["baseline"] == ""
    assert parsed[0]["bench"] == "#3 sim" and float(parsed[0]["value"]) == 61.234567  # full precision

    out = write_table(rows, tmp_path / "sub" / "t.csv")
    assert out.read_text() == format_csv(rows)
    md = write_table(rows, tmp_path / "t.md", preamble="head\n\n").read_text()
    assert md.startswith("head\n\n| bench | figure |")
    assert not [p for p in tmp_path.rglob("*.tmp")]  # no temp files left behind


def test_parse_args_quick_defaults_yield_to_explicit_options():
    import argparse

    def parser():
        p = argparse.ArgumentParser()
        p.add_argument("--seconds", type=float, default=10.0)
        p.add_argument("--repeats", type=int, default=3)
        return p

    quick = ["--seconds", "2", "--repeats", "1"]
    a = parse_args(parser(), [], False, quick)
    assert (a.seconds, a.repeats, a.quick) == (10.0, 3, False)
    a = parse_args(parser(), [], True, quick)
    assert (a.seconds, a.repeats, a.quick) == (2.0, 1, True)
    a = parse_args(parser(), ["--quick", "--repeats", "5"], False, quick)
    assert (a.seconds, a.repeats) == (2.0, 5)


FAKES = {
    "fake_ok": """
        from bench.table import Row, verdict
        def rows(quick=False):
            print("measuring ...")
            return [Row("speed (x)", 2.0 if quick else 3.0, 1.0, ">= 2", verdict(True))]
    """,
    "fake_raises": """
        def rows(quick=False):
            print("about to fail")
            raise RuntimeError("emulator port vanished")
    """,
    "fake_dies": """
        import os
        def rows(quick=False):
            os._exit(7)
    """,
    "fake_hangs": """
        import time
        def rows(quick=False):
            time.sleep(60)
    """,
}


@pytest.fixture()
def fakes(tmp_path):
    for name, src in FAKES.items():
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(src))
    return tmp_path


def test_run_all_turns_crashes_into_rows_and_keeps_going(fakes, capsys):
    rows = run_all.run_all(
        [("fake_raises", None), ("fake_ok", 9), ("fake_dies", None)], quick=True, timeout_s=60, pythonpath=[fakes]
    )
    assert len(rows) == 3
    crash, ok, died = rows
    assert run_all.is_failure(crash) and crash.verdict == "not met" and crash.bench == "fake_raises"
    assert "exit code 1" in str(crash.value) and "emulator port vanished" in str(crash.value)
    assert not run_all.is_failure(ok)
    assert (ok.bench, ok.value, ok.baseline, ok.verdict) == ("#9 fake_ok", 2.0, 1.0, "met")  # quick reached rows()
    assert run_all.is_failure(died) and "exit code 7" in str(died.value)
    err = capsys.readouterr().err
    assert "fake_raises| about to fail" in err  # a failed child's last output is shown


def test_run_all_stops_a_hanging_benchmark(fakes):
    (row,) = run_all.run_bench("fake_hangs", timeout_s=3, pythonpath=[fakes])
    assert run_all.is_failure(row) and "timed out after 3 s" in str(row.value)


def test_main_writes_the_table_and_reports_failure_in_exit_code(fakes, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(run_all, "BENCHES", (("fake_ok", 1), ("fake_raises", 2)))
    monkeypatch.setenv("PYTHONPATH", str(fakes))
    out = tmp_path / "res.csv"
    assert run_all.main(["--quick", "--out", str(out), "--timeout", "60"]) == 1
    printed = capsys.readouterr().out
    assert "#1 fake_ok" in printed and "benchmark did not finish" in printed
    parsed = list(csv.DictReader(out.open()))
    assert [p["bench"] for p in parsed] == ["#1 fake_ok", "#2 fake_raises"]
    assert parsed[1]["figure"] == "benchmark did not finish" and parsed[1]["verdict"] == "not met"
    assert run_all.main(["--only", "fake_ok", "--timeout", "60"]) == 0
