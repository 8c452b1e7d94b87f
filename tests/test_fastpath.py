"""The fast path (fused C++ kernels) and the reference path (pure torch) give the same answers.

Traversal is bit-identical (same float32 operations, no FMA); encodings agree to float rounding (the 8-corner sums
are added in another order); renders give the same hits, distances and normals; training follows the same loss
curve.
"""
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from nbvh_core import kernels
from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.neural.encodings import EncodingConfig, make_encoding
from nbvh_core.neural.model import ModelConfig, NeuralBVH
from nbvh_core.neural.networks import NetworkConfig
from nbvh_core.training.rays import root_box, sample_rays
from nbvh_core.training.train import TrainConfig, train
from nbvh_core.geometry.traversal import LeafStream, TorchBVH, leaves_along_rays


def test_kernels_build_here():
    # CI machines have g++: the fast path must really be the fused one there, not a silent fallback.
    assert kernels.load() is not None, kernels.describe()
    assert kernels.describe().startswith("fast")


ENCODINGS = [
    ("hashgrid", dict(log2_table=11, levels=4, features=16)),  # level 0 dense, levels 1-3 hashed
    ("hashgrid", dict(log2_table=5, levels=3, features=3, n_min=3, n_max=40)),  # odd F: generic kernel
    ("hashvqad", dict(log2_table=8, levels=2, features=4, index_factor=8, candidates=4)),
    # H = 128 T: level 0 dense, reaching 17^3 of its 8,192 entries (codes held for those only)
    ("hashvqad", dict(log2_table=6, levels=2, features=4, index_factor=128, candidates=4)),
]


@pytest.mark.parametrize("kind,kw", ENCODINGS)
def test_encoding_forward_and_backward_agree(kind, kw):
    torch.manual_seed(0)
    enc = make_encoding(EncodingConfig(kind=kind, **kw))
    with torch.no_grad():
        enc.table.normal_()
    pts = torch.rand(5000, 3) * 1.4 - 0.2  # includes points outside the unit box (clamped by both)
    grad = torch.randn(5000, enc.out_dim)
    results = {}
    for path in kernels.PATHS:
        with kernels.using_path(path):
            enc.zero_grad(set_to_none=True)
            out = enc(pts)
            out.backward(grad)
            results[path] = (out.detach(), {n: p.grad.clone() for n, p in enc.named_parameters()})
    (out_r, g_r), (out_f, g_f) = results["reference"], results["fast"]
    assert torch.allclose(out_f, out_r, rtol=1e-5, atol=1e-5)
    for name in g_r:
        assert torch.allclose(g_f[name], g_r[name], rtol=1e-4, atol=1e-5), name
    if kind == "hashvqad":  # frozen codes are looked up inside the kernel
        enc.freeze()
        with kernels.using_path("reference"):
            ref = enc(pts)
        assert torch.allclose(enc(pts), ref, rtol=1e-5, atol=1e-5)


@pytest.fixture(scope="module")
def bunny_rays(sample_meshes):
    bvh = build_bvh(sample_meshes["bunny"], 1023)
    lo, hi = root_box(bvh)
    o, d = sample_rays(lo, hi, 20000, np.random.default_rng(3))
    o, d = torch.from_numpy(o), torch.from_numpy(d)
    d[:500] = torch.tensor([0.0, 0.0, 1.0])  # axis-parallel rays: inf / NaN slabs
    d[500:1000] = torch.tensor([-1.0, 0.0, 0.0])
    return bvh, TorchBVH.from_bvh(bvh), o, d


def test_complete_leaf_lists_are_identical(bunny_rays):
    _, tree, o, d = bunny_rays
    t_max = torch.rand(o.shape[0]) * 1.5
    with kernels.using_path("reference"):
        a = leaves_along_rays(tree, o, d, t_max)
    b = leaves_along_rays(tree, o, d, t_max)
    for f in ("ray", "node", "leaf", "t_enter", "t_exit", "offsets"):
        assert torch.equal(getattr(a, f), getattr(b, f)), f


