"""A folder of two-person BVH captures (like the CMU two-subject trials) with optional texts.

Layout::

    ROOT/
      pairs.txt              one pair per line: ``<actor>.bvh <reactor>.bvh`` (paths relative
                             to ROOT; ``#`` starts a comment), e.g. ``18_01.bvh 19_01.bvh``
      <actor stem>.txt       optional descriptions of the pair, one per line
      train.txt / test.txt   optional split files listing actor stems (e.g. ``18_01``)

Without ``pairs.txt``, files named ``<take>_actor.bvh`` / ``<take>_reactor.bvh`` are
paired by take (text in ``<take>.txt``). The two files of a pair share the capture's
world frame; they are read by :func:`dualflow.motion.io.load_pair` (joint-map and
unit detection, the reactor in the actor's units and axes) and resampled to ``fps``
(default 30). ``split="all"`` keeps every pair; another split needs its split file.
"""

from __future__ import annotations

from pathlib import Path

from dualflow.datasets.collection import DuetSet
from dualflow.datasets.files import read_lines, read_name_list, require_dir, require_file
from dualflow.datasets.sample import DuetSample
from dualflow.errors import DualFlowError
from dualflow.motion.io import load_pair


def _pairs(root: Path) -> list[tuple[str, Path, Path]]:
    manifest = root / "pairs.txt"
    if manifest.is_file():
        out = []
        for i, line in enumerate(read_lines(manifest), 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            parts = line.split()
            if len(parts) != 2 or not all(p.lower().endswith(".bvh") for p in parts):
                raise DualFlowError(f"{manifest}, line {i}: expected '<actor>.bvh <reactor>.bvh', got {line!r}")
            a, b = root / parts[0], root / parts[1]
            for p in (a, b):
                require_file(p, "BVH file", f"it is named on line {i} of {manifest}")
            out.append((a.stem, a, b))
        return out
    out = []
    for a in sorted(root.glob("*_actor.bvh")):
        take = a.name[: -len("_actor.bvh")]
        b = root / f"{take}_reactor.bvh"
        require_file(b, "reactor BVH", f"{a.name} needs its partner {b.name} (or list pairs in pairs.txt)")
        out.append((take, a, b))
    return out


def load_bvh_pairs(
    root: str | Path, split: str = "all", *, fps: float = 30.0, limit: int | None = None, **bvh_options
) -> DuetSet:
    """Load the BVH pairs of ``root`` (module docstring); ``bvh_options`` go to ``load_pair``
    (``joint_map``, ``scale``, ``up``, ``drop_first``, ...)."""
    root = require_dir(Path(root), "BVH pairs", "pass the folder that holds pairs.txt and the .bvh files")
    pairs = _pairs(root)
    if not pairs:
        raise DualFlowError(f"{root}: no pairs.txt and no <take>_actor.bvh / <take>_reactor.bvh files")
    keep = None
    if split != "all":
        keep = set(
            read_name_list(
                require_file(
                    root / f"{split}.txt",
                    f"split file for {split!r}",
                    "list the actor stems of the split, one per line, or use split='all'",
                )
            )
        )
    samples = []
    for name, a, b in pairs:
        if keep is not None and name not in keep:
            continue
        if limit is not None and len(samples) >= int(limit):
            break
        text_path = root / f"{name}.txt"
        texts = tuple(read_lines(text_path)) if text_path.is_file() else ()
        pair = load_pair(a, b, texts[0] if texts else "", fps=float(fps), **bvh_options)
        samples.append(
            DuetSample(
                source="bvh_pairs",
                name=name,
                motion=pair,
                texts=texts,
                roles=(a.stem, b.stem),
                meta={"actor_file": str(a), "reactor_file": str(b)},
            )
        )
    return DuetSet("bvh_pairs", split, root, samples, {})
