"""bench/dualflow_gpu.py runs end to end on the CPU (--quick, tiny preset): every section measures
and writes its figures, and the CUDA-graph and compiled generation paths give the eager output."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import dualflow_gpu  # noqa: E402


@pytest.mark.slow
def test_quick_run_measures_every_section_without_errors(tmp_path):
    out = tmp_path / "gpu.json"
    assert dualflow_gpu.main(["--quick", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    sections = data["sections"]
    assert set(sections) >= {"conv", "generate", "stream", "partner", "train"}
    for name, figures in sections.items():
        for key, value in figures.items():
            assert not (isinstance(value, str) and value.startswith("error")), (name, key, value)
    generate = sections["generate"]
    diffs = [v for k, v in generate.items() if k.startswith("max |eager")]
    # on the CPU every variant (CUDA graph, precision, compiled blocks) computes the eager float32 output
    assert len(diffs) == len(dualflow_gpu.GENERATE_VARIANTS) - 1 and max(diffs) < 1e-4
    rates = [v["samples_per_s"] for v in sections["train"].values() if isinstance(v, dict)]
    assert rates and min(rates) > 0
