"""Two-person motion datasets, one sample format for all (:class:`DuetSample`).

``load_dataset(name, root, split, **options)`` picks a loader by name:

==================  =====================================================  =========================
name                layout                                                 module
==================  =====================================================  =========================
``interhuman``      InterGen's InterHuman folder                           :mod:`.interhuman`
``interhuman_as``   the same + actor-reactor label json (InterHuman-AS)    :mod:`.interhuman`
``dd100``           Duolando's DD100 pos3d + music features                :mod:`.dd100`
``mdd``             the MDD authors' motion/ music/ text/ folders          :mod:`.mdd`
``bvh_pairs``       a folder of two-person BVH captures (+ texts)          :mod:`.bvh_pairs`
``synthetic``       generated duets (:mod:`dualflow.synthetic`), no root   :mod:`.synthetic`
==================  =====================================================  =========================

Training data: :mod:`.config` (the ``data`` section of a training config),
:mod:`.synthetic` (the generated duets as arrays), :mod:`.windows` (fixed-length windows
of any DuetSet) and :mod:`.training` (the torch datasets the trainer reads). Importing this
package never imports torch; only :mod:`.training` does.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from dualflow.datasets.bvh_pairs import load_bvh_pairs
from dualflow.datasets.collection import DuetSet
from dualflow.datasets.dd100 import load_dd100
from dualflow.datasets.interhuman import load_interhuman
from dualflow.datasets.mdd import load_mdd
from dualflow.datasets.sample import DuetSample
from dualflow.datasets.synthetic import load_synthetic
from dualflow.errors import DualFlowError


def _interhuman_as(root, split="train", *, actor_labels=True, **kw) -> DuetSet:
    return load_interhuman(root, split, actor_labels=actor_labels, **kw)


#: registry name -> loader(root, split, **options) -> DuetSet
LOADERS: dict[str, Callable[..., DuetSet]] = {
    "interhuman": load_interhuman,
    "interhuman_as": _interhuman_as,
    "dd100": load_dd100,
    "mdd": load_mdd,
    "bvh_pairs": load_bvh_pairs,
    "synthetic": load_synthetic,
}


def load_dataset(name: str, root: str | Path | None = None, split: str | None = None, **options) -> DuetSet:
    """Load split ``split`` of dataset ``name`` from ``root`` (see the table above).

    split None: the loader's default ("train"; "all" for bvh_pairs).

    options go to the loader (e.g. ``limit``, ``music``, ``actor_labels``, ``n_clips``);
    an unknown option is a DualFlowError naming the loader's valid ones.
    """
    if name not in LOADERS:
        raise DualFlowError(f"unknown dataset {name!r}; choose one of {', '.join(LOADERS)}")
    loader = LOADERS[name]
    if name != "synthetic" and root is None:
        raise DualFlowError(f"dataset {name!r} needs a root folder (--root / data.root)")
    try:
        return loader(root, **options) if split is None else loader(root, split, **options)
    except TypeError as exc:
        if "unexpected keyword" in str(exc) or "positional" in str(exc):
            import inspect

            valid = [p for p in inspect.signature(loader).parameters if p not in ("root", "split")]
            raise DualFlowError(f"dataset {name!r}: bad option(s) {sorted(options)}; valid options: {valid}") from None
        raise


__all__ = [
    "DuetSample",
    "DuetSet",
    "LOADERS",
    "load_dataset",
    "load_bvh_pairs",
    "load_dd100",
    "load_interhuman",
    "load_mdd",
    "load_synthetic",
]
