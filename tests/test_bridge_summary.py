"""The printed run summary: faults by name (extrapolation is not one) and latency labelled for what it measures."""

from pathlib import Path

from ros_free_bridge.commands.run import print_summary
from ros_free_bridge.control.loop import Fault, RunSummary
from ros_free_bridge.robots import resolve_robot
from ros_free_bridge.session import SessionResult


def _result(faults, frames_ahead):
    s = RunSummary(ticks=100, frames_played=30, end_state="STOPPED", reason="the motion ended", faults=int(faults))
    s.e2e_latency = [0.1, 0.12, 0.11]
    r = SessionResult(s, Path("."), resolve_robot("op3"))
    r.pipeline_info = {"frames_ahead": frames_ahead}
    return r


def _printed(result, capsys):
    print_summary(result)
    return capsys.readouterr().out


def test_generated_partner_latency_is_labelled_beyond_the_look_ahead(capsys):
    out = _printed(_result(Fault.STARVED | Fault.EXTRAPOLATED, 10), capsys)
    assert "latency beyond the 10-frame look-ahead (333 ms more from actor frame i) p50 110 ms" in out
    assert "faults: starved; targets extrapolated" in out


def test_a_clean_run_says_no_faults_and_plain_latency(capsys):
    out = _printed(_result(Fault.NONE, None), capsys)
    assert "end-to-end latency p50 110 ms" in out
    assert "faults: none" in out and "extrapolated" not in out
