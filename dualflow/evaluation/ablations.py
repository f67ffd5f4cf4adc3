"""The paper's ablation switches as training-config overrides (Tables 4, 6, 7, 8; app. D).

Each switch is a list of ``dualflow-bridge train --set KEY=VALUE`` overrides applied on top of
the full model's config (which trains with retrieval: ``retrieval.enabled=true``), and the row
label ``dualflow-bridge eval`` prints for it. ``{v}`` is the switch's value (L or k).

==============  ==========================================  =====================================
switch          overrides                                   paper
==============  ==========================================  =====================================
full            retrieval.enabled=true                      DualFlow
no_rag          retrieval.enabled=false                     w/o RAG (Table 7)
no_triplet      loss_weights.triplet=0                      w/o L_triplet
no_sync         loss_weights.sync=0                         w/o L_sync (Table 8)
spectral        music=edge35, model.music_dim=35            spectral music features
                (or duolando54 / 54)
jukebox         music=jukebox, model.music_dim=4800         Jukebox features (the paper's); needs
                                                            precomputed .npy (e.g. MDD's
                                                            Juke_features: data.options.music=jukebox)
look_ahead      model.look_ahead={v}                        L = 0 / 20 vs 10 (Table 6)
retrieval_k     retrieval.k={v}                             k = 1, 3, 7 vs 5 / 3 (Table 7)
==============  ==========================================  =====================================
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
