"""The live actor UDP stream: the packet format and a real loopback socket."""

import socket
import struct
import time

import numpy as np
import pytest

from dualflow.motion import REST_POSE
from ros_free_bridge.sources import udp_packet as pk
from ros_free_bridge.sources.udp import UdpActorSource


def test_packet_layout_is_as_documented():
    data = pk.encode_frame(7, 1.5, REST_POSE)
    assert len(data) == pk.FRAME_SIZE == 288
    assert data[:4] == b"DFA1" and data[4] == 1 and data[5] == 1
    assert struct.unpack_from("<I", data, 8)[0] == 7
    assert struct.unpack_from("<d", data, 16)[0] == 1.5
    assert struct.unpack_from("<f", data, 24 + 4 * (3 * 15 + 2))[0] == pytest.approx(REST_POSE[15, 2])  # head z
    back = pk.decode(data)
    np.testing.assert_allclose(back.positions, REST_POSE, atol=1e-6)
    assert len(pk.encode_estop(1, 0.0)) == pk.ESTOP_SIZE == 24


@pytest.mark.parametrize(
    "data, match",
    [
        (b"xx", "shorter"),
        (b"NOPE" + bytes(284), "magic"),
        (pk.encode_frame(1, 0.0, REST_POSE)[:-4], "288 bytes"),
        (b"DFA1" + bytes([2]) + bytes(283), "version"),
        (b"DFA1" + bytes([1, 9]) + bytes(282), "type"),
    ],
)
def test_malformed_packets_are_rejected(data, match):
    with pytest.raises(pk.PacketError, match=match):
        pk.decode(data)


def test_nan_positions_are_rejected():
    pos = REST_POSE.copy()
    pos[3, 1] = np.nan
    with pytest.raises(pk.PacketError, match="NaN"):
        pk.decode(pk.encode_frame(1, 0.0, pos))


def test_sequence_wraps_around():
    assert pk.is_newer(0, 0xFFFFFFFF) and not pk.is_newer(5, 5) and not pk.is_newer(4, 5)


def _poll_until(src, n, timeout=2.0):
    got, end = [], time.monotonic() + timeout
    while len(got) < n and time.monotonic() < end:
        got += src.poll()
        time.sleep(0.001)
    return got


def test_loopback_stream_drops_garbage_and_stale_packets_and_sees_estop():
    stops = []
    with UdpActorSource(on_estop=stops.append) as src:
        host, port = src.address
        assert host == "127.0.0.1"
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for seq in (1, 2, 2, 1, 3):  # a duplicate and a stale packet
            tx.sendto(pk.encode_frame(seq, seq * 0.1, REST_POSE + seq), (host, port))
        tx.sendto(b"garbage", (host, port))
        tx.sendto(pk.encode_estop(4, 0.4), (host, port))
        frames = _poll_until(src, 3)
        time.sleep(0.05)
        frames += src.poll()
        tx.close()
    assert [f.seq for f in frames] == [1, 2, 3]
    np.testing.assert_allclose(frames[-1].positions, REST_POSE + 3, atol=1e-5)
    assert src.stats.garbage == 1 and src.stats.out_of_order == 2
    assert src.estopped and stops == ["udp e-stop packet"]
