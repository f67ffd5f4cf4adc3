"""Compile DualFlow one block at a time (``torch.compile`` of the block stages, shared by all blocks).

Compiling the whole 20-block model traces every block into one graph (minutes before the first
step, issue 28). The blocks are the same code with different weights, so compiling the three
stages of :class:`~dualflow.model.DualFlowBlock` (``temporal``, ``motion_cross``, ``finish``)
as functions of (block, inputs) gives graphs that every block reuses (weights are graph inputs,
not constants: torch's default ``inline_inbuilt_nn_modules``), so compile time does not grow
with the depth. The model's Python control flow (modes, masks, the loop over blocks) stays eager.

Off by default (``TrainConfig.compile``, ``--compile`` of the benches); on a CPU the compile
time is rarely repaid. Results equal the eager model's up to floating-point reassociation.
"""

from __future__ import annotations

import torch

from dualflow.model import DualFlow, DualFlowBlock

STAGES = ("temporal", "motion_cross", "finish", "modulations")


def compile_blocks(model: DualFlow, **compile_kwargs) -> DualFlow:
    """Replace each block's stages by one compiled function per stage, shared by all blocks
    (``compile_kwargs`` go to ``torch.compile``, e.g. ``mode="max-autotune-no-cudagraphs"``).
    Returns the model, changed in place; its weights and state_dict are untouched."""
    compiled = {name: torch.compile(getattr(DualFlowBlock, name), dynamic=False, **compile_kwargs) for name in STAGES}
    for block in model.blocks:
        for name, fn in compiled.items():
            setattr(block, name, fn.__get__(block, DualFlowBlock))
    return model
