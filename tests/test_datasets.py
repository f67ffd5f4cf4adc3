"""Dataset loaders: small fake trees in each real layout (InterGen's InterHuman, Duolando's
DD100, the MDD authors' folders, BVH pairs), built from synthetic duets whose positions are
known, so every loader is checked for frame, axes, roles, fps, texts and music, and for a
clear error naming the missing or malformed file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dualflow.datasets import LOADERS, DuetSample, load_dataset
from dualflow.datasets.windows import beat_track, window_split
from dualflow.errors import DualFlowError
from dualflow.motion.io import write_bvh_motion
from dualflow.motion.io.formats import _INTERGEN_RAW_TO_YUP
from dualflow.motion.io.units import Y_UP
from dualflow.synthetic import make_duet

RNG = np.random.default_rng(0)


def _duet(seed: int, seconds: float = 1.0, fps: float = 30.0, rule: str = "mirror"):
    return make_duet(rule, seconds=seconds, fps=fps, seed=seed)


def _yup_flat(positions_zup: np.ndarray, n_joints: int = 55) -> np.ndarray:
    """(T, 22, 3) Z-up -> (T, 3·n_joints) Y-up, extra joints filled with noise (SMPL-X style)."""
    yup = positions_zup[..., [1, 2, 0]]
    extra = RNG.normal(size=(len(yup), n_joints - 22, 3))
    return np.concatenate([yup, extra], axis=1).reshape(len(yup), -1).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# InterHuman / InterHuman-AS
# ---------------------------------------------------------------------------------------------


def _intergen_raw(positions_zup: np.ndarray) -> np.ndarray:
    """World Z-up (T, 22, 3) -> InterGen processed (T, 492) (the inverse of the reader's map)."""
    to_world = Y_UP @ _INTERGEN_RAW_TO_YUP
    raw = np.einsum("ba,tjb->tja", to_world, positions_zup)  # inverse of an orthonormal map
    out = RNG.normal(size=(len(raw), 492)).astype(np.float32)
    out[:, :66] = raw.reshape(len(raw), -1)
    return out


def make_interhuman(root: Path, n: int = 4) -> dict[str, object]:
    duets = {}
    for p in ("person1", "person2"):
        (root / "motions_processed" / p).mkdir(parents=True)
    (root / "annots").mkdir()
    for i in range(n):
        name = str(1000 + i)
        d = _duet(i)
        duets[name] = d
        np.save(root / "motions_processed" / "person1" / f"{name}.npy", _intergen_raw(d.actor.positions))
        np.save(root / "motions_processed" / "person2" / f"{name}.npy", _intergen_raw(d.reactor.positions))
        (root / "annots" / f"{name}.txt").write_text(f"text a {i}\ntext b {i}\ntext c {i}\n")
    (root / "train.txt").write_text("1000\n1001\n1002\n")
    (root / "test.txt").write_text("1003\n")
    (root / "ignore_list.txt").write_text("1002\n")
    (root / "actor_reactor.json").write_text(json.dumps({"1000": "person2", "1001": 1}))
    return duets


def test_interhuman_reads_intergen_layout(tmp_path):
    duets = make_interhuman(tmp_path)
    ds = load_dataset("interhuman", tmp_path, "train")
    assert [s.name for s in ds] == ["1000", "1001"]
    assert ds.skipped == {"1002": "in ignore_list.txt"}
    s = ds[0]
    assert s.texts == ("text a 0", "text b 0", "text c 0") and s.text == "text a 0"
    assert s.fps == 30.0 and s.roles == ("person1", "person2")
    # InterGen's axis change + ours give back the world positions exactly (float32 files)
    np.testing.assert_allclose(s.motion.actor.positions, duets["1000"].actor.positions, atol=1e-5)
    np.testing.assert_allclose(s.motion.reactor.positions, duets["1000"].reactor.positions, atol=1e-5)
    feats = s.features()
    assert feats.shape == (s.n_frames - 1, 2, 262) and feats.dtype == np.float32
    assert load_dataset("interhuman", tmp_path, "test")[0].name == "1003"


def test_interhuman_as_swaps_roles_from_labels(tmp_path):
    duets = make_interhuman(tmp_path)
    ds = load_dataset("interhuman_as", tmp_path, "train")
    assert [s.name for s in ds] == ["1000", "1001"] and ds.name == "interhuman_as"
    first = ds[0]
    assert first.roles == ("person2", "person1")
    np.testing.assert_allclose(first.motion.actor.positions, duets["1000"].reactor.positions, atol=1e-5)
    assert ds[1].roles == ("person1", "person2")
    test = load_dataset("interhuman_as", tmp_path, "test")
    assert len(test) == 0 and test.skipped == {"1003": "no actor-reactor label"}


@pytest.mark.parametrize(
    "breakage, needle",
    [
        (lambda r: (r / "motions_processed" / "person2" / "1001.npy").unlink(), "person2/1001.npy"),
        (lambda r: (r / "annots" / "1000.txt").unlink(), "annots/1000.txt"),
        (lambda r: (r / "train.txt").unlink(), "train.txt"),
        (lambda r: (r / "motions_processed" / "person1" / "1000.npy").write_bytes(b"junk"), "person1/1000.npy"),
        (lambda r: (r / "annots" / "1001.txt").write_text("\n\n"), "annots/1001.txt"),
    ],
)
def test_interhuman_errors_name_the_file(tmp_path, breakage, needle):
    make_interhuman(tmp_path)
    breakage(tmp_path)
    with pytest.raises(DualFlowError, match=needle):
        load_dataset("interhuman", tmp_path, "train")


def test_interhuman_as_bad_label(tmp_path):
    make_interhuman(tmp_path)
    (tmp_path / "actor_reactor.json").write_text(json.dumps({"1000": "left"}))
    with pytest.raises(DualFlowError, match="actor_reactor.json.*1000"):
        load_dataset("interhuman_as", tmp_path, "train")


# ---------------------------------------------------------------------------------------------
# DD100
# ---------------------------------------------------------------------------------------------


def make_dd100(root: Path) -> dict[str, object]:
    duets = {}
    for split, takes in (("train", ["Waltz_1_1", "Tango_2_1"]), ("test", ["Jive_3_1"])):
        pos = root / "motion" / "pos3d" / split
        mus = root / "music" / "feature" / split
        pos.mkdir(parents=True)
        mus.mkdir(parents=True)
        for i, take in enumerate(takes):
            d = _duet(10 + i + len(duets))
            duets[take] = d
            np.save(pos / f"{take}_01.npy", _yup_flat(d.actor.positions))  # leader
            np.save(pos / f"{take}_00.npy", _yup_flat(d.reactor.positions))  # follower
            music = RNG.normal(size=(d.n_frames + 5, 54)).astype(np.float32)
            music[:, 53] = 0.0
            music[::8, 53] = 1.0
            np.save(mus / f"{take}.npy", music)
    return duets


def test_dd100_reads_duolando_layout(tmp_path):
    duets = make_dd100(tmp_path)
    ds = load_dataset("dd100", tmp_path, "train")
    assert sorted(s.name for s in ds) == ["Tango_2_1", "Waltz_1_1"]
    s = next(x for x in ds if x.name == "Waltz_1_1")
    assert s.genre == "Waltz" and s.roles == ("leader", "follower") and s.music_kind == "duolando54"
    np.testing.assert_allclose(s.motion.actor.positions, duets["Waltz_1_1"].actor.positions, atol=1e-5)
    np.testing.assert_allclose(s.motion.reactor.positions, duets["Waltz_1_1"].reactor.positions, atol=1e-5)
    assert s.music.shape == (s.n_frames, 54)  # trimmed to the motion
    assert len(load_dataset("dd100", tmp_path, "test")) == 1
    no_music = load_dataset("dd100", tmp_path, "train", music=False)
    assert all(x.music is None for x in no_music)


def test_dd100_skips_takes_without_music_and_rejects_bad_files(tmp_path):
    make_dd100(tmp_path)
    (tmp_path / "music" / "feature" / "train" / "Tango_2_1.npy").unlink()
    ds = load_dataset("dd100", tmp_path, "train")
    assert [s.name for s in ds] == ["Waltz_1_1"] and "Tango_2_1" in ds.skipped
    np.save(tmp_path / "music" / "feature" / "train" / "Waltz_1_1.npy", np.zeros((30, 35), np.float32))
    with pytest.raises(DualFlowError, match="Waltz_1_1.npy.*54"):
        load_dataset("dd100", tmp_path, "train")
    np.save(tmp_path / "motion" / "pos3d" / "train" / "Waltz_1_1_01.npy", np.zeros((30, 10), np.float32))
    with pytest.raises(DualFlowError, match="Waltz_1_1_01.npy"):
        load_dataset("dd100", tmp_path, "train", music=False)
    with pytest.raises(DualFlowError, match="pos3d/val"):
        load_dataset("dd100", tmp_path, "val")


def test_dd100_rejects_a_z_up_file_read_as_y_up(tmp_path):
    d = _duet(3)
    pos = tmp_path / "motion" / "pos3d" / "train"
    pos.mkdir(parents=True)
    for suffix, m in (("_01", d.actor), ("_00", d.reactor)):
        flat = m.positions.reshape(len(m.positions), -1).astype(np.float32)  # Z up, not Y up
        np.save(pos / f"Salsa_1_1{suffix}.npy", flat)
    with pytest.raises(DualFlowError, match="Y-up"):
        load_dataset("dd100", tmp_path, "train", music=False)
    ds = load_dataset("dd100", tmp_path, "train", music=False, up="z")
    np.testing.assert_allclose(ds[0].motion.actor.positions, d.actor.positions, atol=1e-5)


# ---------------------------------------------------------------------------------------------
# MDD
# ---------------------------------------------------------------------------------------------


def make_mdd(root: Path, focused: bool = True) -> dict[str, object]:
    duets = {}
    for genre, take, seed in (("Salsa", "s01_t1", 20), ("Swing", "w02_t3", 21)):
        d = _duet(seed, seconds=1.0, fps=120.0)  # captured at 120 fps
        duets[f"{genre}/{take}"] = d
        pos = root / "motion" / "pos3d" / "train" / genre
        pos.mkdir(parents=True, exist_ok=True)
        np.save(pos / f"{take}_Lead.npy", _yup_flat(d.actor.positions))
        np.save(pos / f"{take}_Follow.npy", _yup_flat(d.reactor.positions))
        for folder, width in (("feature", 54), ("Juke_features", 4800)):
            mus = root / "music" / folder / "train" / genre
            mus.mkdir(parents=True, exist_ok=True)
            np.save(mus / f"{take}.npy", RNG.normal(size=(40, width)).astype(np.float32))
        for folder in ("processed",) + (("spatial", "body_move", "rhythm") if focused else ()):
            txt = root / "text" / folder / "train" / genre
            txt.mkdir(parents=True, exist_ok=True)
            (txt / f"{take}.txt").write_text(f"{folder} of {take}\nsecond line\n")
    return duets


def test_mdd_reads_authors_layout_at_30_fps(tmp_path):
    duets = make_mdd(tmp_path)
    ds = load_dataset("mdd", tmp_path, "train")
    assert [s.name for s in ds] == ["Salsa/s01_t1", "Swing/w02_t3"]
    s = ds[0]
    d = duets["Salsa/s01_t1"]
    assert s.fps == 30.0 and s.n_frames == len(d.actor.positions[::4])
    np.testing.assert_allclose(s.motion.actor.positions, d.actor.positions[::4], atol=1e-5)
    np.testing.assert_allclose(s.motion.reactor.positions, d.reactor.positions[::4], atol=1e-5)
    assert s.genre == "Salsa" and s.roles == ("leader", "follower")
    assert s.text == "processed of s01_t1" and len(s.texts) == 2
    assert s.focused.spatial == "spatial of s01_t1" and s.focused.body == "body_move of s01_t1"
    assert s.focused.rhythm == "rhythm of s01_t1"
    assert s.music_kind == "duolando54" and s.music.shape == (s.n_frames, 54)
    juke = load_dataset("mdd", tmp_path, "train", music="jukebox")
    assert juke[0].music_kind == "jukebox" and juke[0].music.shape[1] == 4800


def test_mdd_errors_and_skips(tmp_path):
    make_mdd(tmp_path)
    (tmp_path / "text" / "rhythm" / "train" / "Swing" / "w02_t3.txt").unlink()
    with pytest.raises(DualFlowError, match="rhythm/train/Swing/w02_t3.txt"):
        load_dataset("mdd", tmp_path, "train")
    (tmp_path / "text" / "processed" / "train" / "Swing" / "w02_t3.txt").unlink()
    ds = load_dataset("mdd", tmp_path, "train")
    assert [s.name for s in ds] == ["Salsa/s01_t1"] and "Swing/w02_t3" in ds.skipped
    with pytest.raises(DualFlowError, match="fps 25 must divide"):
        load_dataset("mdd", tmp_path, "train", fps=25)
    with pytest.raises(DualFlowError, match="motion/pos3d/test"):
        load_dataset("mdd", tmp_path, "test")


def test_mdd_without_focused_texts(tmp_path):
    make_mdd(tmp_path, focused=False)
    assert all(s.focused is None for s in load_dataset("mdd", tmp_path, "train", music=None))


# ---------------------------------------------------------------------------------------------
# BVH pairs, synthetic, registry, windows
# ---------------------------------------------------------------------------------------------


def test_bvh_pairs_folder_with_manifest_and_texts(tmp_path):
    d = _duet(5, seconds=1.0, fps=60.0)
    write_bvh_motion(d.actor, tmp_path / "a_01.bvh")
    write_bvh_motion(d.reactor, tmp_path / "b_01.bvh")
    (tmp_path / "pairs.txt").write_text("# actor reactor\na_01.bvh b_01.bvh\n")
    (tmp_path / "a_01.txt").write_text("two people mirror each other\n")
    ds = load_dataset("bvh_pairs", tmp_path, "all")
    s = ds[0]
    assert s.name == "a_01" and s.fps == 30.0 and s.text == "two people mirror each other"
    np.testing.assert_allclose(s.motion.actor.positions, d.actor.resample(30.0).positions, atol=1e-3)
    np.testing.assert_allclose(s.motion.reactor.positions, d.reactor.resample(30.0).positions, atol=1e-3)
    (tmp_path / "pairs.txt").write_text("a_01.bvh missing.bvh\n")
    with pytest.raises(DualFlowError, match="missing.bvh"):
        load_dataset("bvh_pairs", tmp_path)
    with pytest.raises(DualFlowError, match="train.txt"):
        (tmp_path / "pairs.txt").write_text("a_01.bvh b_01.bvh\n")
        load_dataset("bvh_pairs", tmp_path, "train")


def test_bvh_pairs_on_the_cmu_trial(tmp_path, cmu_pair_paths):
    a, b = cmu_pair_paths
    (tmp_path / "pairs.txt").write_text(f"{a} {b}\n")  # absolute paths work too
    ds = load_dataset("bvh_pairs", tmp_path, limit=1)
    s = ds[0]
    assert s.fps == 30.0 and s.n_frames > 50 and s.roles == ("18_01", "19_01")
    gap = np.linalg.norm(s.motion.actor.positions[:, 0, :2] - s.motion.reactor.positions[:, 0, :2], axis=-1)
    assert 0.3 < np.median(gap) < 3.0  # two people near each other in one world frame


def test_synthetic_matches_trainer_clips():
    from dualflow.datasets.config import TrainingDataConfig
    from dualflow.datasets.synthetic import build_split

    ds = load_dataset("synthetic", split="val", n_clips=3, frames=20)
    ref = build_split(TrainingDataConfig(n_clips=1, val_clips=3, frames=20), "val")
    np.testing.assert_allclose(np.stack([s.features() for s in ds]), ref.features, atol=1e-6)
    assert [s.text for s in ds] == ref.texts
    assert ds[1].style == "follow" and ds[0].music_kind == "beats4"


def test_registry_errors():
    with pytest.raises(DualFlowError, match="unknown dataset 'nope'"):
        load_dataset("nope", "x")
    with pytest.raises(DualFlowError, match="needs a root"):
        load_dataset("dd100")
    with pytest.raises(DualFlowError, match="valid options"):
        load_dataset("synthetic", split="train", colour="red")
    assert set(LOADERS) == {"interhuman", "interhuman_as", "dd100", "mdd", "bvh_pairs", "synthetic"}


def test_beat_track_phase_and_windows(tmp_path):
    imp = np.zeros(40)
    imp[[4, 14, 24, 34]] = 1
    tr = beat_track(imp)
    assert tr[4, 0] == 1 and tr[4, 3] == 1 and tr[14, 3] == 0
    np.testing.assert_allclose(tr[9, 1:3], [0.0, -1.0], atol=1e-6)  # half-way between beats: phase 0.5
    np.testing.assert_allclose(tr[[4, 14, 24], 2], 1.0)  # phase 0 on the beats
    make_dd100(tmp_path)
    ws = window_split(load_dataset("dd100", tmp_path, "train"), frames=10, stride=10)
    assert ws.features.shape[1:] == (10, 2, 262) and ws.beats.shape == (len(ws.features), 10, 4)
    assert ws.labels == ("Tango", "Waltz") and set(ws.rules.tolist()) == {0, 1}
    assert ws.beats[..., 0].sum() > 0  # the Duolando beat column made it into the track


def test_sample_validates_music_width():
    d = _duet(0)
    with pytest.raises(DualFlowError, match="54 columns"):
        DuetSample("x", "y", d, music=np.zeros((10, 3)), music_kind="duolando54")
