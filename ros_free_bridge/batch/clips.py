"""Which clips a ``retarget-check`` batch runs: the motion files of a folder, pairs joined.

A :class:`Clip` is one row of the batch: the file the robot takes, for a pair the actor's file too.
Discovery rules (single files, ``--pairs`` patterns, InterGen's person1/person2 layout): docs/retarget_check.md.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

MOTION_SUFFIXES = (".bvh", ".npz", ".npy")


@dataclass(frozen=True)
class Clip:
    """One row of the batch: ``path`` is the file the robot takes (for a pair: the reactor's),
    ``actor`` the other person's file of a pair, ``name`` the row name; ``problem`` (a pair
    with a missing file) makes it an ``error`` row without running anything."""

    name: str
    path: Path
    actor: Path | None = None
    actor_name: str = ""
    problem: str = ""


@dataclass(frozen=True)
class PairPattern:
    """Two file-name patterns, actor first, reactor second, each with one ``{name}``:
    ``{name}_S1.bvh,{name}_S2.bvh`` joins ``take7_S1.bvh`` (actor) and ``take7_S2.bvh``
    (reactor, the robot's part) in the same folder. Names match whole and case-sensitively."""

    actor: str
    reactor: str

    @classmethod
    def parse(cls, text: str) -> PairPattern:
        from ros_free_bridge.errors import BridgeError

        parts = [p.strip() for p in str(text).split(",")]
        fix = "give two file-name patterns, actor first, e.g. --pairs '{name}_S1.bvh,{name}_S2.bvh'"
        if len(parts) != 2 or not all(parts):
            raise BridgeError(f"--pairs {text!r}: {fix}")
        for p in parts:
            if p.count("{name}") != 1 or re.search(r"\{(?!name\})", p):
                raise BridgeError(
                    f"--pairs {text!r}: each pattern needs exactly one {{name}} and no other braces; {fix}"
                )
            if "/" in p or "\\" in p:
                raise BridgeError(
                    f"--pairs {text!r}: patterns are file names, not paths (both files lie in one folder); {fix}"
                )
            if Path(p.replace("{name}", "x")).suffix.lower() not in MOTION_SUFFIXES:
                raise BridgeError(
                    f"--pairs {text!r}: {p!r} must end in a motion file type ({', '.join(MOTION_SUFFIXES)})"
                )
        if parts[0] == parts[1]:
            raise BridgeError(f"--pairs {text!r}: the actor's and the reactor's patterns are the same; {fix}")
        return cls(*parts)

    def _regex(self, pattern: str) -> re.Pattern:
        head, tail = pattern.split("{name}")
        return re.compile(re.escape(head) + "(?P<name>.+)" + re.escape(tail))

    def match(self, filename: str) -> tuple[str | None, str | None]:
        """(name if ``filename`` is an actor's file, name if it is a reactor's file)."""
        a, r = self._regex(self.actor).fullmatch(filename), self._regex(self.reactor).fullmatch(filename)
        return (a["name"] if a else None), (r["name"] if r else None)

    def __str__(self) -> str:
        return f"{self.actor},{self.reactor}"


def find_motion_files(folder, recursive: bool = False, exclude=None) -> list[Path]:
    """The motion files of ``folder`` (an InterGen pair by its reactor's file), sorted; ``exclude``: a
    folder to leave out (the batch's own output folder, when it lies inside the input)."""
    folder = Path(folder)
    if not folder.is_dir():
        from ros_free_bridge.errors import BridgeError

        raise BridgeError(f"{folder}: not a folder; give a folder of motion files (BVH, npz, npy)")
    skip = Path(exclude).resolve() if exclude is not None else None
    candidates = [
        p
        for p in (folder.rglob("*") if recursive else folder.iterdir())
        if p.is_file()
        and p.suffix.lower() in MOTION_SUFFIXES
        and not (skip is not None and p.resolve().is_relative_to(skip))
    ]
    # InterGen's layout: FOLDER/ or FOLDER/motions_processed/ (with --recursive: any folder) holding
    # person1/ and person2/; their files are listed as pairs, by the reactor's file
    bases = {folder, folder / "motions_processed"}
    if recursive:
        bases |= {p.parent.parent for p in candidates}
    bases = sorted(b for b in bases if (b / "person1").is_dir() and (b / "person2").is_dir())
    people = {b / person for b in bases for person in ("person1", "person2")}
    found = [p for p in candidates if p.parent not in people]
    for base in bases:
        found += _intergen_reactors(base)
    return sorted(found)


def find_clips(folder, recursive: bool = False, exclude=None, pairs: PairPattern | str | None = None) -> list[Clip]:
    """The batch's clips, sorted by name: :func:`find_motion_files`, with the files that
    ``pairs`` joins turned into one clip per capture (a file without its partner: a clip with a ``problem``)."""
    files = find_motion_files(folder, recursive, exclude)
    if pairs is None:
        return [Clip(clip_name(f, folder), f) for f in files]
    pattern = pairs if isinstance(pairs, PairPattern) else PairPattern.parse(pairs)
    present = set(files)
    used: set[Path] = set()
    clips = []
    for f in files:  # pairs first, found from the reactor's side
        _, as_reactor = pattern.match(f.name)
        if as_reactor is not None:
            actor = f.parent / pattern.actor.replace("{name}", as_reactor)
            if actor in present and actor != f:
                clips.append(Clip(clip_name(f, folder), f, actor, clip_name(actor, folder)))
                used |= {f, actor}
    for f in files:
        if f in used:
            continue
        as_actor, as_reactor = pattern.match(f.name)
        name = clip_name(f, folder)
        if as_reactor is not None:
            missing = pattern.actor.replace("{name}", as_reactor)
            clips.append(
                Clip(
                    name,
                    f,
                    problem=f"pair {pattern}: {name} has no actor file {missing} beside it; "
                    f"add it, or move {f.name} out of the folder",
                )
            )
        elif as_actor is not None:
            missing = pattern.reactor.replace("{name}", as_actor)
            clips.append(
                Clip(
                    name,
                    f,
                    problem=f"pair {pattern}: {name} is an actor's file without its reactor "
                    f"{missing} beside it; add it, or move {f.name} out of the folder",
                )
            )
        else:
            clips.append(Clip(name, f))
    return sorted(clips, key=lambda c: c.name)


def _intergen_reactors(base: Path) -> list[Path]:
    """The reactor's file of each clip under ``base``/person1|person2 (a clip with one person only:
    that person's file); InterHuman-AS's actor_reactor.json in the dataset root says who acts."""
    from dualflow.datasets.interhuman import LABEL_FILE, PEOPLE, read_actor_labels

    files = {
        person: {f.name: f for f in (base / person).iterdir() if f.is_file() and f.suffix.lower() in MOTION_SUFFIXES}
        for person in PEOPLE
    }
    root = base.resolve()
    root = root.parent if root.name == "motions_processed" else root
    labels = read_actor_labels(root / LABEL_FILE) if (root / LABEL_FILE).is_file() else {}
    reactors = []
    for name in sorted(set(files["person1"]) | set(files["person2"])):
        order = ("person1", "person2") if labels.get(Path(name).stem) == "person2" else ("person2", "person1")
        reactors.append(next(files[p][name] for p in order if name in files[p]))
    return reactors


def clip_name(path, folder) -> str:
    """A clip's row name: its path relative to the batch's folder (``/``-separated)."""
    return Path(path).relative_to(folder).as_posix()


def as_clips(files, folder=None) -> list[Clip]:
    """Clips from a list of :class:`Clip` or of files (named relative to ``folder``, default by file name)."""
    out = []
    for f in files:
        if isinstance(f, Clip):
            out.append(f)
        else:
            f = Path(f)
            out.append(Clip(clip_name(f, folder) if folder is not None else f.name, f))
    return out
