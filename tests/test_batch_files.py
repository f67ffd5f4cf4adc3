"""Which files retarget-check takes from a folder: plain files, subfolders, InterGen's
person1/person2 layout (the reactor of each pair, InterHuman-AS labels), its own output, and
the two files of one capture joined by a --pairs pattern."""

import json
import re

import numpy as np
import pytest

from dualflow.errors import DualFlowError
from ros_free_bridge.batch.clips import PairPattern, clip_name, find_clips, find_motion_files
from ros_free_bridge.errors import BridgeError


def touch(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    return path


def names(files, folder):
    return [clip_name(f, folder) for f in files]


def test_plain_folder_takes_motion_files_only_and_subfolders_only_when_asked(tmp_path):
    for n in ("b.bvh", "a.npz", "c.NPY", "notes.txt", "sub/d.bvh"):
        touch(tmp_path / n)
    assert names(find_motion_files(tmp_path), tmp_path) == ["a.npz", "b.bvh", "c.NPY"]
    assert names(find_motion_files(tmp_path, recursive=True), tmp_path) == ["a.npz", "b.bvh", "c.NPY", "sub/d.bvh"]


def test_the_output_folder_inside_the_input_is_left_out(tmp_path):
    touch(tmp_path / "a.npz")
    touch(tmp_path / "out" / "clips" / "a.npz" / "trajectory.npz")  # a previous run's outputs
    assert names(find_motion_files(tmp_path, recursive=True, exclude=tmp_path / "out"), tmp_path) == ["a.npz"]
    assert len(find_motion_files(tmp_path, recursive=True)) == 2


@pytest.mark.parametrize("base", ["", "motions_processed"])
def test_intergen_layout_gives_one_clip_per_pair_its_reactor(tmp_path, base):
    people = tmp_path / base if base else tmp_path
    for person in ("person1", "person2"):
        for clip in ("10", "11"):
            touch(people / person / f"{clip}.npy")
    touch(people / "person1" / "12.npy")  # only one person of this clip
    files = find_motion_files(tmp_path, recursive=True)
    prefix = f"{base}/" if base else ""
    assert names(files, tmp_path) == [f"{prefix}person1/12.npy", f"{prefix}person2/10.npy", f"{prefix}person2/11.npy"]


def test_interhuman_as_labels_choose_the_reactor(tmp_path):
    for person in ("person1", "person2"):
        for clip in ("10", "11"):
            touch(tmp_path / "motions_processed" / person / f"{clip}.npy")
    (tmp_path / "actor_reactor.json").write_text(json.dumps({"10": "person2", "11": 1}))
    files = find_motion_files(tmp_path / "motions_processed")
    assert names(files, tmp_path) == ["motions_processed/person1/10.npy", "motions_processed/person2/11.npy"]
    (tmp_path / "actor_reactor.json").write_text(json.dumps({"10": "nobody"}))
    with pytest.raises(DualFlowError, match="actor must be 'person1' or 'person2'"):
        find_motion_files(tmp_path / "motions_processed")


def test_not_a_folder_is_one_clear_error(tmp_path):
    f = touch(tmp_path / "a.npz")
    with pytest.raises(BridgeError, match="not a folder"):
        find_motion_files(f)


def test_relative_names_are_posix_and_unique(tmp_path):
    a, b = touch(tmp_path / "x" / "walk.npz"), touch(tmp_path / "y" / "walk.npz")
    assert np.unique(names([a, b], tmp_path)).size == 2 and names([a], tmp_path) == ["x/walk.npz"]


def test_a_relative_folder_works_for_pairs_too(tmp_path, monkeypatch):
    for person in ("person1", "person2"):
        touch(tmp_path / "ig" / person / "7.npy")
    monkeypatch.chdir(tmp_path)
    files = find_motion_files("ig", recursive=True)
    assert names(files, "ig") == ["person2/7.npy"] and not files[0].is_absolute()


def test_with_recursive_a_pair_layout_is_found_in_any_subfolder(tmp_path):
    for person in ("person1", "person2"):
        touch(tmp_path / "sessions" / "day1" / person / "5.npy")
        touch(tmp_path / "sessions" / "day1" / person / "5.bvh")  # same stem, another file: its own clip
    touch(tmp_path / "sessions" / "solo.bvh")
    files = find_motion_files(tmp_path, recursive=True)
    assert names(files, tmp_path) == ["sessions/day1/person2/5.bvh", "sessions/day1/person2/5.npy", "sessions/solo.bvh"]


def test_labels_are_found_from_a_relative_motions_processed_folder(tmp_path, monkeypatch):
    for person in ("person1", "person2"):
        touch(tmp_path / "motions_processed" / person / "10.npy")
    (tmp_path / "actor_reactor.json").write_text(json.dumps({"10": "person2"}))
    monkeypatch.chdir(tmp_path / "motions_processed")
    assert names(find_motion_files("."), ".") == ["person1/10.npy"]


def test_a_pair_pattern_joins_the_two_files_of_each_capture(tmp_path):
    for n in (
        "take1_S1.bvh",
        "take1_S2.bvh",
        "take2_S1.bvh",
        "take2_S2.bvh",
        "solo.bvh",
        "take3_S2.bvh",  # its actor is missing
        "take4_S1.bvh",  # its reactor is missing
        "take5_S1.npz",
    ):  # another file type: not the pattern's, a clip of its own
        touch(tmp_path / n)
    clips = {c.name: c for c in find_clips(tmp_path, pairs="{name}_S1.bvh,{name}_S2.bvh")}
    assert list(clips) == ["solo.bvh", "take1_S2.bvh", "take2_S2.bvh", "take3_S2.bvh", "take4_S1.bvh", "take5_S1.npz"]
    pair = clips["take1_S2.bvh"]  # named by the reactor's file: the part the robot plays
    assert pair.path == tmp_path / "take1_S2.bvh" and pair.actor == tmp_path / "take1_S1.bvh"
    assert pair.actor_name == "take1_S1.bvh" and not pair.problem
    assert clips["solo.bvh"].actor is None and not clips["solo.bvh"].problem
    assert "no actor file take3_S1.bvh" in clips["take3_S2.bvh"].problem
    assert "without its reactor take4_S2.bvh" in clips["take4_S1.bvh"].problem
    assert not clips["take5_S1.npz"].problem and clips["take5_S1.npz"].actor is None


def test_pairs_are_found_in_subfolders_and_only_within_one_folder(tmp_path):
    touch(tmp_path / "day1" / "a_S1.bvh")
    touch(tmp_path / "day1" / "a_S2.bvh")
    touch(tmp_path / "day2" / "a_S2.bvh")  # day1's actor does not pair with it
    clips = {c.name: c for c in find_clips(tmp_path, recursive=True, pairs="{name}_S1.bvh,{name}_S2.bvh")}
    assert clips["day1/a_S2.bvh"].actor_name == "day1/a_S1.bvh"
    assert clips["day2/a_S2.bvh"].problem and clips["day2/a_S2.bvh"].actor is None


def test_a_prefix_pattern_pairs_the_cmu_trial_numbers(tmp_path):
    """CMU's two-person trials are numbered per subject (18_01 with 19_01)."""
    touch(tmp_path / "18_01.bvh")
    touch(tmp_path / "19_01.bvh")
    [clip] = find_clips(tmp_path, pairs="18_{name}.bvh,19_{name}.bvh")
    assert (clip.name, clip.actor_name) == ("19_01.bvh", "18_01.bvh")


@pytest.mark.parametrize(
    "bad, message",
    [
        ("{name}_S1.bvh", "two file-name patterns"),
        ("{name}_S1.bvh,{name}_S2.bvh,{name}_S3.bvh", "two file-name patterns"),
        ("S1.bvh,{name}_S2.bvh", "exactly one {name}"),
        ("{name}_{name}.bvh,{name}_S2.bvh", "exactly one {name}"),
        ("{take}_S1.bvh,{take}_S2.bvh", "exactly one {name}"),
        ("a/{name}.bvh,b/{name}.bvh", "not paths"),
        ("{name}_S1.txt,{name}_S2.txt", "motion file type"),
        ("{name}.bvh,{name}.bvh", "the same"),
    ],
)
def test_a_bad_pair_pattern_says_what_to_write(bad, message):
    with pytest.raises(BridgeError, match=re.escape(message)):
        PairPattern.parse(bad)
