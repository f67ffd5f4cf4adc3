"""``run/demo --playback-margin/--playback-quantile``: the latency/smoothness trade-off reaches the loop."""

import pytest

from dualflow.motion.io import save_motion
from dualflow.synthetic import make_leader
from ros_free_bridge.cli import main
from ros_free_bridge.telemetry import read_telemetry


def test_the_playback_settings_reach_the_loop(tmp_path):
    clip = tmp_path / "actor.npz"
    save_motion(make_leader(1.0, 30.0, seed=4), clip)
    out = tmp_path / "run"
    rc = main(["run", "--actor", str(clip), "--partner", "imitate", "--transport", "record", "--quiet",
               "--playback-margin", "7", "--playback-quantile", "0.6", "--out", str(out)])
    assert rc == 0
    (session,) = [e for e in read_telemetry(out / "telemetry.dftl").events if e["kind"] == "session"]
    assert session["playback_margin_s"] == pytest.approx(0.007)
    assert session["playback_quantile"] == pytest.approx(0.6)


@pytest.mark.parametrize("command", ["run", "demo"])
@pytest.mark.parametrize("flag, value, says", [("--playback-margin", "-5", "milliseconds >= 0"),
                                               ("--playback-margin", "soon", "milliseconds >= 0"),
                                               ("--playback-quantile", "0", "(0, 1]"),
                                               ("--playback-quantile", "1.5", "(0, 1]")])
def test_a_bad_playback_setting_is_one_clear_error(tmp_path, capsys, command, flag, value, says):
    with pytest.raises(SystemExit) as exc:
        main([command, flag, value, "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert flag in err and says in err