def _stream(tree, o, d):
    out = []
    st = LeafStream(tree, o, d)
    while True:
        ray, leaf, te, tx = st.next()
        if ray.numel() == 0:
            return out
        order = torch.argsort(ray)
        out.append(tuple(x[order] for x in (ray, leaf, te, tx)))
        st.stop(ray[leaf % 5 == 0])  # what a renderer does on hits...
        keep = leaf % 3 == 0
        st.shorten(ray[keep], (te[keep] + tx[keep]) / 2)  # ...and on a nearest-hit search


def test_leaf_streams_are_identical(bunny_rays):
    _, tree, o, d = bunny_rays
    with kernels.using_path("reference"):
        ref = _stream(tree, o, d)
    fast = _stream(tree, o, d)
    assert len(ref) == len(fast) > 3
    for wave_r, wave_f in zip(ref, fast):
        for x, y in zip(wave_r, wave_f):
            assert torch.equal(x, y)


@pytest.fixture(scope="module")
def blob_model(sample_meshes):
    from nbvh_core.geometry.exact import ExactTracer

    mesh = sample_meshes["blob"]
    bvh = build_bvh(mesh, 255)
    tracer = ExactTracer(mesh)
    cfg = ModelConfig(EncodingConfig(kind="hashgrid", log2_table=10, levels=4, features=8),
                      NetworkConfig(kind="mlp", k=8))
    return mesh, bvh, tracer, cfg


def test_training_follows_the_same_loss_curve_and_renders_the_same(blob_model):
    mesh, bvh, tracer, cfg = blob_model
    runs = {}
    for path in kernels.PATHS:
        with kernels.using_path(path):
            torch.manual_seed(0)
            model = NeuralBVH(bvh.nodes, cfg, mesh.transform)
            res = train(model, bvh, tracer, TrainConfig(steps=40, rays_per_step=1024, lr=5e-3, seed=1))
            runs[path] = (model.eval(), np.array([loss for _, loss in res.history]), res.compute_path)
    (_, loss_r, path_r), (m_f, loss_f, path_f) = runs["reference"], runs["fast"]
    assert path_r.startswith("reference") and path_f.startswith("fast")
    assert loss_f[-5:].mean() < 0.95 * loss_f[0]  # it trained (40 small steps: ~10% lower with facing targets)
    # Same data (same seed): only float rounding differs, so the curves stay together.
    assert np.max(np.abs(loss_f - loss_r) / loss_r) < 0.02, np.max(np.abs(loss_f - loss_r) / loss_r)
    # One model queried both ways: same hits, distances and normals.
    from nbvh_core.rendering.render import orbit_cameras

    o, d = (torch.from_numpy(a) for a in orbit_cameras(3)[1].rays(64, 64))
    with kernels.using_path("reference"):
        q_r = m_f.query(o, d)
    q_f = m_f.query(o, d)
    assert q_f.hit.sum() > 100
    assert (q_f.hit != q_r.hit).float().mean() < 1e-3  # a prob within rounding of 0.5 may flip
    both = q_f.hit & q_r.hit
    assert torch.allclose(q_f.t[both], q_r.t[both], atol=1e-4)
    assert torch.allclose(q_f.normal[both], q_r.normal[both], atol=1e-3)


def test_without_kernels_everything_runs_on_the_reference_path(tmp_path):
    code = ("from nbvh_core import kernels; import torch;"
            "from nbvh_core.neural.encodings import EncodingConfig, make_encoding;"
            "e = make_encoding(EncodingConfig(kind='hashgrid', log2_table=6, levels=2, features=4));"
            "print(kernels.describe(), e(torch.rand(10, 3)).shape)")
    env = dict(os.environ, NBVH_NO_KERNELS="1")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.startswith("reference (pure torch): fused kernels unavailable (disabled by NBVH_NO_KERNELS)")
    assert "torch.Size([10, 8])" in out


