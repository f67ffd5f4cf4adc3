"""The Dynamixel packet codec against the ROBOTIS e-Manual's worked examples and
against dynamixel-sdk's own packet functions.

Examples: e-Manual "Protocol 2.0" (https://emanual.robotis.com/docs/en/dxl/protocol2/)
and "Protocol 1.0" (https://emanual.robotis.com/docs/en/dxl/protocol1/).
"""

from __future__ import annotations

import dynamixel_sdk as sdk
import pytest
from dynamixel_sdk.protocol1_packet_handler import Protocol1PacketHandler
from dynamixel_sdk.protocol2_packet_handler import Protocol2PacketHandler
from hypothesis import given, settings
from hypothesis import strategies as st

from ros_free_bridge import BridgeError
from ros_free_bridge.dynamixel import protocol as dp


def h(text: str) -> bytes:
    return bytes.fromhex(text.replace("0x", "").replace(",", " "))


# (id, instruction, params, expected packet) -- instruction packets from the e-Manual.
INSTRUCTION_EXAMPLES = [
    ("ping", 0x01, dp.PING, "", "FF FF FD 00 01 03 00 01 19 4E"),
    ("broadcast ping", 0xFE, dp.PING, "", "FF FF FD 00 FE 03 00 01 31 42"),
    ("read present position", 0x01, dp.READ, "84 00 04 00", "FF FF FD 00 01 07 00 02 84 00 04 00 1D 15"),
    ("write goal 512", 0x01, dp.WRITE, "74 00 00 02 00 00", "FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89"),
    (
        "reg write goal velocity",
        0x01,
        dp.REG_WRITE,
        "68 00 C8 00 00 00",
        "FF FF FD 00 01 09 00 04 68 00 C8 00 00 00 AE 8E",
    ),
    ("action", 0x01, dp.ACTION, "", "FF FF FD 00 01 03 00 05 02 CE"),
    ("factory reset except ID", 0x01, dp.FACTORY_RESET, "01", "FF FF FD 00 01 04 00 06 01 A1 E6"),
    ("reboot", 0x01, dp.REBOOT, "", "FF FF FD 00 01 03 00 08 2F 4E"),
    ("clear multi-turn", 0x01, dp.CLEAR, "01 44 58 4C 22", "FF FF FD 00 01 08 00 10 01 44 58 4C 22 B1 DC"),
    ("sync read", 0xFE, dp.SYNC_READ, "84 00 04 00 01 02", "FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA"),
    (
        "sync write",
        0xFE,
        dp.SYNC_WRITE,
        "74 00 04 00 01 96 00 00 00 02 AA 00 00 00",
        "FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87",
    ),
    (
        "bulk read",
        0xFE,
        dp.BULK_READ,
        "01 90 00 02 00 02 92 00 01 00",
        "FF FF FD 00 FE 0D 00 92 01 90 00 02 00 02 92 00 01 00 1A 05",
    ),
    (
        "bulk write",
        0xFE,
        dp.BULK_WRITE,
        "01 20 00 02 00 A0 00 02 1F 00 01 00 50",
        "FF FF FD 00 FE 10 00 93 01 20 00 02 00 A0 00 02 1F 00 01 00 50 B7 68",
    ),
    (
        "fast sync read",
        0xFE,
        dp.FAST_SYNC_READ,
        "84 00 04 00 03 07 04",
        "FF FF FD 00 FE 0A 00 8A 84 00 04 00 03 07 04 20 F2",
    ),
]

# (id, error, params, expected packet) -- status packets from the e-Manual.
STATUS_EXAMPLES = [
    ("ping ID 1", 0x01, 0x00, "06 04 26", "FF FF FD 00 01 07 00 55 00 06 04 26 65 5D"),
    ("ping ID 2", 0x02, 0x00, "06 04 26", "FF FF FD 00 02 07 00 55 00 06 04 26 6F 6D"),
    ("read ID 1", 0x01, 0x00, "A6 00 00 00", "FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0"),
    ("sync read ID 2", 0x02, 0x00, "1F 08 00 00", "FF FF FD 00 02 08 00 55 00 1F 08 00 00 BA BE"),
    ("write ack", 0x01, 0x00, "", "FF FF FD 00 01 04 00 55 00 A1 0C"),
    ("bulk read voltage", 0x01, 0x00, "77 00", "FF FF FD 00 01 06 00 55 00 77 00 C3 69"),
    ("bulk read temperature", 0x02, 0x00, "24", "FF FF FD 00 02 05 00 55 00 24 8B A9"),
]

