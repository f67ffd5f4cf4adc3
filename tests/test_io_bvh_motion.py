"""BVH <-> SMPL-22 motion: joint maps, units, up axes, reference frames, the SMPL-22 writer."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dualflow import DualFlowError
from dualflow.motion import JOINT_NAMES, REST_POSE, Motion
from dualflow.motion.io import (
    BvhImportOptions,
    load_joint_map,
    motion_to_bvh,
    read_bvh,
    read_bvh_motion,
    write_bvh,
)
from dualflow.motion.io.bvh import BvhClip, BvhJoint
from dualflow.motion.io.bvh_motion import is_reference_frame
from dualflow.motion.io.units import Y_UP, estimate_height
from dualflow.motion.kinematics import forward_kinematics

NO_DROP = BvhImportOptions(drop_first=False)

#: SMPL-22 -> Mixamo names (what the mixamo map expects, one to one).
MIXAMO_NAMES = {
    "pelvis": "Hips",
    "spine1": "Spine",
    "spine2": "Spine1",
    "spine3": "Spine2",
    "neck": "Neck",
    "head": "Head",
    "left_hip": "LeftUpLeg",
    "left_knee": "LeftLeg",
    "left_ankle": "LeftFoot",
    "left_foot": "LeftToeBase",
    "left_collar": "LeftShoulder",
    "left_shoulder": "LeftArm",
    "left_elbow": "LeftForeArm",
    "left_wrist": "LeftHand",
}
MIXAMO_NAMES.update(
    {k.replace("left_", "right_"): v.replace("Left", "Right") for k, v in MIXAMO_NAMES.items() if k.startswith("left_")}
)


def dance(T=40, fps=30.0, seed=0, walk=0.8) -> Motion:
    """A smooth FK motion of the rest skeleton: arms lowered from the T-pose, swinging
    limbs, turning, walking along +X."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) / fps
    amp = rng.uniform(0.05, 0.3, (22, 3))
    phase = rng.uniform(0, 2 * np.pi, (22, 3))
    rv = amp * np.sin(2 * np.pi * 0.7 * t[:, None, None] + phase)
    rv[:, 16, 0] -= 1.2  # left arm down (about +X, +Y turns towards -Z)
    rv[:, 17, 0] += 1.2  # right arm down
    rv[:, 0] = [0.0, 0.0, 1.0] * (0.4 * t[:, None])  # root turns about +Z
    local = Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(T, 22, 3, 3)
    root = np.stack([walk * t, 0.1 * np.sin(t), 0.95 + 0.02 * np.sin(3 * t)], axis=1)
    return Motion(forward_kinematics(root, local), fps=fps, name="dance")


def renamed(clip: BvhClip, names: dict, prefix: str = "", unit: float = 1.0) -> BvhClip:
    """The same clip with other joint names and lengths in another unit (metres / unit)."""
    joints = []
    pos_cols = []
    for joint, start in zip(clip.joints, clip.channel_offsets()):
        base = joint.name[:-4] if joint.is_end_site else joint.name
        new = names.get(base, base) + ("_end" if joint.is_end_site else "")
        joints.append(
            BvhJoint(
                prefix + new, joint.parent, tuple(np.asarray(joint.offset) / unit), joint.channels, joint.is_end_site
            )
        )
        pos_cols += [start + k for k, c in enumerate(joint.channels) if c.endswith("position")]
    motion = clip.motion.copy()
    motion[:, pos_cols] /= unit
    return BvhClip(tuple(joints), clip.frame_time, motion, clip.source)


def reframed(clip: BvhClip, A: np.ndarray) -> BvhClip:
    """The same clip expressed in axes rotated by A (new = A @ old); rotation channels
    are re-decomposed in each joint's own channel order."""
    trans, rots = clip.local_transforms()
    joints, motion = [], np.empty_like(clip.motion)
    for j, (joint, start) in enumerate(zip(clip.joints, clip.channel_offsets())):
        joints.append(
            BvhJoint(joint.name, joint.parent, tuple(A @ np.asarray(joint.offset)), joint.channels, joint.is_end_site)
        )
        axes = joint.rotation_axes
        if axes:
            R = A @ rots[:, j] @ A.T
            angles = Rotation.from_matrix(R).as_euler(axes, degrees=True)
        k_rot = 0
        for k, ch in enumerate(joint.channels):
            if ch.endswith("position"):
                motion[:, start + k] = (trans[:, j] @ A.T)[:, "XYZ".index(ch[0])]
            else:
                motion[:, start + k] = angles[:, k_rot]
                k_rot += 1
    return BvhClip(tuple(joints), clip.frame_time, motion, clip.source)


