"""The card's Triton kernels (`nbvh_core/kernels/triton/`) against the reference torch path: the hash-grid lookup
and its backward, the whole-MLP kernel, and a model's query with both in place. Without a GPU they run in Triton's
interpreter on CPU tensors (TRITON_INTERPRET=1, set by conftest.py before Triton is imported); on a card, on CUDA
tensors. Tolerances: lookup and gradients 1e-5 (float32 rounding; the backward's atomics add in another order),
query: identical hits, t within 1e-3, normals within 1e-2 (the issue's bar; on a card tl.dot is TF32)."""
from __future__ import annotations

import importlib

import pytest
import torch

pytest.importorskip("triton")

from nbvh_core import kernels  # noqa: E402
from nbvh_core.geometry.bvh import build_bvh  # noqa: E402
from nbvh_core.neural.encodings.base import EncodingConfig, vertex_resolution  # noqa: E402
from nbvh_core.neural.model import ModelConfig, NeuralBVH  # noqa: E402
from nbvh_core.neural.networks import NetworkConfig, _mlp, run_layers  # noqa: E402

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
kernel_plan = importlib.import_module("nbvh_core.kernels.plan")  # the module (the package exports its `plan` function)


@pytest.fixture
def triton_here(monkeypatch):
    """The plan's choice for the card, made for this device (the CPU runs the kernels in the interpreter)."""
    monkeypatch.setattr(kernel_plan, "triton_serves",
                        lambda device: kernels.current_path() == "fast" and torch.device(device).type == DEVICE)


def _grid(log2_table: int, features: int = 16, levels: int = 4):
    from nbvh_core.neural.encodings.hashgrid import HashGrid

    torch.manual_seed(0)
    enc = HashGrid(EncodingConfig(kind="hashgrid", log2_table=log2_table, levels=levels, features=features))
    with torch.no_grad():
        enc.table.uniform_(-1, 1)
    return enc.to(DEVICE)


@pytest.mark.parametrize("log2_table,features", [(10, 16), (13, 16), (8, 4)],
                         ids=["hashed-levels", "dense-coarse-levels", "4-features"])
def test_the_grid_lookup_and_its_backward_match_the_reference(log2_table, features):
    from nbvh_core.kernels.triton.hashgrid import grid_encode, level_geometry

    enc = _grid(log2_table, features)
    dense = [vertex_resolution(s) ** 3 <= enc.cfg.table_size for s in enc.scales]
    assert any(dense) == (log2_table == 13) and not all(dense)  # both kinds of level are covered by the cases
    points = torch.rand(333, 3, device=DEVICE) * 1.1 - 0.05  # a few outside the box: clamped, as the reference does
    want = enc.reference_forward(points)
    table = enc.table.detach().clone().requires_grad_(True)
    geometry = level_geometry(enc.scales, [vertex_resolution(s) for s in enc.scales], enc.cfg.table_size, DEVICE)
    got = grid_encode(points, table, geometry)
    assert torch.allclose(got, want, atol=1e-5, rtol=0), (got - want).abs().max()
    grad = torch.randn_like(got)
    got.backward(grad)
    want.backward(grad)
    assert torch.allclose(table.grad, enc.table.grad, atol=1e-5, rtol=0), (table.grad - enc.table.grad).abs().max()


def _vqad(frozen: bool, quantized: bool = False):
    """A small HashVQAD (coarse levels dense in the index, fine ones hashed) with random rows and logits."""
    from nbvh_core.neural.encodings.hashvqad import HashVQAD

    torch.manual_seed(2)
    enc = HashVQAD(EncodingConfig(kind="hashvqad", log2_table=6, levels=4, features=8, index_factor=8,
                                  candidates=4, n_min=4, n_max=48))
    with torch.no_grad():
        enc.table.uniform_(-1, 1)
        enc.logits.normal_()
    enc.temperature = 0.5
    if frozen:
        enc.freeze()
    if quantized:
        enc.quantize_(8)
    return enc.to(DEVICE)