def test_float16_tables_give_the_same_image_within_rounding(blob_model):
    mesh, bvh, tracer, cfg = blob_model
    torch.manual_seed(0)
    model = NeuralBVH(bvh.nodes, cfg, mesh.transform)
    train(model, bvh, tracer, TrainConfig(steps=30, rays_per_step=1024, lr=5e-3, seed=2))
    model.eval()
    from nbvh_core.rendering.render import orbit_cameras

    o, d = (torch.from_numpy(a) for a in orbit_cameras(3)[2].rays(64, 64))
    q32 = model.query(o, d)
    model.half_tables = True
    q16 = model.query(o, d)
    model.half_tables = False
    assert (q16.hit != q32.hit).float().mean() < 5e-3
    both = q16.hit & q32.hit
    assert torch.allclose(q16.t[both], q32.t[both], atol=2e-3)
    # Training never uses the half copy (gradients need the float32 rows).
    model.half_tables = True
    model.train()
    out = model.encoding(torch.rand(10, 3))
    assert out.requires_grad
    model.half_tables = False


FUSED_MODELS = [
    # (encoding, network): the AVX2 paths (F % 8 == 0, width % 16 == 0) and the generic ones (odd F, width 24,
    # no hidden layer), a frozen HashVQAD (codes looked up in the kernel).
    (dict(kind="hashgrid", log2_table=11, levels=4, features=16), dict(kind="mlp", k=8)),
    (dict(kind="hashgrid", log2_table=5, levels=3, features=3, n_min=3, n_max=40), dict(kind="mlp", k=4, width=24)),
    (dict(kind="hashgrid", log2_table=6, levels=2, features=8), dict(kind="mlp", k=3, hidden=0)),
    (dict(kind="hashvqad", log2_table=8, levels=2, features=8, index_factor=8, candidates=4), dict(kind="mlp", k=6)),
    (dict(kind="hashvqad", log2_table=6, levels=2, features=8, index_factor=128, candidates=4), dict(kind="mlp", k=4)),
    # KMLP (the paper's network): pairs are windows of the segment's feature row, the combination in the kernel.
    (dict(kind="hashgrid", log2_table=11, levels=4, features=16), dict(kind="kmlp", k=8)),
    (dict(kind="hashgrid", log2_table=5, levels=3, features=3, n_min=3, n_max=40), dict(kind="kmlp", k=4, width=24)),
    (dict(kind="hashvqad", log2_table=8, levels=2, features=8, index_factor=8, candidates=4), dict(kind="kmlp", k=5)),
    (dict(kind="hashgrid", log2_table=6, levels=2, features=8), dict(kind="kmlp", k=2, hidden=0)),
]


