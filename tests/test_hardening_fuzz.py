"""Property-based fuzzing of every reader (hypothesis): whatever bytes, headers or values
come in, a reader either returns something that satisfies its contract or raises its
package's one error type; never another exception, a huge allocation or a hang.

Each property runs a fixed number of examples (derandomized, no example database), so the
suite takes the same time on every run."""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dualflow.errors import DualFlowError
from dualflow.motion.io import load_any, read_bvh, save_motion
from dualflow.motion.io.npfile import MAX_ARRAY_BYTES, read_npy
from dualflow.motion.io.units import FPS_RANGE, MIN_FRAMES
from dualflow.synthetic import make_leader
from firmware_cfg.config import load_config
from firmware_cfg.errors import ConfigError
from retarget.errors import RetargetError
from retarget.profile import RetargetProfile
from retarget.trajectory import RobotTrajectory
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.sources import udp_packet as pk
from ros_free_bridge.telemetry.log import MAGIC, TelemetryWriter, read_events, read_telemetry

FUZZ = settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

LEADER = make_leader(1.0, 30.0, 0)


def _good_bytes(tmp_path_factory, name):
    path = tmp_path_factory.mktemp("good") / name
    save_motion(LEADER, path)
    return path.read_bytes()


@pytest.fixture(scope="module")
def good_bvh(tmp_path_factory):
    return _good_bytes(tmp_path_factory, "leader.bvh")


@pytest.fixture(scope="module")
def good_npz(tmp_path_factory):
    return _good_bytes(tmp_path_factory, "leader.npz")


def _mutate(data: bytes, edits) -> bytes:
    """Apply (position fraction, kind, value) edits: overwrite a byte, cut, or insert."""
    b = bytearray(data)
    for frac, kind, value in edits:
        if not b:
            break
        pos = int(frac * (len(b) - 1))
        if kind == "set":
            b[pos] = value
        elif kind == "cut":
            del b[pos:]
        else:
            b[pos:pos] = bytes([value]) * (value % 7 + 1)
    return bytes(b)


EDITS = st.lists(
    st.tuples(st.floats(0, 1), st.sampled_from(["set", "cut", "insert"]), st.integers(0, 255)), min_size=1, max_size=6
)


def _check_motion(m) -> None:
    for person in (m.actor, m.reactor) if hasattr(m, "actor") else (m,):
        assert person.n_frames >= MIN_FRAMES
        assert FPS_RANGE[0] <= person.fps <= FPS_RANGE[1]
        assert np.isfinite(person.positions).all()


# -- BVH ---------------------------------------------------------------------------------------
@FUZZ
@given(edits=EDITS)
def test_bvh_mutations_read_or_raise_the_package_error(tmp_path, good_bvh, edits):
    path = tmp_path / "x.bvh"
    path.write_bytes(_mutate(good_bvh, edits))
    try:
        read_bvh(path)
        _check_motion(load_any(path))
    except DualFlowError:
        pass


BVH_WORDS = st.sampled_from(
    [
        "HIERARCHY",
        "ROOT",
        "JOINT",
        "End",
        "Site",
        "{",
        "}",
        "OFFSET",
        "CHANNELS",
        "3",
        "6",
        "Xposition",
        "Zrotation",
        "0",
        "1e308",
        "-1",
        "nan",
        "MOTION",
        "Frames:",
        "Frame Time:",
        "0.0333",
        "1000000000",
        "\n",
    ]
)


@FUZZ
@given(words=st.lists(BVH_WORDS, max_size=300), depth=st.integers(0, 2000))
def test_bvh_token_soup_and_deep_nesting_raise_the_package_error(tmp_path, words, depth):
    nest = "".join(f"JOINT j{k}\n{{\nOFFSET 0 1 0\nCHANNELS 1 Xrotation\n" for k in range(depth))
    path = tmp_path / "soup.bvh"
    path.write_text("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\n" + nest + " ".join(words))
    try:
        read_bvh(path)
    except DualFlowError:
        pass


# -- npy / npz ---------------------------------------------------------------------------------
DIMS = st.one_of(st.integers(0, 100), st.integers(0, 2**63 - 1), st.integers(-5, -1))
DESCR = st.sampled_from(["<f8", "<f4", "|O", "<i4", "|b1", "<c16", "<U5", "<zz", "V8", "[('a', '<f8')]"])


