"""Where the partner model runs (``--partner-device``): a device torch cannot use is one clear
error before anything starts; on a GPU the live partner is the CPU's, from full windows."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from ros_free_bridge.cli import main
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.partner.reactor import partner_device


def test_a_device_torch_cannot_use_is_named_with_the_fix():
    assert partner_device("cpu") == "cpu"
    for bad in ("tpu", "cuda:x", "cuda1"):
        with pytest.raises(BridgeError, match="choose 'cpu' or a CUDA device"):
            partner_device(bad, check_torch=False)
    if not torch.cuda.is_available():
        with pytest.raises(BridgeError, match="use --partner-device cpu"):
            partner_device("cuda")
    else:
        with pytest.raises(BridgeError, match="choose cuda:0"):
            partner_device(f"cuda:{torch.cuda.device_count()}")


def test_the_bridge_process_checks_the_name_without_importing_torch():
    code = (
        "import sys\n"
        "from ros_free_bridge.partner.reactor import partner_device\n"
        "assert partner_device('cuda:1', check_torch=False) == 'cuda:1'\n"
        "assert partner_device('cpu') == 'cpu'\n"
        "assert 'torch' not in sys.modules, 'torch imported'\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


@pytest.mark.skipif(torch.cuda.is_available(), reason="the error is for a machine without CUDA")
def test_run_with_a_cuda_partner_and_no_gpu_exits_2_before_it_starts(tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(
        ["run", "--transport", "record", "--quiet", "--seconds", "1", "--partner-device", "cuda", "--out", str(out)]
    )
    err = capsys.readouterr().err
    assert rc == 2
    assert "partner device 'cuda'" in err and "--partner-device cpu" in err
    assert not (out / "telemetry.jsonl").exists()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_partner_on_a_gpu_is_the_cpu_partner():
    from dualflow.streaming import StreamConfig
    from dualflow.synthetic import make_leader
    from ros_free_bridge.partner.reactor import ReactorStage
    from ros_free_bridge.sources.udp import ActorFrame

    leader = make_leader(4.0, 30.0, seed=3).positions
    outs = []
    for device in ("cpu", "cuda"):
        stream = StreamConfig(window=60, steps=2, incremental=False, precision="float32")
        stage = ReactorStage(30.0, None, stream, device=device)
        frames = []
        for i, pos in enumerate(leader):
            frames += stage.push_many([ActorFrame(i, pos, i / 30.0)])
        frames += stage.flush(len(leader) / 30.0, len(leader) - 1)
        outs.append(np.stack([f.positions for f in frames]))
    cpu, gpu = outs
    assert cpu.shape == gpu.shape and cpu.shape[0] == len(leader)
    assert np.abs(cpu - gpu).max() < 2e-3  # metres: the same partner up to float rounding
