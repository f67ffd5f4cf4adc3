"""Speed of one retrieval query against a 10,000-entry database on the CPU (issue 7, item 3).

Prints, for the vectorised scorer (dualflow.retrieval: one matrix product + argpartition):
  * one cue (384-d text embedding, eq. 1 + top-5),
  * a full query (spatial, body, rhythm 384-d + music 70-d, top-5 each),
  * a training batch of 32 queries with self-exclusion (all four cues),
next to a baseline measured in the same run: a plain Python loop evaluating eq. 1 entry by entry
(math.exp, numpy dot per entry) and sorting. Target: well under 10 ms for one query.

Also printed: the cosine term through numpy's matmul instead of torch's (dualflow.retrieval uses
torch: on a loaded 2-core machine OpenBLAS's threaded GEMV was ~10-20x slower).

Run: python bench/retrieval_speed.py [--entries 10000] [--reps 200] [--quick]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.table import NA, Row, parse_args, script_main, verdict  # noqa: E402
from dualflow.retrieval import DEFAULT_LAMBDA, RetrievalDatabase, similarity_scores, top_k  # noqa: E402

TARGET_MS = 10.0
QUICK = ["--reps", "20"]


def _time(fn, reps: int) -> float:
    """Median wall time of fn() in milliseconds over reps runs (after one warm-up)."""
    fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def python_loop_query(emb: np.ndarray, lengths: np.ndarray, q: np.ndarray, lq: int, k: int) -> list[int]:
    """Baseline: eq. 1 one entry at a time, then a full sort."""
    qn = q / np.linalg.norm(q)
    scores = []
    for i in range(emb.shape[0]):
        li = float(lengths[i])
        s = float(np.dot(emb[i], qn)) * math.exp(-DEFAULT_LAMBDA * abs(li - lq) / max(li, lq))
        scores.append((s, i))
    scores.sort(reverse=True)
    return [i for _, i in scores[:k]]


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--entries", type=int, default=10_000)
    ap.add_argument("--reps", type=int, default=200)
    args = parse_args(ap, argv, quick, QUICK)
    n = args.entries
    rng = np.random.default_rng(0)
    emb = {c: rng.standard_normal((n, 384)).astype(np.float32) for c in ("spatial", "body", "rhythm")}
    emb["music"] = rng.standard_normal((n, 70)).astype(np.float32)
    lengths = rng.integers(30, 300, n)
    # Motions are not touched by a query; a 1-frame placeholder keeps the database small in memory.
    db = RetrievalDatabase(
        np.zeros((n, 1, 2, 262), np.float32), np.minimum(lengths, 1), emb, [str(i) for i in range(n)]
    )
    db.lengths = lengths  # real clip lengths for eq. 1 (the 1-frame motions are never gathered)
    q = {c: rng.standard_normal(e.shape[1]).astype(np.float32) for c, e in db.embeddings.items()}

    one = _time(lambda: top_k(similarity_scores(db.embeddings["body"], db.lengths, q["body"], 120), 5), args.reps)
    full = _time(lambda: db.query(q, 120, k=5), args.reps)
    batch = np.arange(32)
    train = _time(lambda: db.query_training(batch, k=5), max(10, args.reps // 10))
    loop = _time(lambda: python_loop_query(db.embeddings["body"], db.lengths, q["body"], 120, 5), 3)
    qb = q["body"] / np.linalg.norm(q["body"])
    numpy_gemv = _time(lambda: top_k((db.embeddings["body"] @ qb)[None], 5), args.reps)

    # Same answer from both scorers.
    fast = top_k(similarity_scores(db.embeddings["body"], db.lengths, q["body"], 120), 5)[0][0].tolist()
    assert fast == python_loop_query(db.embeddings["body"], db.lengths, q["body"], 120, 5), "scorers disagree"

    print(
        f"retrieval query against {n:,} entries (CPU, median of repeats); baseline = Python loop scorer "
        f"({loop:.1f} ms per cue, x4 for four cues); speed-up {loop / one:.0f}x on one cue"
    )
    target = f"< {TARGET_MS:g}"
    return [
        Row("retrieval: one cue, 384-d, eq.1 + top-5 (ms)", one, loop, target, verdict(one < TARGET_MS)),
        Row(
            "retrieval: full query, 3 text cues + music, top-5 each (ms)",
            full,
            4 * loop,
            target,
            verdict(full < TARGET_MS),
        ),
        Row(
            "retrieval: training batch of 32, self excluded, 4 cues (ms/query)",
            train / 32,
            4 * loop,
            target,
            verdict(train / 32 < TARGET_MS),
        ),
        Row("retrieval: one cue via numpy matmul (OpenBLAS; not used, for comparison) (ms)", numpy_gemv, loop, "", NA),
    ]


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())