@pytest.fixture
def mixamo_file(tmp_path):
    m = dance()
    clip = renamed(motion_to_bvh(m), MIXAMO_NAMES, prefix="mixamorig:", unit=0.01)  # centimetres
    path = tmp_path / "mixamo.bvh"
    write_bvh(clip, path, precision=8)
    return path, m


# -- joint maps ---------------------------------------------------------------------
def test_mixamo_skeleton_in_centimetres_with_namespace(mixamo_file):
    path, m = mixamo_file
    r = read_bvh_motion(path, NO_DROP)
    assert r.joint_map == "mixamo" and r.scale == pytest.approx(0.01)
    np.testing.assert_allclose(r.axes, Y_UP)
    np.testing.assert_allclose(r.motion.positions, m.positions, atol=1e-5)
    assert r.motion.fps == pytest.approx(30.0, rel=1e-6)


def test_four_joint_spine_selects_the_spine3_map(tmp_path):
    m = dance()
    names = dict(MIXAMO_NAMES, spine1="Spine1", spine2="Spine2", spine3="Spine3")
    clip = renamed(motion_to_bvh(m), names)
    # give it an extra 'Spine' joint between Hips and Spine1, like the 4-spine skeletons
    joints = list(clip.joints)
    hips = 0
    joints.append(BvhJoint("Spine", hips, (0.0, 0.0, 0.0), ()))
    clip = BvhClip(tuple(joints), clip.frame_time, clip.motion, "four.bvh")
    write_bvh(clip, tmp_path / "four.bvh")
    r = read_bvh_motion(tmp_path / "four.bvh", NO_DROP)
    assert r.joint_map == "mixamo_spine3"
    np.testing.assert_allclose(r.motion.positions, m.positions, atol=1e-5)  # spine1..3 from Spine1..3, not Spine


def test_user_map_overrides_a_builtin(mixamo_file, tmp_path):
    path, m = mixamo_file
    yaml_map = tmp_path / "map.yaml"
    yaml_map.write_text("base: mixamo\njoints:\n  head: Head_end\n  spine2: {between: [Spine, Spine2], t: 0.25}\n")
    r = read_bvh_motion(path, BvhImportOptions(joint_map=str(yaml_map), drop_first=False))
    clip = read_bvh(path)
    fk = clip.global_positions() * 0.01
    head_end = np.einsum("ab,tb->ta", Y_UP, fk[:, clip.names.index("mixamorig:Head_end")])
    np.testing.assert_allclose(r.motion.positions[:, JOINT_NAMES.index("head")], head_end, atol=1e-6)
    expected = 0.75 * m.positions[:, 3] + 0.25 * m.positions[:, 9]
    np.testing.assert_allclose(r.motion.positions[:, 6], expected, atol=1e-5)
    # a full JSON map (no base) works too
    full = {smpl: src for smpl, src in MIXAMO_NAMES.items()}
    (tmp_path / "map.json").write_text(json.dumps({"joints": full}))
    r2 = read_bvh_motion(path, BvhImportOptions(joint_map=str(tmp_path / "map.json"), drop_first=False))
    np.testing.assert_allclose(r2.motion.positions, m.positions, atol=1e-5)


@pytest.mark.parametrize(
    "content, match",
    [
        ("joints: {hed: Head}\nbase: mixamo\n", r"unknown SMPL joint name\(s\) 'hed'"),
        ("joints: {head: Head}\n", r"no source for SMPL joint\(s\) pelvis"),
        ("base: blender\njoints: {}\n", r"field 'base': unknown map 'blender'"),
        ("joints: {head: {between: [Neck], t: 0.5}}\nbase: mixamo\n", r"joint 'head': a source must be"),
        ("joints: {head: {between: [Neck, Head], t: 2}}\nbase: mixamo\n", r"joint 'head': a source must be"),
        ("joints: [1, 2]\n", r"needs a 'joints:' mapping"),
        ("joints: {}\nextra: 1\n", r"unknown key\(s\) extra"),
        ("joints: {head: [unclosed\n", r"not valid YAML"),
    ],
)
def test_bad_joint_map_files(tmp_path, content, match):
    path = tmp_path / "bad_map.yaml"
    path.write_text(content)
    with pytest.raises(DualFlowError, match=match) as exc:
        load_joint_map(path)
    assert "bad_map.yaml" in str(exc.value)


