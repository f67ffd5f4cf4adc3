"""load_motion / load_pair / load_any / save_motion: every format, and bad input for each reader."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from dualflow import DualFlowError
from dualflow.motion import FOOT_JOINTS, REST_POSE, Motion, TwoPersonMotion
from dualflow.motion.io import load_any, load_motion, load_pair, put_on_ground, save_motion
from dualflow.motion.io.formats import DUET_FORMAT, MOTION_FORMAT


def walker(T=30, fps=30.0, start=(0.0, 0.0), heading=0.0, name="walker") -> Motion:
    """The rest pose turned to ``heading`` (rad about +Z) walking forward at 1 m/s, arms swinging."""
    t = np.arange(T) / fps
    c, s = np.cos(heading), np.sin(heading)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    pos = np.repeat((REST_POSE @ R.T)[None], T, axis=0)
    pos[:, :, :2] += np.asarray(start) + np.outer(t, [c, s])[:, None, :]
    pos[:, 20:22, 2] += 0.1 * np.sin(4 * t)[:, None]
    contacts = np.zeros((T, 4), bool)
    contacts[::2, 0] = True
    return Motion(pos, fps=fps, contacts=contacts, name=name)


def duet() -> TwoPersonMotion:
    return TwoPersonMotion(
        walker(start=(-1, 0)),
        walker(start=(1, 0.2), heading=np.pi, name="partner"),
        text="two people walk past",
        meta={"rule": "test", "beats": np.array([0, 15])},
    )


# -- our npz ------------------------------------------------------------------------
def test_npz_round_trip_one_person(tmp_path):
    m = walker()
    save_motion(m, tmp_path / "m.npz")
    back = load_motion(tmp_path / "m.npz")
    np.testing.assert_array_equal(back.positions, m.positions)
    np.testing.assert_array_equal(back.contacts, m.contacts)
    assert back.fps == 30.0 and back.name == "walker"
    with np.load(tmp_path / "m.npz", allow_pickle=False) as data:  # plain arrays only
        assert str(data["format"]) == MOTION_FORMAT and data["positions"].dtype == np.float64
        assert list(data["joint_names"][:2]) == ["pelvis", "left_hip"]


def test_npz_round_trip_duet_with_text_and_meta(tmp_path):
    d = duet()
    save_motion(d, tmp_path / "d.npz")
    back = load_any(tmp_path / "d.npz")
    assert isinstance(back, TwoPersonMotion)
    np.testing.assert_array_equal(back.reactor.positions, d.reactor.positions)
    assert back.text == d.text and back.meta == {"rule": "test", "beats": [0, 15]}
    assert back.reactor.name == "partner"
    with pytest.raises(DualFlowError, match="holds two people"):
        load_motion(tmp_path / "d.npz")
    with np.load(tmp_path / "d.npz", allow_pickle=False) as data:
        assert str(data["format"]) == DUET_FORMAT


def test_resampling_on_load(tmp_path):
    m = walker(T=61, fps=60.0)
    save_motion(m, tmp_path / "m.npz")
    back = load_motion(tmp_path / "m.npz", fps=30.0)
    assert back.fps == 30.0 and back.n_frames == 31
    np.testing.assert_allclose(back.positions[:, 0, 0], np.arange(31) / 30.0, atol=1e-12)


def test_save_to_bvh_and_back(tmp_path):
    m = walker()
    save_motion(m, tmp_path / "m.bvh", translations="all")  # the swinging wrists change bone lengths
    back = load_motion(tmp_path / "m.bvh", drop_first=False)
    np.testing.assert_allclose(back.positions, m.positions, atol=1e-5)
    with pytest.raises(DualFlowError, match="one person"):
        save_motion(duet(), tmp_path / "d.bvh")
    with pytest.raises(DualFlowError, match="use .npz or .bvh"):
        save_motion(m, tmp_path / "m.csv")
    with pytest.raises(DualFlowError, match="does not exist"):
        save_motion(m, tmp_path / "no" / "m.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.bvh"]  # nothing partial left behind


# -- other people's formats ---------------------------------------------------------
def test_amass_joint_npz_z_up_with_more_joints(tmp_path):
    m = walker()
    joints = np.concatenate([m.positions, np.zeros((m.n_frames, 30, 3))], axis=1)  # SMPL-H: 52 joints
    np.savez(tmp_path / "amass.npz", joints=joints.astype(np.float32), mocap_framerate=np.array(120.0))
    back = load_motion(tmp_path / "amass.npz")
    assert back.fps == 120.0
    np.testing.assert_allclose(back.positions, m.positions, atol=1e-6)
    # flat (T, 3J) arrays and a Y-up statement work too
    np.savez(tmp_path / "flat.npz", positions=m.positions[..., [1, 2, 0]].reshape(m.n_frames, -1), fps=30)
    np.testing.assert_allclose(load_motion(tmp_path / "flat.npz", up="y").positions, m.positions, atol=1e-12)


def test_humanml3d_new_joints_are_y_up_at_20_fps(tmp_path):
    m = walker()
    np.save(tmp_path / "000001.npy", m.positions[..., [1, 2, 0]].astype(np.float32))  # Y up, facing +Z
    back = load_motion(tmp_path / "000001.npy")
    assert back.fps == 20.0 and back.name == "000001"
    np.testing.assert_allclose(back.positions, m.positions, atol=1e-6)
    assert load_motion(tmp_path / "000001.npy", source_fps=30).fps == 30.0


def test_intergen_raw_492(tmp_path):
    m = walker()
    # InterGen raw is Z up with its own horizontal axes: its Y-up form is (x, z, -y) and ours (z, x, y)
    ours = m.positions
    yup = ours[..., [1, 2, 0]]
    raw = np.stack([yup[..., 0], -yup[..., 2], yup[..., 1]], axis=-1)
    rows = np.zeros((m.n_frames, 492), np.float32)
    rows[:, :66] = raw.reshape(m.n_frames, 66)
    rows[:, 66:186] = 7.0  # the hand joints, ignored
    np.save(tmp_path / "1234.npy", rows)
    back = load_motion(tmp_path / "1234.npy")
    assert back.fps == 30.0
    np.testing.assert_allclose(back.positions, ours, atol=1e-6)


def test_intergen_262_features_single_and_pair(tmp_path):
    features = pytest.importorskip("dualflow.motion.features")
    m = walker(T=20)
    f = features.encode_person(m)
    np.save(tmp_path / "p1.npy", f.astype(np.float32))
    back = load_motion(tmp_path / "p1.npy")
    assert back.n_frames == 19 and back.contacts is not None
    # canonical frame: first root above the origin, facing +X, same shape of motion
    np.testing.assert_allclose(back.positions[0, 0, :2], 0.0, atol=1e-5)
    np.testing.assert_allclose(np.diff(back.positions[:, 0, 0]), 1.0 / 30.0, atol=1e-5)
    d = duet()
    pair_f, _ = features.encode_pair(d)
    np.save(tmp_path / "pair.npy", pair_f.astype(np.float32))
    pair = load_any(tmp_path / "pair.npy")
    assert isinstance(pair, TwoPersonMotion)
    gap = np.linalg.norm(pair.actor.positions[:, 0] - pair.reactor.positions[:, 0], axis=-1)
    np.testing.assert_allclose(
        gap, np.linalg.norm(d.actor.positions[:-1, 0] - d.reactor.positions[:-1, 0], axis=-1), atol=1e-4
    )


def test_load_pair_pairs_files_in_one_frame(tmp_path):
    a, b = walker(T=40), walker(T=61, fps=60.0, start=(2, 0), heading=np.pi)
    save_motion(a, tmp_path / "a.npz")
    save_motion(b, tmp_path / "b.bvh")
    pair = load_pair(tmp_path / "a.npz", tmp_path / "b.bvh", text="pass by")
    assert pair.fps == 30.0 and pair.n_frames == 31 and pair.text == "pass by"
    np.testing.assert_allclose(pair.reactor.positions[0, 0, :2], [2, 0], atol=1e-5)  # not re-centred
    assert pair.meta["actor_file"].endswith("a.npz")


def test_put_on_ground():
    m = walker().translated([0, 0, 0.3])
    g = put_on_ground(m)
    assert g.positions[:, list(FOOT_JOINTS), 2].min() == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(g.positions[..., :2], m.positions[..., :2])
    d = duet()
    d2 = TwoPersonMotion(d.actor.translated([0, 0, 0.1]), d.reactor.translated([0, 0, 0.2]))
    g2 = put_on_ground(d2)
    assert g2.actor.positions[:, list(FOOT_JOINTS), 2].min() == pytest.approx(0.0, abs=1e-12)
    # one shared shift keeps the pair's relative placement
    np.testing.assert_allclose(g2.reactor.positions - g2.actor.positions, d2.reactor.positions - d2.actor.positions)


# -- bad input, every reader --------------------------------------------------------
def _npz(tmp_path, name="bad.npz", **arrays):
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


def _npy(tmp_path, arr, name="bad.npy"):
    path = tmp_path / name
    np.save(path, arr)
    return path


@pytest.mark.parametrize(
    "make, match",
    [
        # our npz
        (
            lambda d: _npz(
                d, format=np.array(MOTION_FORMAT), positions=np.zeros((4, 21, 3)), fps=30, joint_names=np.array(["x"])
            ),
            r"bad\.npz, field 'positions': expected joint positions \(T, J >= 22, 3\)",
        ),
        (
            lambda d: _npz(
                d, format=np.array(MOTION_FORMAT), positions=np.zeros((0, 22, 3)), fps=30, joint_names=np.array(["x"])
            ),
            r"bad\.npz: the file has zero frames",
        ),
        (
            lambda d: _npz(
                d,
                format=np.array(MOTION_FORMAT),
                positions=np.full((4, 22, 3), np.nan),
                fps=30,
                joint_names=np.array(["x"]),
            ),
            r"bad\.npz: positions contain NaN",
        ),
        (
            lambda d: _npz(
                d,
                format=np.array(MOTION_FORMAT),
                positions=np.repeat(REST_POSE[None], 4, 0),
                fps=-1,
                joint_names=np.array(["x"]),
            ),
            r"bad\.npz, field 'fps': fps must be > 0",
        ),
        (
            lambda d: _npz(
                d,
                format=np.array(MOTION_FORMAT),
                positions=np.repeat(REST_POSE[None], 4, 0),
                fps=30,
                contacts=np.zeros((3, 4)),
                joint_names=np.array(["x"]),
            ),
            r"bad\.npz, field 'contacts': expected shape \(4, 4\)",
        ),
        (
            lambda d: _npz(
                d,
                format=np.array(MOTION_FORMAT),
                positions=np.repeat(REST_POSE[None], 4, 0) * 100,
                fps=30,
                joint_names=np.array(["x"]),
            ),
            r"bad\.npz: with m the person is 172\.00 m tall.*--scale 0\.01 \(cm\)",
        ),
        (
            lambda d: _npz(d, format=np.array(DUET_FORMAT), actor_positions=np.repeat(REST_POSE[None], 4, 0), fps=30),
            r"bad\.npz: duet file has no field 'reactor_positions'",
        ),
        (lambda d: _npz(d, format=np.array("something-else")), r"field 'format': unknown format 'something-else'"),
        (lambda d: _npz(d, positions=np.array([{"a": 1}], dtype=object)), r"field 'positions': holds Python objects"),
        (
            lambda d: _npz(d, poses=np.zeros((4, 156)), trans=np.zeros((4, 3)), betas=np.zeros(16)),
            r"AMASS/SMPL parameter file.*SMPL body model",
        ),
        (lambda d: _npz(d, something=np.zeros(3)), r"no joint positions found; expected one of the fields joints"),
        (lambda d: _npz(d, joints=np.repeat(REST_POSE[None], 4, 0)), r"no frame rate field.*--source-fps"),
        (
            lambda d: _npz(d, joints=np.repeat(REST_POSE[None], 4, 0), mocap_framerate=np.array([30.0, 60.0])),
            r"field 'mocap_framerate': fps must be one number",
        ),
        # npy
        (lambda d: _npy(d, np.zeros((5, 17, 3))), r"bad\.npy: unrecognised array shape \(5, 17, 3\)"),
        (lambda d: _npy(d, np.zeros((0, 22, 3))), r"bad\.npy: the file has zero frames"),
        (lambda d: _npy(d, np.full((3, 492), np.inf)), r"bad\.npy: contains NaN or inf \(first at frame 0\)"),
        (lambda d: _npy(d, np.array(["a", "b"])), r"bad\.npy: expected a numeric array"),
        (lambda d: _npy(d, np.array([None, 1], dtype=object)), r"bad\.npy: holds Python objects"),
        (
            lambda d: _npy(d, np.repeat(REST_POSE[None], 4, 0)[..., [1, 2, 0]] * 1000),
            r"bad\.npy: with m the person is 1720\.00 m tall.*--scale 0\.001 \(mm\)",
        ),
    ],
)
def test_bad_array_files(tmp_path, make, match):
    path = make(tmp_path)
    with pytest.raises(DualFlowError, match=match):
        load_any(path)


def test_truncated_and_foreign_files(tmp_path):
    save_motion(walker(), tmp_path / "good.npz")
    raw = (tmp_path / "good.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DualFlowError, match=r"cut\.npz: .*(truncated|damaged)"):
        load_any(tmp_path / "cut.npz")
    np.save(tmp_path / "good.npy", np.zeros((4, 22, 3)))
    raw = (tmp_path / "good.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(raw[:200])
    with pytest.raises(DualFlowError, match=r"cut\.npy: .*(truncated|damaged|readable)"):
        load_any(tmp_path / "cut.npy")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(DualFlowError, match=r"text\.npz: not a readable \.npz"):
        load_any(tmp_path / "text.npz")
    with pytest.raises(DualFlowError, match=r"unknown motion file type '\.csv'"):
        (tmp_path / "m.csv").write_text("1,2")
        load_any(tmp_path / "m.csv")
    with pytest.raises(DualFlowError, match="no such file"):
        load_any(tmp_path / "missing.bvh")
    with pytest.raises(DualFlowError, match="is a folder"):
        load_any(tmp_path)
    with pytest.raises(DualFlowError, match="option 'fps' must be a positive number"):
        load_any(tmp_path / "good.npz", fps=0)
    assert zipfile.is_zipfile(tmp_path / "good.npz")  # the good file itself still loads
    assert load_motion(tmp_path / "good.npz").n_frames == 30
