"""MDD (Gupta et al., ICCV 2025) in the layout its authors' loader reads.

Layout (the authors' ``Text2Duet`` motion / music / text roots under one ROOT)::

    ROOT/
      motion/pos3d/{split}/{genre}/{take}_Lead.npy      (T, 165) SMPL-X joints, 120 fps
      motion/pos3d/{split}/{genre}/{take}_Follow.npy
      music/feature/{split}/{genre}/{take}.npy          (T/4, 54) Duolando-style, 30 fps
      music/Juke_features/{split}/{genre}/{take}.npy    (T/4, 4800) Jukebox, 30 fps
      music/WAV/all/{genre}/{take}.wav                  optional audio
      text/{processed,spatial,body_move,rhythm}/{split}/{genre}/{take}.txt

Motion is taken every ``120 / fps``-th frame; the leader is the actor. A take needs both people,
its ``processed`` text and the music file of the chosen ``music`` kind (else it is skipped, as
the authors' loader does); the focused texts are read when all three exist.
"""

from __future__ import annotations

from pathlib import Path

from dualflow.datasets.collection import DuetSet
from dualflow.datasets.dd100 import check_up_axis
from dualflow.datasets.files import load_array, load_features, read_lines, require_dir
from dualflow.datasets.sample import DuetSample, positions_motion
from dualflow.decompose import FocusedDescriptions
from dualflow.errors import DualFlowError
from dualflow.motion.container import TwoPersonMotion

SOURCE_FPS = 120.0
#: music kind -> (folder under music/, sample music_kind, width)
MUSIC_FOLDERS = {"feature": ("feature", "duolando54", 54), "jukebox": ("Juke_features", "jukebox", 4800)}
FOCUSED_FOLDERS = ("spatial", "body_move", "rhythm")


def load_mdd(
    root: str | Path,
    split: str = "train",
    *,
    music: str | None = "feature",
    fps: float = 30.0,
    source_fps: float = SOURCE_FPS,
    limit: int | None = None,
) -> DuetSet:
    """Load one split of MDD (module docstring). music: "feature" (54-d) | "jukebox" (4800-d) | None."""
    if music is not None and music not in MUSIC_FOLDERS:
        raise DualFlowError(f"mdd: music must be one of {sorted(MUSIC_FOLDERS)} or None, got {music!r}")
    skip = _frame_step(fps, source_fps)
    root = Path(root)
    pos_dir, text_dir, music_dir = _split_dirs(root, split, music)
    leads = sorted(pos_dir.glob("*/*_Lead.npy"))
    if not leads:
        raise DualFlowError(f"{pos_dir}: no <genre>/<take>_Lead.npy files; this is not MDD's pos3d folder")
    samples, skipped = [], {}
    for lead_path in leads:
        if limit is not None and len(samples) >= int(limit):
            break
        genre, take = lead_path.parent.name, lead_path.name[: -len("_Lead.npy")]
        key = f"{genre}/{take}"
        follow_path = lead_path.with_name(f"{take}_Follow.npy")
        if not follow_path.is_file():
            skipped[key] = "no _Follow.npy"
            continue
        text_path = text_dir / genre / f"{take}.txt"
        if not text_path.is_file():
            skipped[key] = "no text/processed file"
            continue
        music_path = None if music_dir is None else music_dir / genre / f"{take}.npy"
        if music_path is not None and not music_path.is_file():
            skipped[key] = f"no music/{MUSIC_FOLDERS[music][0]} file"
            continue
        people = [
            _load_dancer(path, f"{take}_{role}", skip, fps)
            for path, role in ((lead_path, "leader"), (follow_path, "follower"))
        ]
        n = min(p.n_frames for p in people)
        feats = None
        if music_path is not None:
            _, kind, width = MUSIC_FOLDERS[music]
            feats = load_features(music_path, width, f"{kind} features")
            n = min(n, len(feats))
            feats = feats[:n]
        if n < 2:
            skipped[key] = "fewer than 2 frames"
            continue
        texts = read_lines(text_path)
        if not texts:
            raise DualFlowError(f"{text_path}: empty description file; write at least one description")
        focused = _focused(root, split, genre, take)
        wav = root / "music" / "WAV" / "all" / genre / f"{take}.wav"
        samples.append(
            DuetSample(
                source="mdd",
                name=key,
                motion=TwoPersonMotion(people[0].slice(0, n), people[1].slice(0, n), texts[0]),
                texts=tuple(texts),
                focused=focused,
                music=feats,
                music_kind=MUSIC_FOLDERS[music][1] if feats is not None else None,
                music_path=wav if wav.is_file() else None,
                genre=genre,
                roles=("leader", "follower"),
                meta={"lead": str(lead_path), "follow": str(follow_path), "text": str(text_path)},
            )
        )
    return DuetSet("mdd", split, root, samples, skipped)


def _frame_step(fps: float, source_fps: float) -> int:
    """Capture frames per output frame; ``fps`` must divide ``source_fps``."""
    skip = source_fps / fps
    if abs(skip - round(skip)) > 1e-9 or round(skip) < 1:
        raise DualFlowError(f"mdd: fps {fps:g} must divide the capture rate {source_fps:g} (e.g. 30, 60, 120)")
    return int(round(skip))


def _split_dirs(root: Path, split: str, music: str | None) -> tuple[Path, Path, Path | None]:
    """The split's (pos3d, processed text, music feature or None) folders, each checked to exist."""
    pos_dir = require_dir(
        root / "motion" / "pos3d" / split,
        f"MDD motion/pos3d/{split}",
        "pass the folder that holds motion/, music/ and text/",
    )
    text_dir = require_dir(
        root / "text" / "processed" / split,
        f"MDD text/processed/{split}",
        "MDD's descriptions live in text/processed/<split>/<genre>/<take>.txt",
    )
    music_dir = None
    if music is not None:
        folder = MUSIC_FOLDERS[music][0]
        music_dir = require_dir(
            root / "music" / folder / split,
            f"MDD music/{folder}/{split}",
            "add the music features or load without music (music=None)",
        )
    return pos_dir, text_dir, music_dir


def _load_dancer(path: Path, name: str, skip: int, fps: float):
    """One dancer's Motion from MDD joint positions ((T, 165) or (T, 55, 3), metres): every ``skip``-th
    frame, the 22 body joints."""
    arr = load_array(path, ndim=(2, 3), min_rows=2)
    arr = arr.reshape(len(arr), -1, 3) if arr.ndim == 2 and arr.shape[1] % 3 == 0 else arr
    if arr.ndim != 3 or arr.shape[1] < 22 or arr.shape[2] != 3:
        raise DualFlowError(f"{path}: expected joint positions (T, 165) or (T, 55, 3), got {arr.shape}")
    arr = arr[::skip, :22]
    check_up_axis(arr, str(path))
    return positions_motion(arr, fps, name, str(path))


def _focused(root: Path, split: str, genre: str, take: str) -> FocusedDescriptions | None:
    paths = [root / "text" / folder / split / genre / f"{take}.txt" for folder in FOCUSED_FOLDERS]
    present = [p.is_file() for p in paths]
    if not any(present):
        return None
    if not all(present):
        missing = paths[present.index(False)]
        raise DualFlowError(
            f"{missing}: missing, but the other focused descriptions of {genre}/{take} exist; "
            "MDD ships spatial, body_move and rhythm together"
        )
    lines = []
    for p in paths:
        got = read_lines(p)
        if not got:
            raise DualFlowError(f"{p}: empty focused description")
        lines.append(got[0])
    return FocusedDescriptions(*lines)
