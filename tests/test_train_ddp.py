"""Multi-process training: 2 CPU processes under torchrun (gloo) keep identical replicas."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch
from safetensors.torch import load_file

from dualflow.train import Trainer, load_train_config

ARGS = [
    "preset=tiny",
    "data.n_clips=8",
    "data.val_clips=0",
    "data.frames=16",
    "batch_size=3",
    "steps=4",
    "threads=1",
    "progress=false",
    "log_every=1",
    "ckpt_every=0",
    "lr=1e-3",
    "warmup_steps=2",
    "ema_decay=0",
    "reactive_prob=0.5",
    "save_replicas=true",
]


@pytest.mark.slow
def test_two_gloo_processes_keep_identical_replicas(tmp_path):
    out = tmp_path / "ddp"
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node",
        "2",
        "-m",
        "dualflow.train",
    ]
    for a in ARGS + [f"out_dir={out}"]:
        cmd += ["--set", a]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    assert "replica max |diff| across 2 processes: 0.000e+00" in proc.stdout
    r0 = load_file(str(out / "replica_rank0.safetensors"))
    r1 = load_file(str(out / "replica_rank1.safetensors"))
    assert r0.keys() == r1.keys() and len(r0) > 20
    for k in r0:
        assert torch.equal(r0[k], r1[k]), k

    # The ranks drew different batches: a single process with rank 0's batches ends elsewhere,
    # so rank 1's gradients really were averaged in (and the weights did train).
    single = Trainer(load_train_config(None, ARGS + [f"out_dir={tmp_path / 'single'}", "save_replicas=false"]))
    init = {k: v.clone() for k, v in single.model.state_dict().items()}
    single.run()
    solo = single.model.state_dict()
    assert any(not torch.equal(solo[k], init[k]) for k in solo)
    assert any(not torch.allclose(solo[k], r0[k], atol=1e-7) for k in r0)
    assert any(not torch.equal(r0[k], init[k]) for k in r0)
