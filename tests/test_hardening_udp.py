"""The live UDP actor under attack: forged sequence jumps, absurd values, garbage, floods and a
second sender, all sent on 127.0.0.1 only. The robot keeps streaming the genuine sender's
frames, and every drop is counted by kind in the status line, the summary and the events."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from dualflow.motion import REST_POSE
from dualflow.synthetic import make_leader
from ros_free_bridge.cli import main
from ros_free_bridge.commands.run import StatusLine, remote_actor_warning
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.sources import udp_packet as pk
from ros_free_bridge.sources.udp import UdpActorSource, is_loopback
from ros_free_bridge.telemetry.log import read_telemetry

LOOPBACK = "127.0.0.1"


def _drain(src, n, timeout=3.0):
    """Poll until ``n`` frames came or ``timeout`` s passed (a bound on waiting, not a timing check)."""
    got, end = [], time.monotonic() + timeout
    while len(got) < n and time.monotonic() < end:
        got += src.poll()
        time.sleep(0.002)
    time.sleep(0.02)
    return got + src.poll()


@pytest.fixture
def source():
    events = []
    src = UdpActorSource(on_event=lambda kind, **info: events.append((kind, info)))
    src.events = events
    yield src
    src.close()


@pytest.fixture
def tx():
    socks = []

    def make():
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        socks.append(s)
        return s

    yield make
    for s in socks:
        s.close()


def test_a_forged_sequence_jump_from_the_sender_does_not_stall_its_genuine_frames(source, tx):
    s = tx()
    for seq in (1, 2, 3, 3 + 2**31 - 1, 3 + 2**31 - 1 + 1, 4, 5):
        s.sendto(pk.encode_frame(seq, 0.0, REST_POSE, stream=7), source.address)
    frames = _drain(source, 5)
    assert [f.seq for f in frames] == [1, 2, 3, 4, 5]
    assert source.stats.seq_jump == 1 and source.stats.out_of_order == 1


def test_values_that_are_finite_in_float32_but_no_person_are_dropped_as_out_of_range(source, tx):
    s = tx()
    huge = np.full((22, 3), 3e38, np.float32)
    nan = REST_POSE.copy()
    nan[0, 0] = np.nan
    far = REST_POSE + 11.0
    for seq, pos in ((1, REST_POSE), (2, huge), (3, nan), (4, far), (5, REST_POSE)):
        s.sendto(pk.encode_frame(seq, 0.0, pos), source.address)
    s.sendto(b"DFA1 not a packet", source.address)
    frames = _drain(source, 2)
    assert [f.seq for f in frames] == [1, 5]
    assert source.stats.out_of_range == 3 and source.stats.garbage == 1
    assert np.abs(np.concatenate([f.positions for f in frames])).max() <= pk.MAX_ABS_M


def test_another_sender_is_foreign_while_the_first_streams_but_its_estop_counts(source, tx):
    genuine, other = tx(), tx()
    genuine.sendto(pk.encode_frame(1, 0.0, REST_POSE), source.address)
    assert [f.seq for f in _drain(source, 1)] == [1]
    other.sendto(pk.encode_frame(2**31, 0.0, REST_POSE + 1), source.address)
    genuine.sendto(pk.encode_frame(2, 0.0, REST_POSE), source.address)
    other.sendto(pk.encode_estop(1, 0.0), source.address)
    frames = _drain(source, 1)
    assert [f.seq for f in frames] == [2]
    assert source.stats.foreign == 1 and source.estopped and source.stats.estops == 1


def test_a_restarted_sender_is_recognised_by_its_stream_id_or_by_silence(tx):
    with UdpActorSource(takeover_s=0.2) as src:
        s = tx()
        for seq in (500, 501):
            s.sendto(pk.encode_frame(seq, 0.0, REST_POSE, stream=1), src.address)
        for seq in (1, 2):  # the same sender restarted: a new stream id, its sequence from 1
            s.sendto(pk.encode_frame(seq, 0.0, REST_POSE, stream=2), src.address)
        assert [f.seq for f in _drain(src, 4)] == [500, 501, 1, 2]
        time.sleep(0.3)  # silent longer than takeover_s: a new process on another port takes over
        t = tx()
        t.sendto(pk.encode_frame(1, 0.0, REST_POSE, stream=3), src.address)
        assert [f.seq for f in _drain(src, 1)] == [1]
        assert src.stats.senders == 3 and src.stats.dropped == 0


def test_a_flood_costs_a_bounded_amount_of_work_per_poll_and_is_reported(source, tx):
    s = tx()
    for _ in range(600):
        s.sendto(b"x" * 40, source.address)
    time.sleep(0.05)
    assert source.poll() == []
    assert source.stats.received == source.max_packets and source.stats.flooded == 1
    kinds = [k for k, _ in source.events]
    assert "udp_drops" in kinds
    drops = dict(source.events[kinds.index("udp_drops")][1])
    assert drops["garbage"] == source.max_packets and drops["flooded"] == 1


def test_listening_beyond_loopback_needs_an_explicit_option_and_warns(capsys, tmp_path):
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and not is_loopback("0.0.0.0")
    with pytest.raises(BridgeError, match="--allow-remote-actor"):
        UdpActorSource("0.0.0.0", 0)  # refused before binding
    code = main(
        [
            "run",
            "--actor",
            "udp://0.0.0.0:9870",
            "--partner",
            "imitate",
            "--transport",
            "record",
            "--robot",
            "ub14",
            "--quiet",
            "-o",
            str(tmp_path / "out"),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "0.0.0.0" in err[0] and "--allow-remote-actor" in err[0]
    assert "any host" in remote_actor_warning("udp://0.0.0.0:9870", True)
    assert remote_actor_warning("udp://127.0.0.1:9870", False) is None


def test_the_status_line_shows_the_drop_counters(source, tx):
    s = tx()
    s.sendto(b"garbage", source.address)
    _drain(source, 0, timeout=0.1)

    class Loop:  # what StatusLine reads of a loop
        class summary:
            ticks, e2e_latency, frames_played, interventions = 0, [], 0, 0

        class state:
            name = "RUNNING"

        deadline_misses = 0
        source_stats = source.stats

    import io

    out = io.StringIO()
    StatusLine(out, every_s=0.0)(Loop, None, 0)
    assert "udp 1 dropped (garbage 1)" in out.getvalue()


ATTACKER = r"""
import socket, sys, time
import numpy as np
sys.path.insert(0, {root!r})
from ros_free_bridge.sources import udp_packet as pk
port = int(sys.argv[1])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
rest = np.zeros((22, 3), np.float32)
to = ("127.0.0.1", port)
for k in range(40):
    s.sendto(pk.encode_frame(2**31 - 1 + k, 0.0, rest), to)           # forged sequence jumps
    s.sendto(pk.encode_frame(k, 0.0, np.full((22, 3), 3e38, np.float32)), to)  # finite, absurd
    s.sendto(b"DFA1" + bytes(40), to)                                      # garbage
    s.sendto(pk.encode_frame(0, 0.0, rest + 1.0), to)                      # stale
    if k % 10 == 5:
        for _ in range(3000):                                              # a flood burst
            s.sendto(b"\x00" * 288, to)
    time.sleep(0.04)