@pytest.mark.parametrize("form", ["soft", "frozen", "frozen-stored"])
def test_hashvqad_s_lookup_and_its_backward_match_the_reference(form, triton_here):
    """HashVQAD through the Triton lookup: while soft, its soft row table read by vertex (the gradient reaching the
    logits and the rows through torch); frozen, each vertex's row through its packed code inside the kernel (the
    fine-tune's table gradient by atomics); stored, the rows as uint8 codes too."""
    enc = _vqad(frozen=form != "soft", quantized=form == "frozen-stored")
    dense = [vertex_resolution(s) ** 3 <= enc.cfg.index_size for s in enc.scales]
    assert any(dense) and not all(dense)
    assert kernels.encoding_kernel(enc, DEVICE) == ("triton u8" if form == "frozen-stored" else "triton f32")
    points = torch.rand(300, 3, device=DEVICE) * 1.1 - 0.05
    if form == "frozen-stored":
        with torch.no_grad():
            got, want = enc(points), enc.reference_forward(points)
        assert torch.allclose(got, want, atol=1e-5, rtol=0), (got - want).abs().max()
        return
    got = enc(points)
    grad = torch.randn_like(got)
    params = [p for p in (enc.table, enc.logits) if p is not None]
    got_grads = torch.autograd.grad(got, params, grad)
    want = enc.reference_forward(points)
    want_grads = torch.autograd.grad(want, params, grad)
    assert torch.allclose(got, want, atol=1e-5, rtol=0), (got - want).abs().max()
    for g, w in zip(got_grads, want_grads):
        assert w.abs().max() > 0 and torch.allclose(g, w, atol=1e-5, rtol=0), (g - w).abs().max()


@pytest.mark.parametrize("bits", [8, 6])
def test_a_shipped_table_s_codes_are_read_as_they_are_held(bits, triton_here):
    """A table held as a file stores it (uint8 codes with per (level, feature) offset and scale; 6-bit codes are
    the default preset's): the encoding's forward runs the Triton kernel on the codes and matches the reference's
    dequantized lookup."""
    enc = _grid(11, 4, levels=10)  # the default preset's grid: 10 levels of 4 features, T = 2^11
    enc.quantize_(bits)
    assert kernels.encoding_kernel(enc, DEVICE) == "triton u8"
    points = torch.rand(257, 3, device=DEVICE)
    with torch.no_grad():
        got = enc(points)
        want = enc.reference_forward(points)
    assert torch.allclose(got, want, atol=1e-5, rtol=0), (got - want).abs().max()


@pytest.mark.parametrize("kind,n_in,width,weights,n_out", [("kmlp", 128, 64, "f32", 5), ("mlp", 512, 64, "f32", 5),
                                                           ("mlp", 100, 32, "f16", 5), ("kmlp", 40, 16, "f32", 5),
                                                           ("mlp", 24, 32, "f32", 40)])
def test_the_mlp_kernel_matches_torch_s_layers(kind, n_in, width, weights, n_out):
    from nbvh_core.kernels.triton.mlp import mlp_forward, pack_mlp
    from nbvh_core.neural.networks import linear_weight

    torch.manual_seed(1)
    net = _mlp(n_in, NetworkConfig(kind=kind, width=width), n_out).to(DEVICE)  # 40: an appearance head's outputs
    if weights == "f16":  # held as a file stores it: the kernel reads the same float16 values, cast once
        net = net.half()
    x = torch.randn(77, n_in, device=DEVICE)  # not a multiple of the 32-row tile
    with torch.no_grad():
        want = run_layers(net, x)
        got = mlp_forward(x, pack_mlp(net, lambda m: linear_weight(m, torch.float32)))
    tol = 1e-5 if DEVICE == "cpu" else 2e-3 * want.abs().max().item()  # TF32 on a card
    assert got.shape == want.shape and torch.allclose(got, want, atol=tol, rtol=0), (got - want).abs().max()


@pytest.mark.parametrize("kind,n_in,width,hidden,n_out", [("kmlp", 128, 64, 4, 5), ("mlp", 100, 32, 3, 5),
                                                            ("mlp", 40, 16, 1, 5), ("mlp", 24, 32, 2, 40)],
                         ids=["kmlp-default-width", "mlp-padded-input", "one-hidden-layer", "head-40-outputs"])
