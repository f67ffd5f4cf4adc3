"""Evaluation as the field does it (paper sec. 4, InterGen / Duolando protocols).

* :mod:`.metrics` — FID, R-precision, MM distance, diversity, multimodality (numpy);
* :mod:`.rhythm` — Beat Alignment Score and Beat Echo Degree (numpy);
* :mod:`.dance` — DD100's FID_k / FID_cd / Div (numpy);
* :mod:`.evaluator` — the trainable InterCLIP-style motion-text evaluator (torch);
* :mod:`.protocol` — the replicated evaluation of a checkpoint or the ground truth;
* :mod:`.table` — the Table-1-shaped results table;
* :mod:`.reactor` — reactor position error against the synthetic follower rule (torch).

This ``__init__`` stays light (no torch import); ``reactor_errors`` and
``generate_reactor`` (formerly ``dualflow/evaluation.py``) are re-exported lazily.
"""

from __future__ import annotations

_LAZY = {"reactor_errors", "generate_reactor", "mpjpe", "ReactorErrors"}


def __getattr__(name: str):
    if name in _LAZY:
        from dualflow.evaluation import reactor

        return getattr(reactor, name)
    raise AttributeError(f"module 'dualflow.evaluation' has no attribute {name!r}")