def _npy(shape, descr, payload: bytes, fortran=False) -> bytes:
    header = (
        "{'descr': "
        + (descr if descr.startswith("[") else repr(descr))
        + f", 'fortran_order': {fortran}, 'shape': {tuple(shape)!r}, }}"
    )
    text = header.encode("latin1")
    text += b" " * (64 - (10 + len(text) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text + payload


@FUZZ
@given(shape=st.lists(DIMS, max_size=4), descr=DESCR, payload=st.binary(max_size=2048), fortran=st.booleans())
def test_npy_headers_never_allocate_beyond_the_limit(tmp_path, shape, descr, payload, fortran):
    path = tmp_path / "x.npy"
    path.write_bytes(_npy(shape, descr, payload, fortran))
    try:
        arr = read_npy(path)
    except DualFlowError:
        return
    assert arr.nbytes <= MAX_ARRAY_BYTES and not arr.dtype.hasobject
    try:
        _check_motion(load_any(path))
    except DualFlowError:
        pass


@FUZZ
@given(edits=EDITS)
def test_npz_mutations_read_or_raise_the_package_error(tmp_path, good_npz, edits):
    path = tmp_path / "x.npz"
    path.write_bytes(_mutate(good_npz, edits))
    try:
        _check_motion(load_any(path))
    except DualFlowError:
        pass


ARRAYS = st.one_of(
    st.builds(
        lambda n, j, v: np.full((n, j, 3), v),
        st.integers(0, 5),
        st.sampled_from([21, 22, 24]),
        st.floats(allow_nan=True, allow_infinity=True),
    ),
    st.builds(np.array, st.one_of(st.floats(), st.text(max_size=5), st.lists(st.floats(), max_size=3))),
    st.builds(lambda s: _npy(s, "<f8", b"\0" * 64), st.lists(DIMS, min_size=1, max_size=3)),
)


@FUZZ
@given(
    members=st.dictionaries(
        st.sampled_from(
            [
                "format",
                "positions",
                "fps",
                "joints",
                "mocap_framerate",
                "contacts",
                "name",
                "actor_positions",
                "reactor_positions",
                "meta",
            ]
        ),
        ARRAYS,
        max_size=6,
    ),
    fmt=st.sampled_from([None, "dualflow-motion-1", "dualflow-duet-1"]),
)
def test_npz_fields_of_any_shape_dtype_and_value_read_or_raise(tmp_path, members, fmt):
    path = tmp_path / "m.npz"
    with zipfile.ZipFile(path, "w") as z:
        for k, v in members.items():
            if isinstance(v, np.ndarray):
                buf = io.BytesIO()
                np.save(buf, v)
                v = buf.getvalue()
            z.writestr(k + ".npy", v)
        if fmt and "format" not in members:
            buf = io.BytesIO()
            np.save(buf, np.array(fmt))
            z.writestr("format.npy", buf.getvalue())
    try:
        _check_motion(load_any(path))
    except DualFlowError:
        pass


# -- robot trajectories --------------------------------------------------------------------------
@FUZZ
@given(
    n=st.integers(0, 6),
    joints=st.integers(0, 4),
    fps=st.floats(allow_nan=True, allow_infinity=True),
    value=st.floats(allow_nan=True, allow_infinity=True),
    dtype=st.sampled_from(["f8", "f4", "i4", "b1", "U3"]),
    header=st.one_of(
        st.just(None),
        st.recursive(
            st.none() | st.integers() | st.text(max_size=4),
            lambda c: (
                st.lists(c, max_size=3)
                | st.dictionaries(st.sampled_from(["joint_names", "robot", "meta"]), c, max_size=3)
            ),
            max_leaves=8,
        ),
    ),
)
def test_trajectory_files_load_or_raise_the_package_error(tmp_path, n, joints, fps, value, dtype, header):
    names = [f"j{k}" for k in range(joints)]
    with np.errstate(all="ignore"):
        q = np.full((n, joints), value).astype(dtype)
    arrays = {
        "joint_pos": q,
        "root_pos": np.zeros((n, 3)),
        "root_quat": np.tile([1.0, 0, 0, 0], (n, 1)),
        "fps": np.array(fps),
        "header": np.array(json.dumps({"joint_names": names} if header is None else header)),
    }
    path = tmp_path / "t.npz"
    np.savez(path, **arrays)
    try:
        traj = RobotTrajectory.load_npz(path)
    except RetargetError:
        return
    assert traj.n_frames >= 2 and np.isfinite(traj.joint_pos).all() and 1 <= traj.fps <= 1000


# -- telemetry and events ----------------------------------------------------------------------
JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=5), c, max_size=4),
    max_leaves=12,
)


@pytest.fixture(scope="module")
def good_telemetry(tmp_path_factory):
    path = tmp_path_factory.mktemp("tel") / "t.dftl"
    with TelemetryWriter(path, ["a", "b", "c"], 100.0) as w:
        for k in range(5):
            w.record(t=k / 100, tick=k, command=np.full(3, 0.1 * k))
    raw = path.read_bytes()
    line, body = raw.split(b"\n", 1)
    return json.loads(line[len(MAGIC) :]), body


