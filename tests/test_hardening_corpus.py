"""Over 300 malformed files of every format, each through the command that reads it: exit
code 2 and one line naming the file, never a traceback, a hang or silent acceptance. The
corpus and its outcome table: tests/hardening_corpus.py (also a script, to compare
revisions). The good files it is made from pass the same commands."""

from __future__ import annotations

import os
from collections import Counter

import hardening_corpus as hc
import pytest

from ros_free_bridge.cli import main

os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    root = tmp_path_factory.mktemp("corpus")
    return root, hc.build_corpus(root)


def test_the_corpus_is_large_and_covers_every_format(corpus):
    _, cases = corpus
    formats = Counter(c.fmt for c in cases)
    assert len(cases) >= 200
    assert set(formats) >= {
        "bvh",
        "motion-npz",
        "duet-npz",
        "amass-npz",
        "humanml3d-npy",
        "intergen-npy",
        "trajectory-npz",
        "telemetry",
        "telemetry-events",
        "checkpoint",
        "hardware-yaml",
        "profile-yaml",
        "music",
        "joint-map",
        "train-config",
    }
    assert sum(c.argv[0] == "run" for c in cases) >= 20  # the run command reads actors, checkpoints, robots, music


FORMATS = [
    "bvh",
    "motion-npz",
    "duet-npz",
    "amass-npz",
    "humanml3d-npy",
    "intergen-npy",
    "trajectory-npz",
    "telemetry",
    "telemetry-events",
    "checkpoint",
    "hardware-yaml",
    "profile-yaml",
    "music",
    "joint-map",
    "train-config",
]


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_malformed_file_gets_one_line_and_exit_code_2(corpus, fmt):
    _, cases = corpus
    bad = []
    for case in (c for c in cases if c.fmt == fmt):
        outcome = hc.run_case(case, timeout_s=120.0)  # the guard turns a hang into a failure, not a stuck run
        if outcome.kind != "ok":
            bad.append(f"{case.label} [{' '.join(case.argv[:2])}]: {outcome.kind}: {outcome.message.strip()[:300]}")
    assert not bad, f"{len(bad)} {fmt} case(s) not answered with one line and exit code 2:\n" + "\n".join(bad)


def test_the_good_files_the_corpus_is_made_from_pass(corpus, capsys):
    root, _ = corpus
    good = root / "good"
    for name in ("leader.npz", "leader.bvh", "duet.npz", "amass.npz"):
        assert main(["motion", "info", str(good / name)]) == 0, capsys.readouterr().err
    assert (
        main(
            [
                "check",
                str(good / "trajectory.npz"),
                "--robot",
                hc.MODEL_ROBOT,
                "--no-plots",
                "-o",
                str(root / "out" / "good_check"),
            ]
        )
        == 0
    ), capsys.readouterr().err
    tel = str(good / "telemetry.dftl")
    assert main(["plot", tel, "-o", str(root / "out" / "good_plot")]) == 0, capsys.readouterr().err
    assert main(["replay", tel, "--robot", hc.MODEL_ROBOT, "--transport", "record"]) == 0, capsys.readouterr().err
    assert "replayed 40 of 40 commands" in capsys.readouterr().err
    assert (
        main(
            [
                "run",
                "--model",
                str(good / "ckpt"),
                "--robot",
                hc.MODEL_ROBOT,
                "--generator",
                "thread",
                "--transport",
                "record",
                "--seconds",
                "1",
                "--max-duration",
                "0.3",
                "--quiet",
                "-o",
                str(root / "out" / "good_run"),
            ]
        )
        == 0
    ), capsys.readouterr().err
