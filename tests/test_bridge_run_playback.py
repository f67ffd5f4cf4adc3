"""``run/demo --playback-margin/--playback-quantile/--smoothing``: the latency/smoothness trade-off reaches the loop."""

import pytest

from dualflow.motion.io import save_motion
from dualflow.synthetic import make_leader
from ros_free_bridge.cli import main
from ros_free_bridge.telemetry.log import read_telemetry


def test_the_playback_settings_reach_the_loop(tmp_path):
    clip = tmp_path / "actor.npz"
    save_motion(make_leader(1.0, 30.0, seed=4), clip)
    out = tmp_path / "run"
    rc = main(
        [
            "run",
            "--actor",
            str(clip),
            "--partner",
            "imitate",
            "--transport",
            "record",
            "--quiet",
            "--playback-margin",
            "7",
            "--playback-quantile",
            "0.6",
            "--smoothing",
            "25",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    (session,) = [e for e in read_telemetry(out / "telemetry.dftl").events if e["kind"] == "session"]
    assert session["playback_margin_s"] == pytest.approx(0.007)
    assert session["playback_quantile"] == pytest.approx(0.6)
    assert session["revision_smoothing"] == pytest.approx(25.0)


def test_the_session_defaults_play_by_the_median_arrival_and_smooth_the_revisions(tmp_path):
    from ros_free_bridge.session import ADAPTIVE_MARGIN, SessionOptions

    out = tmp_path / "run"
    assert (
        main(
            [
                "run",
                "--actor",
                "synthetic",
                "--seconds",
                "1",
                "--partner",
                "imitate",
                "--transport",
                "record",
                "--quiet",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    (session,) = [e for e in read_telemetry(out / "telemetry.dftl").events if e["kind"] == "session"]
    d = SessionOptions()
    assert (
        session["playback_margin_s"] == pytest.approx(ADAPTIVE_MARGIN)
        and session["playback_quantile"] == d.playback_quantile
    )
    assert (
        session["extrapolate_frames"] == d.extrapolate_frames
        and session["revision_smoothing"] == d.revision_smoothing > 0
    )


@pytest.mark.parametrize("command", ["run", "demo"])
@pytest.mark.parametrize(
    "flag, value, says",
    [
        ("--playback-margin", "-5", "milliseconds >= 0"),
        ("--playback-margin", "soon", "milliseconds >= 0"),
        ("--playback-quantile", "0", "(0, 1]"),
        ("--playback-quantile", "1.5", "(0, 1]"),
        ("--smoothing", "-1", "rad/s >= 0"),
        ("--smoothing", "inf", "rad/s >= 0"),
    ],
)
def test_a_bad_playback_setting_is_one_clear_error(tmp_path, capsys, command, flag, value, says):
    with pytest.raises(SystemExit) as exc:
        main([command, flag, value, "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert flag in err and says in err