@FUZZ
@given(
    changes=st.dictionaries(st.sampled_from(["joint_names", "rate_hz", "fields", "meta"]), JSON, max_size=3),
    body=st.one_of(st.none(), st.binary(max_size=600)),
)
def test_telemetry_headers_and_records_read_or_raise_the_package_error(tmp_path, good_telemetry, changes, body):
    header, good_body = good_telemetry
    path = tmp_path / "t.dftl"
    path.write_bytes(MAGIC + json.dumps({**header, **changes}).encode() + b"\n" + (good_body if body is None else body))
    try:
        tel = read_telemetry(path)
    except BridgeError:
        return
    assert len(tel.records) >= 1 and 1 <= tel.rate_hz <= 10000
    assert tel.records["command"].shape[1:] == (len(tel.joint_names),)
    assert np.isfinite(tel.records["command"]).all()


@FUZZ
@given(
    data=st.one_of(
        st.binary(max_size=400), st.lists(JSON.map(json.dumps), max_size=5).map(lambda lines: "\n".join(lines).encode())
    )
)
def test_events_files_read_or_raise_the_package_error(tmp_path, data):
    path = tmp_path / "t.dftl.events.jsonl"
    path.write_bytes(data)
    try:
        events = read_events(path)
    except BridgeError:
        return
    assert all(isinstance(e, dict) and isinstance(e.get("kind"), str) for e in events)


# -- checkpoints ---------------------------------------------------------------------------------
@FUZZ
@given(
    model=st.one_of(
        JSON,
        st.dictionaries(
            st.sampled_from(["width", "n_heads", "n_blocks", "dropout", "conv_kernels", "prediction", "look_ahead"]),
            JSON,
            max_size=3,
        ),
    ),
    version=JSON,
)
def test_checkpoint_configs_load_or_raise_the_package_error(tmp_path_factory, tiny_checkpoint, model, version):
    import shutil

    from dualflow.checkpoint import load_checkpoint

    d = tmp_path_factory.mktemp("ck") / "c"
    shutil.copytree(tiny_checkpoint, d)
    config = json.loads((d / "config.json").read_text())
    if isinstance(model, dict) and isinstance(config["model"], dict):
        model = {**config["model"], **model}
    config.update(model=model, version=version)
    (d / "config.json").write_text(json.dumps(config))
    try:
        load_checkpoint(d)
    except DualFlowError:
        pass


# -- YAML: hardware configs, profiles, joint maps ----------------------------------------------
YAMLISH = st.one_of(
    st.binary(max_size=300),
    st.text(alphabet="[]{}:-,&*!|>'\" \nabc01.#", max_size=300).map(str.encode),
    st.sampled_from([3, 60, 1500]).map(lambda n: ("a: " + "[" * n + "]" * n).encode()),
)


@FUZZ
@given(data=YAMLISH)
def test_hardware_configs_load_or_raise_the_package_error(tmp_path, data):
    path = tmp_path / "hardware.yaml"
    path.write_bytes(data)
    try:
        load_config(path, check_mjcf=False)
    except ConfigError:
        pass


@FUZZ
@given(data=YAMLISH)
def test_profiles_load_or_raise_the_package_error(tmp_path, data):
    path = tmp_path / "profile.yaml"
    path.write_bytes(data)
    try:
        RetargetProfile.load(path)
    except RetargetError:
        pass


@FUZZ
@given(data=YAMLISH)
def test_joint_maps_load_or_raise_the_package_error(tmp_path, data):
    from dualflow.motion.io import load_joint_map

    path = tmp_path / "map.yaml"
    path.write_bytes(data)
    try:
        load_joint_map(path)
    except DualFlowError:
        pass


# -- UDP packets -------------------------------------------------------------------------------
@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(
    data=st.one_of(
        st.binary(max_size=400),
        st.builds(
            lambda seq, v, stream: pk.encode_frame(seq, 0.0, np.full((22, 3), v, np.float32), stream),
            st.integers(0, 2**32 - 1),
            st.floats(width=32),
            st.integers(0, 2**32 - 1),
        ),
    )
)
def test_udp_packets_decode_to_a_bounded_frame_or_raise_packet_error(data):
    try:
        packet = pk.decode(data)
    except pk.PacketError as exc:
        assert exc.kind in ("garbage", "out_of_range")
        return
    if isinstance(packet, pk.ActorFramePacket):
        assert np.isfinite(packet.positions).all() and np.abs(packet.positions).max() <= pk.MAX_ABS_M
        assert np.isfinite(np.square(packet.positions.astype(np.float32))).all()  # float32 arithmetic too
