"""Issue 28's speed changes compute what the code before them computed, and old checkpoints load."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import save_file
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from dualflow.checkpoint import load_checkpoint, load_model
from dualflow.errors import DualFlowError
from dualflow.losses import triplet_loss
from dualflow.model import N_ADA, Conditions, DualFlow, DualFlowConfig
from dualflow.train import ema_update, load_train_config, train


def _random_model(seed: int = 0, **over) -> DualFlow:
    torch.manual_seed(seed)
    model = DualFlow(DualFlowConfig.preset("tiny", **over)).eval()
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.startswith(("out_a", "out_b")) or ".modulation." in name:
                p.normal_(0.0, 0.2)
    return model


def _split(state: dict) -> dict:
    """The same weights in the layout before the fused modulation: five linears per block."""
    old = {}
    for key, value in state.items():
        if key.endswith(("modulation.weight", "modulation.bias")) and ".norms." not in key:
            prefix, name = key.rsplit("modulation.", 1)
            for k, part in enumerate(value.chunk(N_ADA, 0)):
                old[f"{prefix}norms.{k}.modulation.{name}"] = part.clone()
        else:
            old[key] = value
    return old


def test_weights_of_five_separate_modulations_load_into_the_fused_one():
    model = _random_model()
    old = _split(model.state_dict())
    assert not any(k.endswith(".modulation.weight") and ".norms." not in k for k in old)
    again = DualFlow(model.config).eval()
    again.load_state_dict(old)  # the block's load hook stacks them
    x = torch.randn(2, 12, 262)
    for mode in ("interactive", "reactive"):
        with torch.no_grad():
            want = model(x, x.flip(1), 0.3, mode=mode)
            got = again(x, x.flip(1), 0.3, mode=mode)
        for a, b in zip(want, got):
            torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_an_old_checkpoint_directory_loads_and_an_old_training_run_says_how_to_go_on(tmp_path):
    run = train(
        load_train_config(
            None,
            [
                "preset=tiny",
                "data.n_clips=8",
                "data.val_clips=0",
                "data.frames=16",
                "batch_size=4",
                "threads=1",
                "progress=false",
                "ckpt_every=0",
                "steps=2",
                f"out_dir={tmp_path / 'run'}",
            ],
        )
    )
    final = run.final_checkpoint
    model, ckpt = load_model(final)
    assert not ckpt.converted
    save_file(_split({k: v.contiguous() for k, v in ckpt.state_dict.items()}), str(final / "model.safetensors"))
    old_model, old = load_model(final)
    assert old.converted
    x = torch.randn(1, 16, 262)
    with torch.no_grad():
        torch.testing.assert_close(old_model(x, x, 0.5, mode="reactive")[1], model(x, x, 0.5, mode="reactive")[1])
    step_dir = sorted((tmp_path / "run" / "checkpoints").glob("step_*"))[-1]
    state = load_checkpoint(step_dir).state_dict
    save_file(_split({k: v.contiguous() for k, v in state.items()}), str(step_dir / "model.safetensors"))
    with pytest.raises(DualFlowError, match="init_from"):
        load_checkpoint(step_dir, resume=True)
    assert json.loads((final / "config.json").read_text())["format"] == "dualflow-checkpoint"


def test_causal_self_attention_without_a_mask_tensor_equals_the_boolean_mask():
    model = _random_model(1)
    x = torch.randn(2, 14, 262)
    with torch.no_grad():
        fast = model(x, x.flip(1), 0.6, mode="reactive")[1]  # no frame mask: SDPA is_causal
        masked = model(x, x.flip(1), 0.6, mode="reactive", frame_mask=torch.ones(2, 14, dtype=torch.bool))[1]
    torch.testing.assert_close(fast, masked, rtol=1e-5, atol=1e-5)


def test_triplet_loss_is_the_mean_over_valid_triplets_and_zero_without_any():
    torch.manual_seed(0)
    v = torch.randn(6, 5, 3, requires_grad=True)
    labels = torch.tensor([0, 0, 1, 1, 2, 0])
    flat = torch.nn.functional.normalize(v.reshape(6, -1), dim=-1)
    dist = 1 - flat @ flat.T
    terms = [
        torch.relu(dist[i, p] - dist[i, n] + 0.2)
        for i in range(6)
        for p in range(6)
        for n in range(6)
        if p != i and labels[p] == labels[i] and labels[n] != labels[i]
    ]
    torch.testing.assert_close(triplet_loss(v, labels=labels), torch.stack(terms).mean())
    none = triplet_loss(v, labels=torch.arange(6))  # no positives
    assert none.item() == 0.0 and none.requires_grad


def test_ema_update_matches_averaged_model():
    model = _random_model(2)
    a = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(0.9), use_buffers=True)
    b = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(0.9), use_buffers=True)
    for _ in range(3):
        with torch.no_grad():
            for p in model.parameters():
                p.add_(torch.randn_like(p))
        a.update_parameters(model)
        ema_update(b, model, 0.9)
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        torch.testing.assert_close(x, y, rtol=0, atol=0, msg=name)


def test_train_step_without_sync_keeps_tensors_and_logs_the_same_numbers(tmp_path):
    from dualflow.train import Trainer

    args = [
        "preset=tiny",
        "data.n_clips=8",
        "data.val_clips=0",
        "data.frames=16",
        "batch_size=4",
        "threads=1",
        "progress=false",
    ]
    one = Trainer(load_train_config(None, args + [f"out_dir={tmp_path / 'a'}"]))
    two = Trainer(load_train_config(None, args + [f"out_dir={tmp_path / 'b'}"]))
    for _ in range(3):
        synced = one.train_step()
        raw = two.train_step(sync=False)
        assert torch.is_tensor(raw["loss"]) and torch.is_tensor(raw["grad_norm"])
        assert two.row_values(raw) == synced
    assert not one.model.music_in.weight.requires_grad  # music "none": its encoder is frozen


def test_compiled_blocks_share_their_graphs_and_compute_the_same():
    torch._dynamo.reset()
    from torch._dynamo.utils import counters

    from dualflow.compile import compile_blocks

    graphs = []
    for n_blocks in (2, 4):
        torch._dynamo.reset()
        counters.clear()
        model = _random_model(3, n_blocks=n_blocks)
        x = torch.randn(1, 10, 262)
        cond = Conditions(text=torch.randn(1, model.config.text_dim))
        with torch.no_grad():
            want = model(x, x, 0.4, cond, mode="reactive")[1]
            compile_blocks(model, backend="eager")
            got = model(x, x, 0.4, cond, mode="reactive")[1]
        torch.testing.assert_close(got, want)
        assert sum(counters["graph_break"].values()) == 0
        graphs.append(counters["stats"]["unique_graphs"])
    assert graphs[0] == graphs[1]  # twice the blocks, no more graphs: one compile serves every block
    torch._dynamo.reset()


@pytest.mark.parametrize("causal", [False, True])
def test_convolutions_as_matrix_products_equal_conv1d_values_and_gradients(causal):
    """MultiScaleConv(gemm=True), the CUDA default, computes what Conv1d computes: centred and
    causal padding, a frame mask, and the gradients of the input, weights, biases and gates."""
    from dualflow.model import MultiScaleConv

    torch.manual_seed(1)
    conv = MultiScaleConv(12, (3, 7, 11), 0.0)
    z = torch.randn(2, 17, 12)  # fewer frames than the largest kernel's reach on both sides
    mask = (torch.rand(2, 17) > 0.3).float()
    results = []
    for gemm in (False, True):
        conv.gemm = gemm
        conv.zero_grad()
        x = z.clone().requires_grad_(True)
        y = conv(x, causal=causal, frame_mask=mask)
        (y * torch.linspace(-1, 1, 12)).sum().backward()
        grads = [x.grad] + [p.grad.clone() for p in conv.parameters()]
        results.append((y.detach(), grads))
    (y0, g0), (y1, g1) = results
    torch.testing.assert_close(y1, y0, atol=1e-5, rtol=1e-5)
    for a, b in zip(g1, g0):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)
    if causal:  # frame i must not see later frames on the matrix-product path either
        conv.gemm = True
        late = z.clone()
        late[:, 9:] += 5.0
        torch.testing.assert_close(conv(late, True, None)[:, :9], conv(z, True, None)[:, :9])


def test_graphed_velocity_off_the_gpu_calls_the_function_and_says_why():
    from dualflow.cuda_graph import GraphedVelocity
    from dualflow.flow import SamplingSettings, generate

    calls = []

    def velocity(x, t):
        calls.append(t[0].item())
        return -x

    graphed = GraphedVelocity(velocity)
    x = torch.ones(1, 3, 4)
    torch.testing.assert_close(graphed(x, torch.zeros(1)), -x)
    assert calls == [0.0] and graphed.graph is None and "not a CUDA device" in graphed.eager_reason
    model = _random_model(4)
    actor = torch.randn(1, 12, 262)
    on = generate(model, 12, mode="reactive", x_actor=actor, sampling=SamplingSettings(steps=3, cuda_graph=True))[1]
    off = generate(model, 12, mode="reactive", x_actor=actor, sampling=SamplingSettings(steps=3, cuda_graph=False))[1]
    torch.testing.assert_close(on, off)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (CUDA graphs)")
def test_graphed_generation_on_cuda_equals_eager_and_rejects_another_shape():
    from dualflow.cuda_graph import GraphedVelocity
    from dualflow.flow import SamplingSettings, generate

    model = _random_model(5).cuda()
    actor = torch.randn(1, 40, 262, device="cuda")
    cond = Conditions(text=torch.randn(1, model.config.text_dim, device="cuda"))
    runs = [
        generate(model, 40, cond, mode="reactive", x_actor=actor, sampling=SamplingSettings(steps=4, cuda_graph=g))[1]
        for g in (False, True)
    ]
    torch.testing.assert_close(runs[1], runs[0], atol=1e-5, rtol=1e-5)
    graphed = GraphedVelocity(lambda x, t: x * t[:, None, None])
    graphed(torch.ones(2, 3, 4, device="cuda"), torch.full((2,), 0.5, device="cuda"))
    assert graphed.graph is not None
    with pytest.raises(DualFlowError, match="differs from the captured"):
        graphed(torch.ones(2, 5, 4, device="cuda"), torch.full((2,), 0.5, device="cuda"))


def test_sampling_precision_changes_nothing_off_the_gpu_and_is_checked():
    from dualflow.flow import SamplingSettings, generate

    model = _random_model(4)
    actor = torch.randn(1, 12, 262)
    runs = [
        generate(model, 12, mode="reactive", x_actor=actor, sampling=SamplingSettings(steps=3, precision=p))[1]
        for p in ("float32", "tf32", "bf16")
    ]
    assert all(torch.equal(runs[0], r) and r.dtype == torch.float32 for r in runs[1:])
    with pytest.raises(DualFlowError, match="precision must be one of"):
        SamplingSettings(precision="fp16")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (bf16 autocast, CUDA graphs)")
def test_reduced_precision_sampling_on_cuda_keeps_the_state_in_float32_and_graphs_it():
    from dualflow.flow import SamplingSettings, generate

    model = _random_model(5).cuda()
    with torch.no_grad():  # the output head starts at zero: give the velocity something to say
        torch.nn.init.normal_(model.out_b.weight, std=0.05)
    actor = torch.randn(1, 40, 262, device="cuda")
    cond = Conditions(text=torch.randn(1, model.config.text_dim, device="cuda"))

    def run(graph, precision):
        s = SamplingSettings(steps=4, cuda_graph=graph, precision=precision)
        return generate(model, 40, cond, mode="reactive", x_actor=actor, sampling=s)[1]

    tf32_before = torch.backends.cuda.matmul.allow_tf32
    fp32 = run(False, "float32")
    for precision, limit in (("bf16", 0.05), ("tf32", 0.01)):
        eager, graphed = run(False, precision), run(True, precision)
        assert graphed.dtype == torch.float32
        torch.testing.assert_close(graphed, eager, atol=1e-5, rtol=1e-5)  # the same kernels, replayed
        diff = (eager - fp32).abs().max().item()
        assert 0 < diff < limit * fp32.abs().max().item(), precision  # rounding: changed, only a little
    assert torch.backends.cuda.matmul.allow_tf32 == tf32_before  # the switch is put back


@pytest.mark.parametrize("masked", [False, True])
def test_reactive_pass_with_both_streams_stacked_equals_actor_context_then_reactor(masked):
    """Training's reactive forward (no actor_context: the actor and reactor streams stacked along
    the batch, block by block) gives what the sampler's two passes give, with and without a
    frame mask, music and retrieval tokens; and its gradients reach the actor's input projection."""
    model = _random_model(6)
    b, n = 3, 14
    torch.manual_seed(7)
    x_a, x_b = torch.randn(b, n, 262), torch.randn(b, n, 262)
    frame_mask = None
    if masked:
        frame_mask = torch.ones(b, n, dtype=torch.bool)
        frame_mask[1, 10:] = False
    cond = Conditions(
        text=torch.randn(b, model.config.text_dim),
        music=torch.randn(b, n, model.config.music_dim),
        retrieval=torch.randn(b, 4, model.config.width),
    )
    t = torch.rand(b)
    with torch.no_grad():
        context = model.actor_context(x_a, cond, frame_mask=frame_mask)
        want = model(x_a, x_b, t, cond, mode="reactive", frame_mask=frame_mask, actor_context=context)[1]
    got = model(x_a, x_b, t, cond, mode="reactive", frame_mask=frame_mask)[1]
    torch.testing.assert_close(got, want, atol=2e-5, rtol=2e-5)
    got.square().sum().backward()
    assert model.in_a.weight.grad is not None and model.in_a.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("gemm", [False, True])