@pytest.mark.parametrize("half", [False, True, "int8"], ids=["f32-weights", "f16-weights", "int8-weights"])
@pytest.mark.parametrize("enc_kw,net_kw", FUSED_MODELS)
def test_fused_inference_matches_the_layer_by_layer_network(enc_kw, net_kw, half, sample_meshes):
    torch.manual_seed(0)
    bvh_nodes = build_bvh(sample_meshes["blob"], 63).nodes
    model = NeuralBVH(bvh_nodes, ModelConfig(EncodingConfig(**enc_kw), NetworkConfig(**net_kw))).eval()
    with torch.no_grad():
        model.encoding.table.normal_()
    if enc_kw["kind"] == "hashvqad":
        model.encoding.freeze()
    n_rays, n_seg = 300, 1001  # not a multiple of the kernel's 48-segment tile
    o = torch.rand(n_rays, 3)
    d = torch.nn.functional.normalize(torch.randn(n_rays, 3), dim=1)
    ray = torch.randint(0, n_rays, (n_seg,))
    te = torch.rand(n_seg) * 0.5
    tx = te + torch.rand(n_seg) * 0.5
    _half_the_segments_hit(model, o, d, ray, te, tx)
    if half is True:  # the stored half-precision network, held as it is stored; the kernel reads float16 weights
        n_params = sum(p.numel() for p in model.network.parameters())
        model.hold_network_half()
        assert model.resident_bytes()["network"] == 2 * n_params
        assert kernels.plan(model).network.endswith("f16 weights") and kernels.plan(model).train_step == "autograd"
    elif half == "int8":  # int8 rows + float16 scales, held as a file stores them
        model.hold_network_int8()
        linears = [m for m in model.network.modules() if isinstance(m, torch.nn.Linear)]
        assert model.resident_bytes()["network"] == sum(m.in_features * m.out_features + 4 * m.out_features
                                                        for m in linears)
        assert kernels.plan(model).network.endswith("int8 weights")
    fused = model._fused_network()
    assert fused is not None
    with torch.no_grad():
        with kernels.using_path("reference"):
            want = model.forward(o[ray], d[ray], te, tx)
        got = model._fused_raw(fused, o, d, ray, te, tx)
    assert got.shape == want.shape
    # Absolute rounding per output on its own scale (the hit logit spread over a few units by the calibration).
    scale = want.abs().amax(dim=tuple(range(want.dim() - 1))).clamp_min(1.0)
    assert ((got - want).abs() <= 1e-4 * want.abs() + 1e-5 * scale).all(), (got - want).abs().max()
    _first_hits_decide_as_decode(model, want, o, d, ray, te, tx)
    # Rays in chunks give the same image as one stream.
    q_all = model.query(o, d)
    q_chunks = model.query(o, d, ray_chunk=64)
    assert q_all.leaves_evaluated > 0
    assert torch.equal(q_all.hit, q_chunks.hit) and q_all.leaves_evaluated == q_chunks.leaves_evaluated
    # Equal to the last bits for MLPs; KMLP's decode (torch's softplus/cumsum) may round differently by batch size.
    assert torch.allclose(q_all.t, q_chunks.t, rtol=1e-6, atol=1e-7)