def test_the_mlp_training_kernels_give_torch_s_outputs_and_gradients(kind, n_in, width, hidden, n_out):
    """The training pass (`mlp_train_forward`: the forward kernel storing activations, the backward kernel, one matmul
    per layer for the weights) against torch's autograd over the same layers: output and every gradient (the input's
    and each weight's and bias's) within 1e-5 of the largest (float32 here; TF32 on a card: 5e-3)."""
    from nbvh_core.kernels.triton.mlp import mlp_train_forward

    torch.manual_seed(2)
    net = _mlp(n_in, NetworkConfig(kind=kind, width=width, hidden=hidden), n_out).to(DEVICE)
    x = torch.randn(77, n_in, device=DEVICE, requires_grad=True)  # not a multiple of the 32-row tile
    grad = torch.randn(77, n_out, device=DEVICE)  # 40: an appearance head's patches, padded to 64 columns
    got = mlp_train_forward(x, net)
    got_grads = torch.autograd.grad(got, [x, *net.parameters()], grad)
    want = net(x)
    want_grads = torch.autograd.grad(want, [x, *net.parameters()], grad)
    rel = 1e-5 if DEVICE == "cpu" else 5e-3
    assert torch.allclose(got, want, atol=rel * want.abs().max().item(), rtol=0), (got - want).abs().max()
    for name, g, w in zip(["x", *(n for n, _ in net.named_parameters())], got_grads, want_grads):
        assert g.shape == w.shape and torch.allclose(g, w, atol=rel * w.abs().max().item(), rtol=0), \
            (name, float((g - w).abs().max()), float(w.abs().max()))


@pytest.mark.parametrize("network", ["mlp", "kmlp"])
def test_a_training_step_on_the_card_runs_its_layers_in_triton_with_autograd_s_gradients(network, sample_meshes,
                                                                                         triton_here, monkeypatch):
    """The plan's training step on a card: torch's autograd over the stages, the layers' forward and backward the
    Triton MLP's; loss and every parameter's gradient (the table's through the lookup's backward included) as
    NBVH_CARD_TRAINING_LAYERS=torch (cuBLAS layers) gives them."""
    from nbvh_core.geometry.exact import ExactTracer
    from nbvh_core.training.rays import label_samples, root_box, sample_rays
    from nbvh_core.training.train import samples_loss
    import numpy as np

    mesh = sample_meshes["blob"]
    bvh = build_bvh(mesh, 15)
    torch.manual_seed(0)
    model = NeuralBVH(bvh.nodes, ModelConfig(EncodingConfig(kind="hashgrid", log2_table=8, levels=2, features=8),
                                             NetworkConfig(kind=network, k=4, hidden=2, width=32))).to(DEVICE)
    o, d = sample_rays(*root_box(bvh), 200, np.random.default_rng(3))
    batch = label_samples(bvh, ExactTracer(mesh), o, d, "consistent")

    def step() -> tuple[float, dict]:
        model.zero_grad(set_to_none=True)
        loss, _ = samples_loss(model, batch, torch.device(DEVICE))
        loss.backward()
        return float(loss), {n: p.grad.clone() for n, p in model.named_parameters()}

    assert kernels.plan(model, DEVICE).train_step == "autograd, triton layers"
    got_loss, got = step()
    monkeypatch.setenv(kernel_plan.TRAINING_LAYERS_ENV, "torch")
    assert kernels.plan(model, DEVICE).train_step == "autograd"
    want_loss, want = step()
    rel = 1e-5 if DEVICE == "cpu" else 5e-3
    assert got_loss == pytest.approx(want_loss, rel=rel)
    for name, g in got.items():
        scale = float(want[name].abs().max().clamp_min(1e-8))
        assert torch.allclose(g, want[name], atol=rel * scale, rtol=0), (name, float((g - want[name]).abs().max()))


def test_a_shape_the_mlp_kernel_does_not_take_is_refused_and_left_to_torch():
    from nbvh_core.kernels.triton.mlp import pack_mlp

    net = _mlp(32, NetworkConfig(kind="mlp", width=24))
    with pytest.raises(ValueError, match="power of two"):
        pack_mlp(net)
    assert "hidden widths [24, 24, 24, 24]" in kernel_plan.triton_network_gap(net)