print("attacker done", flush=True)
"""


def test_attacks_from_another_local_sender_do_not_stop_the_genuine_stream(tmp_path, capsys):
    from pathlib import Path

    probe = UdpActorSource()
    port = probe.address[1]
    probe.close()
    leader = make_leader(5.0, 30.0, seed=3)
    out = tmp_path / "run"
    done = threading.Event()
    attacker = []

    def genuine():
        events = out / "telemetry.dftl.events.jsonl"
        end = time.monotonic() + 60
        while time.monotonic() < end and not (events.exists() and '"kind": "ready"' in events.read_text()):
            time.sleep(0.02)
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        root = str(Path(__file__).resolve().parents[1])
        attacker.append(
            subprocess.Popen(
                [sys.executable, "-c", ATTACKER.format(root=root), str(port)], stdout=subprocess.PIPE, text=True
            )
        )
        t0 = time.monotonic()
        for k in range(leader.n_frames):
            s.sendto(pk.encode_frame(k + 1, time.time(), leader.positions[k], stream=12345), (LOOPBACK, port))
            time.sleep(max(0.0, t0 + (k + 1) / 30.0 - time.monotonic()))
        s.close()
        done.set()

    threading.Thread(target=genuine, daemon=True).start()
    code = main(
        [
            "run",
            "--actor",
            f"udp://{LOOPBACK}:{port}",
            "--partner",
            "imitate",
            "--transport",
            "record",
            "--robot",
            "ub14",
            "--max-duration",
            "3",
            "--quiet",
            "-o",
            str(out),
        ]
    )
    printed = capsys.readouterr().out
    assert attacker and "attacker done" in attacker[0].communicate(timeout=60)[0]
    assert code == 0, printed  # ended by --max-duration, not by a watchdog
    tel = read_telemetry(out / "telemetry.dftl")
    (end,) = [e for e in tel.events if e["kind"] == "end"]
    assert end["summary"]["frames_played"] >= 45  # of the 90 the genuine sender sent in those 3 s
    (summary_line,) = [line for line in printed.splitlines() if line.startswith("udp input:")]
    assert "dropped" in summary_line and "foreign" in summary_line
    (final,) = [e for e in tel.events if e["kind"] == "input"]
    assert final["dropped"]["foreign"] > 0 and final["senders"] == 1
    assert any(e["kind"] == "udp_drops" for e in tel.events)
    senders = [e for e in tel.events if e["kind"] == "udp_sender"]
    assert len(senders) == 1 and senders[0]["stream"] == 12345