def _half_the_segments_hit(model, o, d, ray, te, tx) -> None:
    """Scale and shift the hit logit's last row so that the logits spread over a few units (a KMLP's pairs then
    decide at different points) and the median hit probability is 0.5 (a random network mostly misses, or hits)."""
    last = [m for m in model.network.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad(), kernels.using_path("reference"):
        last.weight[0] *= 3.0 / float(model.forward(o[ray], d[ray], te, tx)[..., 0].std())
        centre = float(last.bias[0] - model.forward(o[ray], d[ray], te, tx)[..., 0].median())
        lo, hi = centre - 20.0, centre + 20.0
        for _ in range(20):  # bisection on the bias
            last.bias[0] = (lo + hi) / 2
            p_hit = model.network.decode(model.forward(o[ray], d[ray], te, tx))[0]
            lo, hi = ((lo + hi) / 2, hi) if p_hit.median() < 0.5 else (lo, (lo + hi) / 2)


def _first_hits_decide_as_decode(model, raw, o, d, ray, te, tx) -> None:
    """The queries' first hits (for a KMLP combined in the kernel, a decided segment's later pairs skipped) against
    `network.decode` of the reference raw outputs: the same hit decisions, depths and normals; the probability equal
    for misses and a lower bound > 0.5 for hits. Segments within rounding of a tie are left out."""
    with torch.no_grad():
        p_want, t_want, n_want = model.network.decode(raw)
        p_got, t_got, n_got = model._fused_first_hits(model._fused_network(), o, d, ray, te, tx)
    clear = (p_want - 0.5).abs() > 1e-4
    if raw.dim() == 3 and raw.shape[1] > 1:  # KMLP: and the most likely first-hit pair is clear
        log_q, _ = model.network._first_hit_log_probs(raw[..., 0])
        top = log_q.topk(2, dim=1).values
        clear &= (top[:, 0] - top[:, 1]) > 1e-4
    hit, miss = clear & (p_want > 0.5), clear & (p_want <= 0.5)
    assert hit.sum() > 20 and miss.sum() > 20  # both cases exercised
    assert torch.equal(p_got[clear] > 0.5, p_want[clear] > 0.5)
    assert torch.allclose(p_got[miss], p_want[miss], atol=1e-5)
    assert (p_got[hit] <= p_want[hit] + 1e-5).all() and (p_got[hit] > 0.5).all()
    assert torch.allclose(t_got[hit], t_want[hit], atol=1e-5)
    assert torch.allclose(n_got[hit], n_want[hit], atol=1e-4)
    if raw.dim() == 3 and raw.shape[1] > 1:  # some hits decided before their last pair (else the skip is untested)
        assert (p_got[hit] < p_want[hit] - 1e-4).any()


def test_fused_inference_is_not_used_where_it_does_not_apply(sample_meshes):
    model = NeuralBVH(build_bvh(sample_meshes["blob"], 15).nodes,
                      ModelConfig(EncodingConfig(kind="hashgrid", log2_table=6, levels=2, features=4),
                                  NetworkConfig(kind="kmlp", k=4)))
    with kernels.using_path("reference"):
        assert model._fused_network() is None
    assert model._fused_network() is not None



@pytest.mark.parametrize("enc_kw,net_kw", FUSED_MODELS + [
    (dict(kind="hashvqad", log2_table=8, levels=2, features=8, index_factor=8, candidates=4, init_scale=0.5),
     dict(kind="mlp", k=4)),  # soft (not frozen): gradients go on through the softmax
    # the unoriented normal loss (the L1 to the nearer of +-target, a flag of the kernel)
    (dict(kind="hashgrid", log2_table=6, levels=2, features=8), dict(kind="mlp", k=4, normal_loss="unoriented")),
    (dict(kind="hashgrid", log2_table=6, levels=2, features=8), dict(kind="kmlp", k=4, normal_loss="unoriented")),
    # the unit pull on raw normals, on where the network's default leaves it off (MLP) and off where it is on (KMLP)
    (dict(kind="hashgrid", log2_table=6, levels=2, features=8), dict(kind="mlp", k=4, normal_unit_weight=0.7)),
    (dict(kind="hashgrid", log2_table=6, levels=2, features=8), dict(kind="kmlp", k=4, normal_unit_weight=0.0))])
def test_fused_training_step_gives_the_loss_and_gradients_of_autograd(enc_kw, net_kw, sample_meshes):
    from nbvh_core.geometry.exact import ExactTracer
    from nbvh_core.neural import fused_mlp as mlp
    from nbvh_core.training.rays import label_samples
    from nbvh_core.training.train import samples_loss

    mesh = sample_meshes["blob"]
    bvh = build_bvh(mesh, 63)
    torch.manual_seed(0)
    model = NeuralBVH(bvh.nodes, ModelConfig(EncodingConfig(**enc_kw), NetworkConfig(**net_kw)))
    with torch.no_grad():
        model.encoding.table.normal_()
    if enc_kw["kind"] == "hashvqad" and "init_scale" not in enc_kw:
        model.encoding.freeze()
    o, d = sample_rays(*root_box(bvh), 700, np.random.default_rng(3))
    batch = label_samples(bvh, ExactTracer(mesh), o, d, "consistent")
    assert 0 < int(batch.hit.sum()) < len(batch)
    with kernels.using_path("reference"):
        model.zero_grad(set_to_none=True)
        want_loss, want_parts = samples_loss(model, batch, torch.device("cpu"))
        want_loss.backward()
    want = {n: p.grad.clone() for n, p in model.named_parameters()}
    assert mlp.applies(model)
    model.zero_grad(set_to_none=True)
    got_loss, got_parts = mlp.train_step(model, batch)
    assert got_loss == pytest.approx(float(want_loss.detach()), rel=1e-4)
    for key in want_parts:
        assert float(got_parts[key]) == pytest.approx(float(want_parts[key]), rel=1e-4, abs=1e-6), key
    for name, p in model.named_parameters():
        scale = want[name].abs().max().clamp_min(1e-6)
        assert torch.allclose(p.grad, want[name], rtol=1e-3, atol=1e-4 * float(scale)), \
            (name, float((p.grad - want[name]).abs().max()), float(scale))


@pytest.mark.parametrize("tau,index_factor", [(1.0, 4), (0.05, 4), (1.0, 128)])
def test_fused_soft_hashvqad_table_matches_the_reference(tau, index_factor):
    """HashVQAD's soft row table (softmax over t candidates) and its backward into the logits and the rows; with
    H = 128 T the coarsest level is dense and reaches 17^3 of its 8,192 entries: only those have logits and rows."""
    from nbvh_core.neural.encodings import HashVQAD

    torch.manual_seed(1)
    enc = HashVQAD(EncodingConfig(kind="hashvqad", log2_table=6, levels=3, features=8, index_factor=index_factor,
                                  candidates=8, init_scale=0.5))
    with torch.no_grad():
        enc.logits.normal_()
    enc.temperature = tau
    H = index_factor * 64
    reach = enc.reachable_entries()
    assert reach == ([17 ** 3, H, H] if index_factor == 128 else [H, H, H])
    assert enc.logits.shape == (sum(reach), 8)  # only the reachable entries have logits (and soft rows)
    grad = torch.randn(sum(reach), 8)
    unread = torch.rand(sum(reach)) < 0.5  # entries no vertex of a batch read: zero gradient rows, skipped
    grad[unread] = 0.0
    with kernels.using_path("reference"):
        want = enc.row_table()
        want.backward(grad)
    want_g = (enc.logits.grad.clone(), enc.table.grad.clone())
    enc.logits.grad = enc.table.grad = None
    got = enc.row_table()
    got.backward(grad)
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-6)
    assert torch.allclose(enc.logits.grad, want_g[0], rtol=1e-4, atol=1e-5)
    assert torch.allclose(enc.table.grad, want_g[1], rtol=1e-4, atol=1e-5)
    assert got.shape == (sum(reach), 8) and got.abs().sum(-1).min() > 0
    assert enc.logits.grad[~unread].abs().sum(-1).min() > 0  # every entry read learns
    assert (enc.logits.grad[unread] == 0).all()