def _query_model(mesh, network: str, nodes: int, features: int, levels: int, k: int, encoding: str = "hashgrid"):
    """A small model whose hit logit varies widely around its median, so that some rays hit and some miss."""
    torch.manual_seed(0)
    grid = dict(kind="hashgrid", log2_table=9) if encoding == "hashgrid" else dict(
        kind="hashvqad", log2_table=7, index_factor=16, candidates=4)
    cfg = ModelConfig(EncodingConfig(levels=levels, features=features, **grid),
                      NetworkConfig(kind=network, k=k, hidden=2, width=32))
    model = NeuralBVH(build_bvh(mesh, nodes).nodes, cfg).eval().to(DEVICE)
    with torch.no_grad():
        model.encoding.table.normal_()
        if encoding == "hashvqad":
            model.encoding.logits.normal_()
            model.encoding.freeze()
        last = [m for m in model.network.net if isinstance(m, torch.nn.Linear)][-1]
        last.weight[0] *= 30.0
        last.bias[0] = 0.0
        probe = torch.rand(256, cfg.network.k, 3, device=DEVICE)
        feats = model.encoding(probe.reshape(-1, 3)).reshape(256, cfg.network.k, -1)
        last.bias[0] = -model.network(feats)[..., 0].median() - (0.0 if network == "mlp" else 1.0)
    return model


def _rays(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    o = torch.rand(n, 3, generator=g) * 0.2 + torch.tensor([0.4, 0.4, -1.0])
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 1.0]), dim=1)
    d[0] = torch.tensor([0.0, 0.0, 1.0])  # axis-parallel: zero direction components, inf in the slab test
    return o.to(DEVICE), d.to(DEVICE)


@pytest.mark.parametrize("network,nodes,features,levels,k,stored,encoding", [
    ("mlp", 7, 16, 2, 4, False, "hashgrid"), ("kmlp", 7, 16, 2, 4, False, "hashgrid"),
    ("mlp", 63, 4, 10, 4, True, "hashgrid"),  # the default preset's shape, held as its file stores it
    ("kmlp", 255, 8, 3, 5, True, "hashgrid"),
    ("kmlp", 15, 4, 4, 3, False, "hashvqad"), ("mlp", 15, 8, 2, 4, True, "hashvqad")],
    ids=["mlp", "kmlp", "default-shape-stored", "kmlp-deep-tree-stored", "hashvqad-kmlp", "hashvqad-mlp-stored"])
def test_a_model_s_query_is_one_triton_kernel_matching_the_reference(network, nodes, features, levels, k, stored,
                                                                     encoding, sample_meshes, triton_here,
                                                                     monkeypatch):
    """The plan runs the whole query as the Triton ray-query kernel; its hits are identical, t within 1e-3 and
    normals within 1e-2 of the reference path's, and it evaluates the same segments (same order, stop at the first
    hit). Stored: the table as 6-bit codes, the network as int8 rows, the nodes in the 8-bit format. On a card the
    products are float32 here (TF32 may decide a logit within ~1e-3 of its threshold otherwise: bench_speed
    records the agreement at TF32)."""
    from nbvh_core.kernels.triton import ray_query
    from nbvh_core.neural.quantize import StorageConfig

    monkeypatch.setattr(ray_query, "PRECISION", "ieee")

    model = _query_model(sample_meshes["blob"], network, nodes, features, levels, k, encoding)
    if stored:
        model.finalize_storage(StorageConfig(table_bits=6, network_bits=8, node_bits=8))
    p = kernels.plan(model, DEVICE)
    assert p.query == "triton" and p.encoding == ("triton u8" if stored else "triton f32"), p
    o, d = _rays(96)
    got = model.query(o, d)
    with kernels.using_path("reference"):
        assert kernels.plan(model, DEVICE).query == "stream"
        want = model.query(o, d)
    assert 0 < int(want.hit.sum()) < len(o) and torch.equal(got.hit, want.hit)
    assert torch.allclose(got.t[want.hit], want.t[want.hit], atol=1e-3)
    assert torch.allclose(got.normal[want.hit], want.normal[want.hit], atol=1e-2)
    assert torch.isinf(got.t[~got.hit]).all() and not got.normal[~got.hit].any()
    assert got.leaves_evaluated == want.leaves_evaluated > len(o)