@pytest.mark.parametrize("music", [False, True])
@pytest.mark.parametrize("mode", ["interactive", "reactive"])
def test_inference_shortcuts_compute_what_the_full_network_does(mode, music, gemm):
    """In inference (eval, no autograd) a cross-attention to a single key (the null music and
    retrieval tokens) is that key's constant output, the convolutions' tap-major weights are
    kept between calls, the modulated norms and the gated convolution sums are fused
    multiply-adds, and a reactive actor context carries its conditioning latents and the music
    and motion keys projected once: each must equal the full computation that runs with
    autograd on."""
    model = _random_model(6)
    for block in model.blocks:
        block.conv.gemm = gemm
    x_a, x_b = torch.randn(2, 1, 14, 262).unbind(0)
    cond = Conditions(  # no retrieval (a single null key), music or its null key
        text=torch.randn(1, model.config.text_dim),
        music=torch.randn(1, 14, model.config.music_dim) if music else None,
    )
    context = model.actor_context(x_a, cond) if mode == "reactive" else None
    assert mode == "interactive" or (context.cues is not None and (context.projected[0][0] is not None) == music)
    want = model(x_a, x_b, 0.4, cond, mode=mode)
    with torch.no_grad():
        got = model(x_a, x_b, 0.4, cond, mode=mode, actor_context=context)
        if mode == "reactive":  # the actor stream's own shortcuts: its context built in inference
            inferred = model(x_a, x_b, 0.4, cond, mode=mode, actor_context=model.actor_context(x_a, cond))
            torch.testing.assert_close(inferred[1], want[1], atol=1e-5, rtol=1e-5)
        conv = model.blocks[0].conv
        assert (conv._tap_major[0] is not None) == gemm  # kept for the next call
        conv.convs[0].weight.mul_(1.5)  # an in-place change of the weights must not reuse it
        changed = model(x_a, x_b, 0.4, cond, mode=mode, actor_context=context)
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, atol=1e-5, rtol=1e-5)
    with torch.enable_grad():
        want_changed = model(x_a, x_b, 0.4, cond, mode=mode, actor_context=context)
    torch.testing.assert_close(changed[1], want_changed[1], atol=1e-5, rtol=1e-5)
    assert not torch.allclose(changed[1], got[1])
    model.eval()  # a CUDA graph may hold the kept copy: eval() must not free it
    assert (conv._tap_major[0] is not None) == gemm
    model.train()
    assert all(entry is None for block in model.blocks for entry in block.conv._tap_major)