def test_a_soft_step_computes_exactly_the_entries_its_batch_reads(sample_meshes, monkeypatch):
    """`fused_mlp.entries_read` marks the soft-table entries of every corner of every segment point (the reference
    lookup's indices), the soft table computes those rows only (the others zero), and a step on it gives the same
    loss and gradients as on the full table."""
    from nbvh_core.neural.encodings.base import corner_indices
    from nbvh_core.geometry.exact import ExactTracer
    from nbvh_core.neural import fused_mlp as mlp
    from nbvh_core.training.rays import label_samples

    mesh = sample_meshes["blob"]
    bvh = build_bvh(mesh, 63)
    torch.manual_seed(0)
    model = NeuralBVH(bvh.nodes, ModelConfig(
        EncodingConfig(kind="hashvqad", log2_table=6, levels=3, features=8, index_factor=64, candidates=8,
                       init_scale=0.5), NetworkConfig(kind="kmlp", k=4)))
    enc = model.encoding
    o, d = sample_rays(*root_box(bvh), 300, np.random.default_rng(5))
    batch = label_samples(bvh, ExactTracer(mesh), o, d, "consistent")
    frac = torch.linspace(0.0, 1.0, 4)
    needed = mlp.entries_read(model, batch, frac)
    points = model.segment_points(batch.rays_o[batch.ray], batch.rays_d[batch.ray], batch.t_enter, batch.t_exit)
    idx, _ = corner_indices(points.reshape(-1, 3), enc.scales, enc.vertex_table_size())
    flat = idx + torch.tensor(enc.code_starts()[:-1])[None, :, None]
    want = torch.zeros(sum(enc.reachable_entries()), dtype=torch.uint8)
    want[flat.reshape(-1)] = 1
    assert torch.equal(needed, want)
    assert 0.05 < float(want.float().mean()) < 0.95  # a real subset: some entries read, some not
    with torch.no_grad():
        full, part = enc.row_table(), enc.row_table(needed)
    assert torch.equal(part[needed == 1], full[needed == 1]) and (part[needed == 0] == 0).all()
    grads = []
    for use_mask in (True, False):
        model.zero_grad(set_to_none=True)
        if not use_mask:  # the same step on the whole soft table
            monkeypatch.setattr(mlp, "entries_read", lambda *a: None)
        loss, _ = mlp.train_step(model, batch)
        grads.append((loss, {n: p.grad.clone() for n, p in model.named_parameters()}))
    monkeypatch.undo()
    assert grads[0][0] == grads[1][0]
    for name, g in grads[0][1].items():
        assert torch.equal(g, grads[1][1][name]), name
    model.encoding.freeze()
    assert mlp.entries_read(model, batch, frac) is None  # frozen: the kernels read the stored table


