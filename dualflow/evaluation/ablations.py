"""The paper's ablation switches as training-config overrides (Tables 4, 6, 7, 8; app. D).

Contract: :data:`ABLATION_SWITCHES` maps a switch (full, no_rag, no_triplet, no_sync, spectral,
jukebox, look_ahead, retrieval_k) to the ``dualflow-bridge train --set KEY=VALUE`` overrides
applied on top of the full model's config (which trains with retrieval) and to the row label
``dualflow-bridge eval`` prints; ``{v}`` in an override is the switch's value (L or k).
"""

from __future__ import annotations

from dualflow.errors import DualFlowError

#: switch -> (row label, overrides on top of the full model's config)
ABLATION_SWITCHES: dict[str, tuple[str, tuple[str, ...]]] = {
    "full": ("DualFlow", ("retrieval.enabled=true",)),
    "no_rag": ("DualFlow (w/o RAG)", ("retrieval.enabled=false",)),
    "no_triplet": ("DualFlow (w/o L_triplet)", ("retrieval.enabled=true", "loss_weights.triplet=0")),
    "no_sync": ("DualFlow (w/o L_sync)", ("retrieval.enabled=true", "loss_weights.sync=0")),
    "spectral": ("DualFlow (Spectral)", ("retrieval.enabled=true", "music=edge35", "model.music_dim=35")),
    "jukebox": ("DualFlow (Jukebox)", ("retrieval.enabled=true", "music=jukebox", "model.music_dim=4800")),
    "look_ahead": ("DualFlow (L={v})", ("retrieval.enabled=true", "model.look_ahead={v}")),
    "retrieval_k": ("DualFlow (k={v})", ("retrieval.enabled=true", "retrieval.k={v}")),
}


def ablation_overrides(switch: str, value: int | None = None) -> tuple[str, list[str]]:
    """(row label, ``--set`` overrides) of one switch; ``value`` for look_ahead / retrieval_k."""
    if switch not in ABLATION_SWITCHES:
        raise DualFlowError(f"unknown ablation switch {switch!r}; choose one of {', '.join(ABLATION_SWITCHES)}")
    label, sets = ABLATION_SWITCHES[switch]
    needs_value = "{v}" in label
    if needs_value and value is None:
        raise DualFlowError(f"ablation switch {switch!r} needs a value (L or k)")
    v = "" if value is None else str(int(value))
    return label.format(v=v), [s.format(v=v) for s in sets]