def test_map_naming_missing_joints_and_unknown_skeleton(mixamo_file, tmp_path):
    path, _ = mixamo_file
    with pytest.raises(DualFlowError, match=r"needs joints the file lacks: .*Neck1.*--joint-map"):
        read_bvh_motion(path, BvhImportOptions(joint_map="cmu"))
    clip = renamed(read_bvh(path), {}, prefix="")
    odd = BvhClip(
        tuple(BvhJoint(f"bone{i}", j.parent, j.offset, j.channels, j.is_end_site) for i, j in enumerate(clip.joints)),
        clip.frame_time,
        clip.motion,
        "odd.bvh",
    )
    write_bvh(odd, tmp_path / "odd.bvh")
    with pytest.raises(DualFlowError, match=r"odd\.bvh: unknown skeleton.*--joint-map"):
        read_bvh_motion(tmp_path / "odd.bvh")


# -- units and axes -----------------------------------------------------------------
@pytest.mark.parametrize("unit", [1.0, 0.01, 0.001, 0.0254, 0.0254 / 0.45])
def test_length_unit_is_detected_from_height(tmp_path, unit):
    m = dance(seed=3)
    write_bvh(renamed(motion_to_bvh(m), {}, unit=unit), tmp_path / "u.bvh", precision=9)
    r = read_bvh_motion(tmp_path / "u.bvh", NO_DROP)
    assert r.scale == pytest.approx(unit)
    assert r.height == pytest.approx(estimate_height(m.positions))
    np.testing.assert_allclose(r.motion.positions, m.positions, atol=1e-5)


def test_wrong_or_undetectable_scale_says_how_to_fix(tmp_path):
    m = dance()
    write_bvh(renamed(motion_to_bvh(m), {}, unit=0.01), tmp_path / "cm.bvh")
    with pytest.raises(
        DualFlowError, match=r"cm\.bvh: with m the person is 1\d\d\.\d\d m tall.*use --scale 0.01 \(cm\)"
    ):
        read_bvh_motion(tmp_path / "cm.bvh", BvhImportOptions(scale=1.0))
    # a 0.5 m figure fits no unit
    tiny = Motion(m.positions * 0.3, fps=m.fps)
    write_bvh(motion_to_bvh(tiny), tmp_path / "tiny.bvh")
    with pytest.raises(DualFlowError, match=r"tiny\.bvh: cannot tell the length unit.*--scale"):
        read_bvh_motion(tmp_path / "tiny.bvh")
    r = read_bvh_motion(tmp_path / "tiny.bvh", BvhImportOptions(scale=1.0, height_range=None, drop_first=False))
    np.testing.assert_allclose(r.motion.positions, tiny.positions, atol=1e-5)


def test_z_up_file_is_detected_from_the_rest_pose(tmp_path):
    m = dance(seed=5)
    clip = motion_to_bvh(m)  # Y up
    zclip = reframed(clip, Y_UP)  # the same motion written Z up, facing +X
    write_bvh(zclip, tmp_path / "z.bvh", precision=9)
    r = read_bvh_motion(tmp_path / "z.bvh", NO_DROP)
    np.testing.assert_allclose(r.axes, np.eye(3))
    np.testing.assert_allclose(r.motion.positions, m.positions, atol=1e-5)
    # stating the wrong axis is caught
    with pytest.raises(DualFlowError, match=r"head is below the pelvis.*--up"):
        read_bvh_motion(tmp_path / "z.bvh", BvhImportOptions(up="y", drop_first=False, height_range=None))


def test_reference_first_frame_is_dropped_when_it_jumps(tmp_path):
    m = dance(T=60)
    clip = motion_to_bvh(m)
    tpose = clip.motion[:1].copy()
    tpose[:, 3:] = 0.0  # all rotations zero, root kept: a CMU-style reference pose
    with_ref = BvhClip(clip.joints, clip.frame_time, np.concatenate([tpose, clip.motion]), "ref.bvh")
    write_bvh(with_ref, tmp_path / "ref.bvh", precision=8)
    r = read_bvh_motion(tmp_path / "ref.bvh")
    assert r.dropped_first_frame and r.motion.n_frames == 60
    np.testing.assert_allclose(r.motion.positions, m.positions, atol=1e-5)
    kept = read_bvh_motion(tmp_path / "ref.bvh", BvhImportOptions(drop_first=False))
    assert kept.motion.n_frames == 61
    # smooth capture keeps its first frame
    write_bvh(clip, tmp_path / "plain.bvh")
    assert not read_bvh_motion(tmp_path / "plain.bvh").dropped_first_frame
    assert not is_reference_frame(m.positions[:2])