def test_fused_queries_read_the_node_records_in_place(sample_meshes):
    """A model answering rays on the fast path holds its nodes once: the traversal reads model.nodes' own memory
    (the 32-byte records resident_bytes counts), and no int64 link copies are made."""
    from nbvh_core.rendering.render import orbit_cameras

    torch.manual_seed(0)
    model = NeuralBVH(build_bvh(sample_meshes["blob"], 255).nodes,
                      ModelConfig(EncodingConfig(kind="hashgrid", log2_table=6, levels=2, features=8),
                                  NetworkConfig(kind="mlp", k=4))).eval()
    o, d = (torch.from_numpy(a) for a in orbit_cameras(2)[0].rays(32, 32))
    fast = model.query(o, d)
    tree = model.tree()
    assert np.shares_memory(tree.records.numpy(), model.nodes) and tree._links is None
    assert model.resident_bytes()["bvh"] == model.nodes.nbytes
    with kernels.using_path("reference"):
        ref = model.query(o, d)
    assert torch.equal(fast.hit, ref.hit) and torch.allclose(fast.t[fast.hit], ref.t[ref.hit], atol=1e-5)


def test_the_stored_8bit_nodes_are_traversed_as_held(sample_meshes, tmp_path):
    """finalize_storage(node_bits=8) and a loaded 8-bit file hold the file's 10 B per node; the fused traversal decodes
    boxes on the way down, bit-identical to the decoded nodes (same leaves, same t), and the reference path decodes."""
    import copy

    from nbvh_core.storage.fileformat import load_nbvh, save_nbvh
    from nbvh_core.neural.quantize import StorageConfig, snap_nodes, stored_node_bytes
    from nbvh_core.rendering.render import orbit_cameras

    torch.manual_seed(0)
    nodes = snap_nodes(build_bvh(sample_meshes["bunny"], 511).nodes)
    model = NeuralBVH(nodes, ModelConfig(EncodingConfig(kind="hashgrid", log2_table=8, levels=2, features=8),
                                         NetworkConfig(kind="mlp", k=4))).eval()
    with torch.no_grad():
        model.encoding.table.normal_(0, 0.3)
    held = copy.deepcopy(model)
    model.finalize_storage(StorageConfig(8, 16, 32))
    held.finalize_storage(StorageConfig(8, 16, 8))
    assert held._nodes is None and held.resident_bytes()["bvh"] == stored_node_bytes(511, 8, shape_only=False) < model.nodes.nbytes
    assert kernels.plan(held).traversal == "fused 8-bit nodes"
    o, d = (torch.from_numpy(a) for a in orbit_cameras(3)[1].rays(48, 48))
    for bias in (5.0, -5.0):  # every ray stops at its first leaf / every ray walks all its leaves
        for m in (model, held):
            with torch.no_grad():
                m.network.net[-1].bias[0] = bias
        a, b = model.query(o, d), held.query(o, d)
        assert torch.equal(a.hit, b.hit) and torch.equal(a.t, b.t) and a.leaves_evaluated == b.leaves_evaluated > 0
    with kernels.using_path("reference"):
        r = held.query(o, d)
    assert torch.equal(r.hit, a.hit) and r.leaves_evaluated == a.leaves_evaluated
    save_nbvh(held, tmp_path / "m.nbvh", storage=StorageConfig(8, 16, 8))
    loaded = load_nbvh(tmp_path / "m.nbvh")
    assert loaded._nodes is None and np.array_equal(loaded.compact_nodes["boxes"], held.compact_nodes["boxes"])
    assert torch.equal(loaded.query(o, d).hit, a.hit)
