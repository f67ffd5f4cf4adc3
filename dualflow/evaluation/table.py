"""The results table, shaped like the paper's Table 1 (rows: methods and ablations).

Columns: R-Precision top-1/2/3 (↑), FID (↓), MMDist (↓), Diversity (→, closer to
the ground truth's is better), MModality (↑), BED (↑), BAS (↑). A cell is
"mean±ci" (95 % half-width over replications) or "-" when the metric is
undefined for the row (multimodality of the ground truth, BAS without beats).
Section rows (a label with no metrics) print as headings, e.g. "Reactive Task".
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from dualflow.evaluation.metrics import Estimate
from dualflow.evaluation.protocol import METRIC_KEYS

HEADERS = {
    "r1": "R@1 ↑",
    "r2": "R@2 ↑",
    "r3": "R@3 ↑",
    "fid": "FID ↓",
    "mm_dist": "MMDist ↓",
    "diversity": "Diversity →",
    "multimodality": "MModality ↑",
    "bed": "BED ↑",
    "bas": "BAS ↑",
}


def cell(est: Estimate | None, digits: int = 3) -> str:
    if est is None or est.n == 0 or math.isnan(est.mean):
        return "-"
    if est.n < 2:
        return f"{est.mean:.{digits}f}"
    return f"{est.mean:.{digits}f}±{est.ci:.{digits}f}"


def format_table(rows: Sequence[tuple[str, dict[str, Estimate] | None]], title: str = "", digits: int = 3) -> str:
    """Plain-text table: one line per (label, metrics) row; metrics None = a section heading."""
    body = [
        [label] + ([cell(m.get(k), digits) for k in METRIC_KEYS] if m is not None else [""] * len(METRIC_KEYS))
        for label, m in rows
    ]
    head = ["Method"] + [HEADERS[k] for k in METRIC_KEYS]
    widths = [max(len(r[i]) for r in body + [head]) for i in range(len(head))]

    def line(r):
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip()

    out = ([title] if title else []) + [line(head), "-" * len(line(head))]
    for (label, m), r in zip(rows, body):
        out.append(f"[{label}]" if m is None else line(r))
    return "\n".join(out)
