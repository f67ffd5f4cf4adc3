"""InterHuman and InterHuman-AS in InterGen's layout.

Layout (InterGen's ``datasets/interhuman.py``)::

    ROOT/
      train.txt  val.txt  test.txt     clip names, one per line
      ignore_list.txt                  optional; clips to leave out
      motions_processed/person{1,2}/<name>.npy   (T, 492) at 30 fps, first 22 positions used
      annots/<name>.txt                one description per line
      actor_reactor.json               InterHuman-AS only: clip -> actor

Motion files go through :func:`dualflow.motion.io.load_motion` (InterGen's axis change, then
ours), so both people stay in the capture's shared frame; clips shorter than ``min_frames``
(InterGen: 15) are skipped. InterHuman-AS (ReGenNet) labels the actor as ``"person1"`` /
``"person2"``, ``1`` / ``2`` or ``{"actor": "person1"}`` (the file was not available to check);
unlabelled clips are skipped. Plain InterHuman keeps person1 as the actor.
"""

from __future__ import annotations

import json
from pathlib import Path

from dualflow.datasets.collection import DuetSet
from dualflow.datasets.files import read_lines, read_name_list, require_dir, require_file
from dualflow.datasets.sample import DuetSample
from dualflow.errors import DualFlowError
from dualflow.motion.container import TwoPersonMotion
from dualflow.motion.io import load_motion

PEOPLE = ("person1", "person2")
LABEL_FILE = "actor_reactor.json"
MIN_FRAMES = 15


def read_actor_labels(path: Path) -> dict[str, str]:
    """Clip name -> "person1" | "person2" (the actor) from an InterHuman-AS label file."""
    require_file(
        path,
        "InterHuman-AS actor-reactor label file",
        f"put the JSON mapping clip name -> actor ('person1' or 'person2') at {path}",
    )
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DualFlowError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(raw, dict):
        raise DualFlowError(f"{path}: expected a JSON object mapping clip name -> actor, got {type(raw).__name__}")
    labels = {}
    for name, value in raw.items():
        if isinstance(value, dict):
            value = value.get("actor")
        if value in (1, "1", "person1", "p1"):
            labels[str(name)] = "person1"
        elif value in (2, "2", "person2", "p2"):
            labels[str(name)] = "person2"
        else:
            raise DualFlowError(
                f"{path}, clip {name!r}: actor must be 'person1' or 'person2' (or 1 / 2), got {value!r}"
            )
    return labels


def load_interhuman(
    root: str | Path,
    split: str = "train",
    *,
    actor_labels: str | Path | bool | None = None,
    min_frames: int = MIN_FRAMES,
    limit: int | None = None,
) -> DuetSet:
    """Load one split of InterHuman (or InterHuman-AS with ``actor_labels``).

    actor_labels: None/False = InterHuman (person1 acts); True = ``ROOT/actor_reactor.json``;
    a path = that label file. limit: keep the first ``limit`` clips of the split file.
    """
    root = require_dir(
        Path(root), "InterHuman dataset", "pass the folder that holds train.txt, motions_processed/ and annots/"
    )
    split_file = _check_layout(root, split)
    ignore = set()
    if (root / "ignore_list.txt").is_file():
        ignore = set(read_name_list(root / "ignore_list.txt"))
    labels = _actor_labels(root, actor_labels)
    source = "interhuman_as" if labels is not None else "interhuman"

    names = read_name_list(split_file)
    if limit is not None:
        names = names[: int(limit)]
    samples, skipped = [], {}
    for name in names:
        if name in ignore:
            skipped[name] = "in ignore_list.txt"
            continue
        if labels is not None and name not in labels:
            skipped[name] = "no actor-reactor label"
            continue
        paths, people, text_path = _read_clip(root, name, split_file)
        if people[0].n_frames < int(min_frames):
            skipped[name] = f"shorter than {min_frames} frames"
            continue
        texts = read_lines(text_path)
        if not texts:
            raise DualFlowError(f"{text_path}: empty annotation file; write at least one description")
        actor_i = 0 if labels is None or labels[name] == "person1" else 1
        pair = TwoPersonMotion(
            people[actor_i].replace(name=f"{name}_{PEOPLE[actor_i]}"),
            people[1 - actor_i].replace(name=f"{name}_{PEOPLE[1 - actor_i]}"),
            texts[0],
        )
        samples.append(
            DuetSample(
                source=source,
                name=name,
                motion=pair,
                texts=tuple(texts),
                roles=(PEOPLE[actor_i], PEOPLE[1 - actor_i]),
                meta={"files": [str(p) for p in paths], "annots": str(text_path)},
            )
        )
    return DuetSet(source, split, root, samples, skipped)


def _check_layout(root: Path, split: str) -> Path:
    """The split's name list (``ROOT/<split>.txt``), after checking InterGen's folders are present."""
    split_file = require_file(
        root / f"{split}.txt",
        f"split file for {split!r}",
        "InterGen's layout has train.txt, val.txt and test.txt in the dataset root",
    )
    for person in PEOPLE:
        require_dir(
            root / "motions_processed" / person,
            f"motions_processed/{person}",
            "InterGen's layout keeps each person's .npy files under motions_processed/person1|person2",
        )
    require_dir(root / "annots", "annots", "InterGen's layout keeps one <name>.txt per clip under annots/")
    return split_file


def _actor_labels(root: Path, actor_labels: str | Path | bool | None) -> dict[str, str] | None:
    """Clip name -> acting person read from the label file ``actor_labels`` names, or None for InterHuman."""
    if actor_labels is True:
        return read_actor_labels(root / LABEL_FILE)
    if actor_labels not in (None, False):
        return read_actor_labels(Path(actor_labels))
    return None


def _read_clip(root: Path, name: str, split_file: Path):
    """(the two .npy paths, the two people's Motions of equal length, the annotation path) of clip ``name``."""
    paths = [root / "motions_processed" / p / f"{name}.npy" for p in PEOPLE]
    for p in paths:
        require_file(
            p, "motion file", f"clip {name!r} is listed in {split_file.name}; restore the file or remove the line"
        )
    text_path = require_file(
        root / "annots" / f"{name}.txt",
        "annotation file",
        f"clip {name!r} needs its descriptions in annots/{name}.txt",
    )
    people = [load_motion(p, source_fps=30.0) for p in paths]
    if people[0].n_frames != people[1].n_frames:
        raise DualFlowError(
            f"{paths[1]}: {people[1].n_frames} frames, but {paths[0].name} of person1 has "
            f"{people[0].n_frames}; both people of a clip must have the same length"
        )
    return paths, people, text_path