def test_the_appearance_head_s_query_runs_the_triton_lookup_and_layers(sample_meshes, triton_here):
    """A hit's look on the card: the head's grid (8-bit codes, as a file holds it) through the Triton lookup and its
    layers through the Triton MLP; the same patches and coordinates within 1e-4 as the reference path's."""
    from nbvh_core.neural.appearance import AppearanceConfig, AppearanceHead, finalize_head

    torch.manual_seed(3)
    head = AppearanceHead(AppearanceConfig(slots=2, patches=6, uv=True, patch_degree=1))
    with torch.no_grad():
        head.encoding.table.uniform_(-1, 1)
        head.affine.normal_()
        head.patch_slot.copy_(torch.tensor([0, 0, 1, 1, 0, 1]))
    finalize_head(head, table_bits=6, network_bits=8)
    model = _query_model(sample_meshes["blob"], "mlp", 7, 16, 2, 4)
    model.appearance = head.to(DEVICE)
    assert kernels.plan(model, DEVICE).appearance == "triton u8 lookup, triton layers"
    points = torch.rand(200, 3, device=DEVICE)
    slot, uv = head.predict(points)
    with kernels.using_path("reference"):
        assert kernels.plan(model, DEVICE).appearance == "torch lookup, torch layers"
        want_slot, want_uv = head.predict(points)
    assert len(set(want_slot.tolist())) == 2 and (slot == want_slot).all()
    assert abs(uv - want_uv).max() < 1e-4, abs(uv - want_uv).max()


def test_a_ray_query_kernel_that_fails_leaves_the_stream_path_answering_and_says_why(sample_meshes, triton_here,
                                                                                  monkeypatch):
    """A card or driver the kernel does not build for: the query warns once with the reason, the leaf stream answers
    (the reference path's hits), and the plan names the fallback."""
    from nbvh_core.kernels.triton import ray_query

    model = _query_model(sample_meshes["blob"], "mlp", 7, 16, 2, 4)
    assert kernels.plan(model, DEVICE).query == "triton"

    def broken(*args, **kwargs):
        raise RuntimeError("PTX .version 9.9 does not support .target sm_200\nmore lines")

    monkeypatch.setattr(ray_query, "first_hits", broken)
    o, d = _rays(64)
    with pytest.warns(RuntimeWarning, match="Triton ray query failed .*sm_200.*leaf stream answers"):
        got = model.query(o, d)
    with kernels.using_path("reference"):
        want = model.query(o, d)
    assert torch.equal(got.hit, want.hit) and torch.allclose(got.t[want.hit], want.t[want.hit], atol=1e-3)
    p = kernels.plan(model, DEVICE)
    assert p.query == "stream" and "ray query: the Triton ray query failed" in p.note, p


def test_the_ray_query_compiles_for_the_card_without_spilling(tmp_path):
    """The interpreter checks what the kernel computes, not that the card's compiler takes it: here Triton compiles
    it for sm_90a (the H100/H200) and its own ptxas assembles it, no card needed (bench/speed/kernel_registers.py). At the
    default preset's shape it must spill no register to local memory (224 registers recorded)."""
    import csv
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env["NBVH_BENCH_RESULTS"] = str(tmp_path)
    out = subprocess.run([sys.executable, "-m", "bench.speed.kernel_registers", "--cases", "1"], cwd=root, env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    with open(tmp_path / "kernel_registers.csv") as f:
        (row,) = list(csv.DictReader(f))
    assert row["kernel"] == "ray query mlp, u8 codes" and int(row["spill_store_bytes"]) == 0, row
    assert 128 <= int(row["registers"]) <= 255, row


def test_what_the_triton_kernels_do_not_cover_runs_torch_and_the_plan_says_why(sample_meshes, triton_here):
    cfg = ModelConfig(EncodingConfig(kind="hashvqad", log2_table=6, levels=2, features=6, index_factor=8,
                                     candidates=4), NetworkConfig(kind="kmlp", k=4, width=24))
    model = NeuralBVH(build_bvh(sample_meshes["blob"], 7).nodes, cfg).to(DEVICE)
    p = kernels.plan(model, DEVICE)
    assert p.encoding == "torch" and p.network == "torch" and p.train_step == "autograd"
    assert "rows of 6 float32 features" in p.note and "hidden widths" in p.note
    pts = torch.rand(50, 3, device=DEVICE)
    assert torch.equal(model.encoding(pts), model.encoding.reference_forward(pts))