# -- the SMPL-22 writer -------------------------------------------------------------
def test_written_skeleton_is_smpl22_y_up_in_metres():
    clip = motion_to_bvh(dance())
    joints = [j for j in clip.joints if not j.is_end_site]
    assert tuple(j.name for j in joints) == tuple(JOINT_NAMES[i] for i in _dfs_order())
    assert joints[0].channels == ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
    assert all(j.channels == ("Zrotation", "Yrotation", "Xrotation") for j in joints[1:])
    rest = clip.rest_positions()
    head, pelvis = clip.names.index("head"), clip.names.index("pelvis")
    assert rest[head, 1] - rest[pelvis, 1] > 0.5  # Y is up
    lhip, rhip = clip.names.index("left_hip"), clip.names.index("right_hip")
    assert rest[lhip, 0] > rest[rhip, 0]  # left towards +X, so it faces +Z
    assert {j.name for j in clip.joints if j.is_end_site} == {
        "head_end",
        "left_wrist_end",
        "right_wrist_end",
        "left_foot_end",
        "right_foot_end",
    }


def _dfs_order():
    from dualflow.motion import PARENTS

    order = []

    def visit(j):
        order.append(j)
        for c in range(22):
            if PARENTS[c] == j:
                visit(c)

    visit(0)
    return order


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), lengths=st.floats(0.8, 1.2))
def test_write_read_reproduces_rigid_skeleton_motion(seed, lengths, tmp_path_factory):
    rng = np.random.default_rng(seed)
    T = 12
    # joints: random axes, up to 1 rad (an upside-down person is rejected on reading)
    rv = rng.normal(size=(T, 22, 3))
    rv *= rng.uniform(0, 1.0, (T, 22, 1)) / np.linalg.norm(rv, axis=-1, keepdims=True)
    local = Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(T, 22, 3, 3)
    # root: any heading, tilted by less than 0.6 rad
    tilt = rv[:, 0] * [0.6, 0.6, 0.0]
    local[:, 0] = (
        Rotation.from_rotvec(tilt) * Rotation.from_euler("z", rng.uniform(-np.pi, np.pi, (T, 1)))
    ).as_matrix()
    root = rng.normal(0, 2, (T, 3))
    offsets = (
        REST_POSE - REST_POSE[[0, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19]]
    ) * lengths
    m = Motion(forward_kinematics(root, local, offsets), fps=float(rng.choice([20, 30, 60])))
    path = tmp_path_factory.mktemp("rt") / "m.bvh"
    write_bvh(motion_to_bvh(m), path, precision=8)
    back = read_bvh_motion(path, BvhImportOptions(drop_first=False, height_range=None, scale=1.0)).motion
    np.testing.assert_allclose(back.positions, m.positions, atol=2e-5)
    assert back.fps == pytest.approx(m.fps, rel=1e-6)


def test_all_translations_mode_is_exact_for_any_positions(tmp_path):
    m = dance(seed=7)
    noisy = Motion(m.positions + np.random.default_rng(0).normal(0, 0.01, m.positions.shape), fps=m.fps)
    write_bvh(motion_to_bvh(noisy, translations="all"), tmp_path / "all.bvh", precision=8)
    back = read_bvh_motion(tmp_path / "all.bvh", NO_DROP).motion
    np.testing.assert_allclose(back.positions, noisy.positions, atol=1e-5)
    # the usual root-only layout keeps bone lengths fixed: the error is bounded by the jitter
    write_bvh(motion_to_bvh(noisy), tmp_path / "root.bvh", precision=8)
    err = np.linalg.norm(read_bvh_motion(tmp_path / "root.bvh", NO_DROP).motion.positions - noisy.positions, axis=-1)
    assert 0.001 < err.mean() < 0.05
    with pytest.raises(DualFlowError, match="translations"):
        motion_to_bvh(m, translations="some")