def test_single_key_attention_is_the_key_value_through_the_output():
    from dualflow.model import Attention

    torch.manual_seed(3)
    attn = Attention(16, 4, 0.0).eval()
    key = torch.randn(2, 1, 16)
    query = torch.randn(2, 5, 16)
    full = attn(query, key, None)
    torch.testing.assert_close(attn.single_key(key).expand_as(full), full)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (CUDA graphs)")
@pytest.mark.parametrize("music", [False, True])
def test_streamed_full_windows_replayed_from_a_graph_equal_the_eager_stream(music):
    from dualflow.streaming import ReactiveStreamer, StreamConfig

    model = _random_model(7).cuda()
    n = 40
    cond = Conditions(
        text=torch.randn(1, model.config.text_dim, device="cuda"),
        music=torch.randn(1, n, model.config.music_dim, device="cuda") if music else None,
    )
    actor = torch.randn(n, 262, device="cuda")
    streams = []
    for graph in (False, True):
        config = StreamConfig(window=16, steps=3, cuda_graph=graph, precision="float32")
        streamer = ReactiveStreamer(model, config, cond)
        for i in range(n):
            streamer.push(actor[i])
        streamer.flush()
        streams.append((streamer.emitted, streamer._graphs))
    (eager, no_graphs), (replayed, graphs) = streams
    captured = [g for g in graphs.values() if g is not None]
    assert not no_graphs and len(captured) == 1  # the steady full window; the last one's shape ran once
    assert captured[0].graph is not None
    assert replayed.shape == eager.shape == (n, 262)
    torch.testing.assert_close(replayed, eager, atol=1e-5, rtol=1e-5)


def test_an_actor_context_reuses_its_latents_only_for_its_own_conditions():
    """A context built with other conditions (e.g. the guidance's null) still reads its actor
    keys, as before, but the reactor's text, music and retrieval latents come from the
    conditions given, not from the context."""
    from dualflow.model import ActorContext

    model = _random_model(8)
    x_a, x_b = torch.randn(2, 1, 12, 262).unbind(0)
    cond_a = Conditions(text=torch.randn(1, model.config.text_dim), music=torch.randn(1, 12, model.config.music_dim))
    cond_b = Conditions(text=torch.randn(1, model.config.text_dim))
    with torch.no_grad():
        context = model.actor_context(x_a, cond_a)
        bare = ActorContext(keys=context.keys, shape=context.shape)  # the context as it was: keys only
        got = model(x_a, x_b, 0.3, cond_b, mode="reactive", actor_context=context)[1]
        want = model(x_a, x_b, 0.3, cond_b, mode="reactive", actor_context=bare)[1]
        own = model(x_a, x_b, 0.3, cond_a, mode="reactive", actor_context=context)[1]
    torch.testing.assert_close(got, want)
    assert not torch.allclose(got, own)