#: Fast Sync Read reply for ID3 = 166, ID7 = 2079, ID4 = 1023 (one packet, per-part CRCs).
FAST_SYNC_REPLY = "FF FF FD 00 FE 19 00 55 00 03 A6 00 00 00 84 08 00 07 1F 08 00 00 16 CA 00 04 FF 03 00 00 D1 9E"
#: Fast Bulk Read reply for ID3 position 166 (4 B), ID7 PWM 421 (2 B), ID4 temperature 31 (1 B).
FAST_BULK_REPLY = "FF FF FD 00 FE 14 00 55 00 03 A6 00 00 00 67 A4 00 07 A5 01 24 74 00 04 1F D9 C1"


@pytest.mark.parametrize(
    "name,pid,inst,params,expected", INSTRUCTION_EXAMPLES, ids=[e[0] for e in INSTRUCTION_EXAMPLES]
)
def test_instruction_packets_match_emanual(name, pid, inst, params, expected):
    raw = dp.encode_instruction(pid, inst, h(params))
    assert raw == h(expected)
    pkt = dp.decode_packet(raw)
    assert (pkt.id, pkt.instruction, pkt.params, pkt.error) == (pid, inst, h(params), None)


@pytest.mark.parametrize("name,pid,err,params,expected", STATUS_EXAMPLES, ids=[e[0] for e in STATUS_EXAMPLES])
def test_status_packets_match_emanual(name, pid, err, params, expected):
    assert dp.encode_status(pid, err, h(params)) == h(expected)
    pkt = dp.decode_packet(h(expected))
    assert pkt.is_status and (pkt.id, pkt.error, pkt.params) == (pid, err, h(params))


def test_fast_sync_read_reply_matches_emanual_with_cumulative_crcs():
    parts = [
        (0, 3, (166).to_bytes(4, "little")),
        (0, 7, (2079).to_bytes(4, "little")),
        (0, 4, (1023).to_bytes(4, "little")),
    ]
    assert dp.encode_fast_status(parts) == h(FAST_SYNC_REPLY)
    assert dp.decode_fast_status(h(FAST_SYNC_REPLY), [4, 4, 4]) == parts


def test_fast_bulk_read_reply_matches_emanual():
    parts = [(0, 3, (166).to_bytes(4, "little")), (0, 7, (421).to_bytes(2, "little")), (0, 4, bytes([31]))]
    assert dp.encode_fast_status(parts) == h(FAST_BULK_REPLY)
    # The e-Manual's Fast Bulk Read *instruction* example repeats the Fast Sync Read CRC
    # (20 F2) by mistake; the CRC of its bytes is 0x2DDA (sent DA 2D), which is what we produce.
    raw = dp.encode_instruction(0xFE, dp.FAST_BULK_READ, h("03 84 00 04 00 07 7C 00 02 00 04 92 00 01 00"))
    assert raw[-2:] == h("DA 2D")


def test_fast_read_reply_with_a_broken_part_is_rejected():
    raw = bytearray(h(FAST_SYNC_REPLY))
    raw[18] ^= 0x01  # a data byte of ID 7's part
    with pytest.raises(BridgeError, match="servo ID 7"):
        dp.decode_fast_status(bytes(raw), [4, 4, 4])


def test_byte_stuffing_worked_example():
    # Writing FF FF FD 00 to address 0x74 puts the header pattern inside the parameters:
    # one FD is inserted, LEN grows by one, and the CRC covers the stuffed bytes.
    raw = dp.encode_instruction(1, dp.WRITE, h("74 00 FF FF FD 00"))
    assert raw[:7] == h("FF FF FD 00 01 0A 00")
    assert raw[7:-2] == h("03 74 00 FF FF FD FD 00")
    assert dp.crc16(raw[:-2]) == raw[-2] | (raw[-1] << 8)
    assert dp.decode_packet(raw).params == h("74 00 FF FF FD 00")
    assert dp.stuff(h("FF FF FD FF FF FD")) == h("FF FF FD FD FF FF FD FD")
    assert dp.unstuff(h("FF FF FD FD FF FF FD FD")) == h("FF FF FD FF FF FD")


