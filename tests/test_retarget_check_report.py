"""The browsable report, opened as a person would: headless Chromium (Debian's package) loads
OUT/index.html and a clip page from disk, runs their scripts, and the rendered DOM has a row
and a working link per clip, and a video element whose file exists and that Chromium decodes.
The batch is the real CMU two-person capture joined with --pairs (the robot plays 19_01 beside
18_01), a standing clip and an unreadable file, on the OP3 with videos."""

import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest
from conftest import CMU_DIR, _require

from dualflow.motion import REST_POSE, Motion
from dualflow.motion.io import save_motion
from ros_free_bridge.batch.report_html import markdown_to_html
from ros_free_bridge.batch.results import read_results
from ros_free_bridge.cli import main

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def dump_dom(page: Path, fragment: str = "") -> str:
    """The DOM after the page's scripts ran (and 3 s of virtual time for the video's metadata)."""
    if CHROMIUM is None:
        pytest.skip("headless Chromium is not installed (Debian: apt-get install chromium; .ci/run installs it)")
    url = page.resolve().as_uri() + (f"#{fragment}" if fragment else "")
    done = subprocess.run(
        [CHROMIUM, "--headless", "--disable-gpu", "--no-sandbox", "--virtual-time-budget=3000", "--dump-dom", url],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


class Elements(HTMLParser):
    """Every start tag as (tag, attributes)."""

    def __init__(self, text: str):
        super().__init__()
        self.found: list[tuple[str, dict]] = []
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        self.found.append((tag, dict(attrs)))

    def all(self, tag: str, **want) -> list[dict]:
        return [a for t, a in self.found if t == tag and all(a.get(k) == v for k, v in want.items())]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    actor, reactor = _require(CMU_DIR / "18_01.bvh"), _require(CMU_DIR / "19_01.bvh")
    folder = tmp_path_factory.mktemp("report") / "captures"
    folder.mkdir()
    shutil.copy(actor, folder / "18_01.bvh")
    shutil.copy(reactor, folder / "19_01.bvh")
    save_motion(Motion(np.repeat(REST_POSE[None], 30, 0), 30.0), folder / "standing.npz")
    (folder / "broken.bvh").write_text("HIERARCHY\n")
    out = folder.parent / "out"
    code = main(
        [
            "retarget-check",
            str(folder),
            "--robot",
            "op3",
            "--pairs",
            "18_{name}.bvh,19_{name}.bvh",
            "-o",
            str(out),
            "--jobs",
            "2",
            "--no-compile",
        ]
    )
    assert code == 1  # the unreadable file at least
    return out


@pytest.mark.slow
def test_the_pair_is_one_clip_the_robot_playing_the_reactor(report):
    rows = {r["clip"]: r for r in read_results(report)}
    assert sorted(rows) == ["19_01.bvh", "broken.bvh", "standing.npz"]
    pair = rows["19_01.bvh"]
    assert pair["actor"] == "18_01.bvh" and pair["status"] in ("pass", "fail") and pair["frames"] >= 70
    check = json.loads((report / "clips" / "19_01.bvh" / "check.json").read_text())
    # the actor is in the check's scene: the distance to them was measured
    assert check["metrics"]["min_human_distance_m"] is not None
    assert rows["standing.npz"]["actor"] == "" and rows["broken.bvh"]["status"] == "error"


@pytest.mark.slow
def test_index_html_in_chromium_has_a_row_and_a_working_link_per_clip(report):
    dom = dump_dom(report / "index.html")
    page = Elements(dom)
    assert page.all("body", **{"data-ready": "1"}), "the page's script did not run"
    rows = page.all("tr")
    clips = [r["data-clip"] for r in rows if "data-clip" in r]
    assert clips == ["19_01.bvh", "broken.bvh", "standing.npz"]
    status = {r["clip"]: r["status"] for r in read_results(report)}
    assert [r["data-status"] for r in rows if "data-clip" in r] == [status[c] for c in clips]
    links = [a["href"] for a in page.all("a") if a.get("href", "").startswith("clips/")]
    assert links == [f"clips/{c}/index.html" for c in clips]
    for href in links:
        assert (report / unquote(href)).is_file(), href
    assert re.search(r'id="shown"[^>]*>3 of 3 clips shown<', dom)
    # nothing from the network: relative links only, inline scripts only
    assert all("://" not in a["href"] and not a["href"].startswith("//") for a in page.all("a"))
    assert page.all("script") and all("src" not in s for s in page.all("script"))


@pytest.mark.slow
def test_the_index_sorts_and_filters_in_chromium(report):
    """The view in the address (what clicking a column head and the filters write there)."""
    frames = {r["clip"]: r["frames"] for r in read_results(report)}
    page = Elements(dump_dom(report / "index.html", "sort=-frames"))
    order = [r["data-clip"] for r in page.all("tr") if "data-clip" in r]
    assert [frames[c] for c in order] == sorted(frames.values(), reverse=True)
    [head] = page.all("th", **{"data-key": "frames"})
    assert "desc" in head["class"].split()
    page = Elements(dump_dom(report / "index.html", "status=error"))
    visible = [r["data-clip"] for r in page.all("tr") if "data-clip" in r and "hidden" not in r]
    assert visible == ["broken.bvh"]
    page = Elements(dump_dom(report / "index.html", "q=18_01"))  # the pair's actor file
    assert [r["data-clip"] for r in page.all("tr") if "data-clip" in r and "hidden" not in r] == ["19_01.bvh"]


@pytest.mark.slow
def test_a_clip_page_in_chromium_shows_the_video_plots_and_reports(report):
    folder = report / "clips" / "19_01.bvh"
    dom = dump_dom(folder / "index.html")
    page = Elements(dom)
    [video] = page.all("video")
    src = folder / unquote(video["src"])
    assert src.is_file() and src.stat().st_size > 10_000 and src.name == "video.mp4"
    # Chromium decoded it: a length that only the file's frames give (the film stops soon after a fall)
    assert 0.3 < float(video["data-duration"]) < 6.0
    images = [folder / unquote(i["src"]) for i in page.all("img")]
    assert {p.name for p in images} >= {"check_joints.png", "check_torque.png", "check_balance.png"}
    assert all(p.is_file() for p in images)
    assert "Physics check" in dom and "Retarget report" in dom and "18_01.bvh" in dom
    [back] = [a for a in page.all("a") if a.get("href", "").endswith("index.html")][:1]
    assert (folder / back["href"]).resolve() == (report / "index.html").resolve()
    # an error row's page has no video, and says why the clip failed
    broken = dump_dom(report / "clips" / "broken.bvh" / "index.html")
    assert "<video" not in broken and "HIERARCHY" in broken


def test_markdown_of_our_reports_becomes_html():
    md = (
        "# Title\n\n**FAIL: fall at 1.00 s**\n\n| a | b |\n|---|---|\n| 1 | <x> |\n\n"
        "- one\n- two\n\n![Plot](check_1.png)\n"
    )
    html = markdown_to_html(md, shift=1)
    assert "<h2>Title</h2>" in html and "<strong>FAIL: fall at 1.00 s</strong>" in html
    assert "<td>&lt;x&gt;</td>" in html and "<li>two</li>" in html and 'src="check_1.png"' in html