def crc_bitwise(data: bytes, crc: int = 0) -> int:
    """The definition, one bit at a time: polynomial 0x8005 (x^16 + x^15 + x^2 + 1), MSB
    first, init 0, no final XOR."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def test_crc_is_the_dynamixel_polynomial():
    assert dp.crc16(h("FF FF FD 00 01 03 00 01")) == 0x4E19  # the e-Manual's PING packet
    assert dp.crc16(b"456", dp.crc16(b"123")) == dp.crc16(b"123456")
    assert dp.crc16(b"123456789") == crc_bitwise(b"123456789") == 0xFEE8  # CRC-16/UMTS check value


@settings(max_examples=80, deadline=None)
@given(st.binary(max_size=300), st.integers(0, 0xFFFF), st.integers(0, 300))
def test_crc_equals_the_bitwise_definition_on_any_buffer(data, start, cut):
    """Any bytes-like input (the transport passes memoryviews of replies), any running start."""
    expected = crc_bitwise(data, start)
    assert dp.crc16(data, start) == expected
    assert dp.crc16(bytearray(data), start) == expected
    assert dp.crc16(memoryview(data)[cut:], dp.crc16(memoryview(data)[:cut], start)) == expected


def test_decode_rejects_bad_crc_and_length_with_a_clear_message():
    good = h("FF FF FD 00 01 03 00 01 19 4E")
    with pytest.raises(dp.PacketError, match="CRC mismatch"):
        dp.decode_packet(good[:-1] + b"\x00")
    with pytest.raises(dp.PacketError, match="length field"):
        dp.decode_packet(good + b"\x00")
    with pytest.raises(dp.PacketError, match="header"):
        dp.decode_packet(b"\x00" * 10)


# ---------------------------------------------------------------- protocol 1.0

P1_EXAMPLES = [
    ("broadcast write ID", 0xFE, dp.WRITE, "03 01", "FF FF FE 04 03 03 01 F6"),
    ("reg write goal 500", 0x01, dp.REG_WRITE, "1E F4 01", "FF FF 01 05 04 1E F4 01 E2"),
    ("broadcast action", 0xFE, dp.ACTION, "", "FF FF FE 02 05 FA"),
    ("factory reset", 0x00, dp.FACTORY_RESET, "", "FF FF 00 02 06 F7"),
    (
        "sync write",
        0xFE,
        dp.SYNC_WRITE,
        "1E 04 00 10 00 50 01 01 20 02 60 03",
        "FF FF FE 0E 83 1E 04 00 10 00 50 01 01 20 02 60 03 67",
    ),
    ("bulk read", 0xFE, dp.BULK_READ, "00 02 01 1E 02 02 24", "FF FF FE 09 92 00 02 01 1E 02 02 24 1D"),
    ("read temperature", 0x01, dp.READ, "2B 01", "FF FF 01 04 02 2B 01 CC"),
]


@pytest.mark.parametrize("name,pid,inst,params,expected", P1_EXAMPLES, ids=[e[0] for e in P1_EXAMPLES])
def test_protocol1_instruction_packets_match_emanual(name, pid, inst, params, expected):
    assert dp.encode_instruction1(pid, inst, h(params)) == h(expected)
    pkt = dp.decode_packet1(h(expected), status=False)
    assert (pkt.id, pkt.instruction, pkt.params) == (pid, inst, h(params))


@pytest.mark.parametrize(
    "pid,err,params,expected",
    [
        (0x01, 0x00, "", "FF FF 01 02 00 FC"),
        (0x00, 0x00, "", "FF FF 00 02 00 FD"),
        (0x01, 0x00, "00 80", "FF FF 01 04 00 00 80 7A"),
        (0x02, 0x00, "00 80", "FF FF 02 04 00 00 80 79"),
        (0x01, 0x00, "20", "FF FF 01 03 00 20 DB"),
    ],
)
def test_protocol1_status_packets_match_emanual(pid, err, params, expected):
    assert dp.encode_status1(pid, err, h(params)) == h(expected)
    pkt = dp.decode_packet1(h(expected), status=True)
    assert (pkt.id, pkt.error, pkt.params) == (pid, err, h(params))
    with pytest.raises(dp.PacketError, match="checksum"):
        dp.decode_packet1(h(expected)[:-1] + bytes([h(expected)[-1] ^ 1]), status=True)


# ---------------------------------------------------------------- against dynamixel-sdk


class CapturePort:
    """The minimal port interface the SDK's packet functions use: records writes and
    replays canned bytes for reads (a stand-in for the serial port, not for our code)."""

    def __init__(self, incoming: bytes = b"") -> None:
        self.is_using = False
        self.written = b""
        self.incoming = bytearray(incoming)
        self.timed_out = False

    def clearPort(self):  # noqa: N802 (SDK naming)
        pass

    def writePort(self, packet):  # noqa: N802
        self.written += bytes(packet)
        return len(packet)

    def readPort(self, length):  # noqa: N802
        chunk = bytes(self.incoming[:length])
        del self.incoming[:length]
        return chunk

    def setPacketTimeout(self, n):  # noqa: N802
        pass

    def isPacketTimeout(self):  # noqa: N802
        self.timed_out = True
        return True


params_st = st.binary(min_size=0, max_size=40) | st.lists(st.sampled_from([0xFF, 0xFD, 0x00, 0x01]), max_size=40).map(
    bytes
)


def _needs_stuffing(body: bytes) -> bool:
    return b"\xff\xff\xfd" in body


@settings(max_examples=80, deadline=None)
@given(servo_id=st.integers(0, 252), address=st.integers(0, 700), data=params_st.filter(lambda b: len(b) > 0))
def test_write_instruction_bytes_equal_the_sdks(servo_id, address, data):
    port = CapturePort()
    Protocol2PacketHandler().writeTxOnly(port, servo_id, address, len(data), list(data))
    body = address.to_bytes(2, "little") + data
    ours = dp.encode_instruction(servo_id, dp.WRITE, body)
    if not _needs_stuffing(bytes([dp.WRITE]) + body):
        assert port.written == ours
    else:
        # dynamixel-sdk 4.1.0 (Python) computes the stuffed packet but drops it when the
        # length changes (addStuffing's result is discarded), so it sends the body
        # unstuffed with a CRC over those bytes. Our decoder (and so the emulator) still
        # reads the SDK's packet as the SDK meant it.
        assert len(port.written) < len(ours)  # the SDK's packet went out unstuffed
        # Our decoder reads the SDK's packet as meant, unless the data itself holds
        # FF FF FD FD: unstuffed, that is indistinguishable from a stuffed FF FF FD,
        # and a real servo would read it that way too.
        sent = dp.decode_packet(port.written)
        expected = body if b"\xff\xff\xfd\xfd" not in body else dp.unstuff(body)
        assert (sent.id, sent.instruction, sent.params) == (servo_id, dp.WRITE, expected)


@settings(max_examples=60, deadline=None)
@given(
    ids=st.lists(st.integers(0, 252), min_size=1, max_size=20, unique=True),
    address=st.integers(0, 200),
    length=st.integers(1, 8),
    fast=st.booleans(),
)
def test_sync_read_instruction_bytes_equal_the_sdks(ids, address, length, fast):
    port = CapturePort()
    Protocol2PacketHandler().syncReadTx(port, address, length, ids, len(ids), fast)
    inst = dp.FAST_SYNC_READ if fast else dp.SYNC_READ
    ours = dp.encode_instruction(0xFE, inst, address.to_bytes(2, "little") + length.to_bytes(2, "little") + bytes(ids))
    assert port.written == ours


@settings(max_examples=60, deadline=None)
@given(servo_id=st.integers(0, 252), error=st.integers(0, 255), data=params_st)
def test_sdk_decodes_our_status_packets(servo_id, error, data):
    raw = dp.encode_status(servo_id, error, data)
    port = CapturePort(raw)
    rx, result = Protocol2PacketHandler().rxPacket(port, False)
    assert result == sdk.COMM_SUCCESS
    assert rx[4] == servo_id and rx[8] == error
    length = rx[5] | (rx[6] << 8)
    body = dp.stuff(bytes([dp.STATUS, error]) + data)
    if body.count(b"\xff\xfd\xfd") == body.count(b"\xff\xff\xfd\xfd"):
        assert bytes(rx[9 : 7 + length - 2]) == data  # the SDK removed our stuffing
    # else: dynamixel-sdk 4.1.0 unstuffs in place and, after one removal, can mistake a
    # later FF FD FD for a stuffed marker; our own decoder reads the packet right:
    assert dp.decode_packet(raw).params == data


@settings(max_examples=30, deadline=None)
@given(values=st.lists(st.integers(0, 2**32 - 1), min_size=1, max_size=20))
def test_sdk_group_fast_sync_read_parses_our_reply(values):
    ids = list(range(1, len(values) + 1))
    parts = [(0, i, v.to_bytes(4, "little")) for i, v in zip(ids, values)]
    port = CapturePort(dp.encode_fast_status(parts))
    ph = Protocol2PacketHandler()
    group = sdk.GroupSyncRead(port, ph, 132, 4)
    for i in ids:
        group.addParam(i)
    assert group.fastSyncReadRxPacket() == sdk.COMM_SUCCESS
    assert [group.getData(i, 132, 4) for i in ids] == values


@settings(max_examples=60, deadline=None)
@given(data=st.binary(max_size=64))
def test_crc_equals_sdk_update_crc(data):
    assert dp.crc16(data) == Protocol2PacketHandler().updateCRC(0, list(data), len(data))


@settings(max_examples=60, deadline=None)
@given(servo_id=st.integers(0, 253), address=st.integers(0, 255), data=st.binary(min_size=1, max_size=30))
def test_protocol1_write_bytes_equal_the_sdks(servo_id, address, data):
    port = CapturePort()
    Protocol1PacketHandler().writeTxOnly(port, servo_id, address, len(data), list(data))
    assert port.written == dp.encode_instruction1(servo_id, dp.WRITE, bytes([address]) + data)


@settings(max_examples=60, deadline=None)
@given(servo_id=st.integers(0, 253), error=st.integers(0, 0x7F), data=st.binary(max_size=30))
def test_sdk_protocol1_decodes_our_status_packets(servo_id, error, data):
    port = CapturePort(dp.encode_status1(servo_id, error, data))
    rx, result = Protocol1PacketHandler().rxPacket(port)
    assert result == sdk.COMM_SUCCESS
    assert (rx[2], rx[4], bytes(rx[5:-1])) == (servo_id, error, data)


# ---------------------------------------------------------------- stream framing


@settings(max_examples=60, deadline=None)
@given(
    payloads=st.lists(params_st, min_size=1, max_size=5),
    cuts=st.lists(st.integers(1, 50), max_size=20),
    garbage=st.binary(max_size=8).filter(lambda g: b"\xff" not in g),
)
def test_stream_parser_reassembles_packets_across_arbitrary_reads(payloads, cuts, garbage):
    packets = [dp.encode_instruction(i + 1, dp.WRITE, b"\x74\x00" + p) for i, p in enumerate(payloads)]
    stream = garbage + b"".join(packets)
    parser = dp.StreamParser(protocol=2)
    frames, pos = [], 0
    for n in cuts + [len(stream)]:
        frames += parser.feed(stream[pos : pos + n])
        pos += n
    assert [f.raw for f in frames] == packets
    assert all(f.valid and f.protocol == 2 for f in frames)
    assert parser.pending == 0


def test_stream_parser_flags_bad_crc_and_mixes_protocols():
    good2 = dp.encode_instruction(1, dp.PING)
    bad2 = good2[:-1] + bytes([good2[-1] ^ 0x55])
    good1 = dp.encode_instruction1(3, dp.READ, b"\x24\x02")
    frames = dp.StreamParser(protocol=None).feed(bad2 + good1 + good2)
    assert [(f.protocol, f.valid) for f in frames] == [(2, False), (1, True), (2, True)]
    assert dp.StreamParser(protocol=2).feed(good1) == []
    with pytest.raises(BridgeError, match="protocol must be"):
        dp.StreamParser(protocol=3)
