"""Training labels made on the card (`training/card_labels.py`): the mesh's exact hits (`kernels/triton/mesh_trace.py`
through `geometry/card_tracer.py`) and the leaves each ray enters (`kernels/triton/leaf_lists.py`) against the host's
reference, Embree and the C++ leaf lists. Without a GPU the kernels run in Triton's interpreter on CPU tensors
(conftest.py sets TRITON_INTERPRET=1); on a card, on CUDA tensors. Tolerances: the same segments (ray, leaf, t_enter,
t_exit: the same float32 slab test); t within 1e-5 where both hit; hit flags agree on at least 99% of samples (float32
Moller-Trumbore against Embree's watertight test: a ray grazing an edge may decide otherwise; measured 100% on these
rays)."""
from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch

pytest.importorskip("triton")

from nbvh_core import kernels  # noqa: E402
from nbvh_core.geometry.bvh import build_bvh  # noqa: E402
from nbvh_core.geometry.card_tracer import CardTracer, mesh_records  # noqa: E402
from nbvh_core.geometry.exact import ExactTracer  # noqa: E402
from nbvh_core.geometry.traversal import TorchBVH, leaves_along_rays  # noqa: E402
from nbvh_core.training.card_labels import CardLabels  # noqa: E402
from nbvh_core.training.rays import label_samples, root_box, sample_rays  # noqa: E402

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
kernel_plan = importlib.import_module("nbvh_core.kernels.plan")


def _rays(bvh, n: int, seed: int = 0):
    lo, hi = root_box(bvh)
    return sample_rays(lo, hi, n, np.random.default_rng(seed))


def _on(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a)).to(DEVICE)


def test_the_card_s_mesh_tree_holds_every_triangle_once_in_leaves_of_at_most_four(sample_meshes):
    mesh = sample_meshes["gyroid"]
    records, depth, triangles, tri_ids = mesh_records(mesh)
    links = records.view(np.int32)[:, 6:8]
    inner = links[:, 0] > 0
    counts = -links[~inner, 0]
    assert counts.max() <= 4 and counts.min() >= 1 and counts.sum() == mesh.n_triangles
    covered = np.concatenate([np.arange(s, s + c) for s, c in zip(links[~inner, 1], counts)])
    assert np.array_equal(np.sort(covered), np.arange(mesh.n_triangles))  # each row of the table in one leaf
    assert np.array_equal(np.sort(tri_ids), np.arange(mesh.n_triangles))
    kids = links[inner, 0]
    assert kids.min() > 0 and kids.max() + 1 < len(records) and len(np.unique(kids)) == len(kids)
    # a child's box lies inside its parent's
    parent_of = np.repeat(np.flatnonzero(inner), 2)
    child = np.stack((kids, kids + 1), 1).reshape(-1)
    assert (records[child, :3] >= records[parent_of, :3] - 1e-6).all()
    assert (records[child, 3:6] <= records[parent_of, 3:6] + 1e-6).all()
    assert 1 <= depth <= 64


@pytest.mark.parametrize("name", ["gyroid", "terrain"], ids=["thin-walls", "open-surface"])
def test_the_card_s_first_hits_match_embree_s(name, sample_meshes):
    mesh = sample_meshes[name]
    bvh = build_bvh(mesh, 64)
    o, d = _rays(bvh, 256, seed=1)
    want = ExactTracer(mesh).first_hit(o, d)
    t, tri, normal = CardTracer(mesh, DEVICE).first_hit(_on(o), _on(d))
    t, tri, normal = t.cpu().numpy(), tri.cpu().numpy(), normal.cpu().numpy()
    assert want.hit.sum() > 60  # a test of hits, not of misses
    assert (tri == want.tri).mean() >= 0.99, (tri != want.tri).sum()
    both = (tri == want.tri) & want.hit
    assert np.abs(t[both] - want.t[both]).max() <= 1e-5
    assert np.abs(normal[both] - want.normal[both]).max() <= 1e-6
    assert np.isinf(t[tri < 0]).all() and (normal[tri < 0] == 0).all()


def test_a_t_range_query_finds_the_nearest_hit_inside_the_range_only(sample_meshes):
    """Nearest hit with t_min <= t <= t_max: against Embree's every-hit list, the first hit at or beyond t_min."""
    mesh = sample_meshes["gyroid"]
    bvh = build_bvh(mesh, 64)
    o, d = _rays(bvh, 256, seed=2)
    tracer = ExactTracer(mesh)
    every = tracer.all_hits(o, d)
    rng = np.random.default_rng(3)
    last = np.where(np.diff(every.offsets) > 0, every.t[np.maximum(every.offsets[1:] - 1, 0)], 1.0)
    t_min = (rng.uniform(0, 1, 256) * (last + 0.2)).astype(np.float32)  # windows among each ray's hits
    t_max = (t_min + rng.uniform(0, 0.4, 256)).astype(np.float32)
    t, tri = CardTracer(mesh, DEVICE).nearest(_on(o), _on(d), _on(t_min), _on(t_max))
    t, tri = t.cpu().numpy(), tri.cpu().numpy()
    want_t = np.full(256, np.inf, np.float32)
    for r in range(256):
        hits = every.t[every.offsets[r]:every.offsets[r + 1]]
        inside = hits[(hits >= t_min[r]) & (hits <= t_max[r])]
        if inside.size:
            want_t[r] = inside[0]
    found = np.isfinite(want_t)
    assert found.sum() > 25 and (~found).sum() > 25  # both kinds of answer occur
    assert (np.isfinite(t) == found).mean() >= 0.99
    agree = found & np.isfinite(t)
    assert np.abs(t[agree] - want_t[agree]).max() <= 1e-5
    assert (t[np.isfinite(t)] >= t_min[np.isfinite(t)]).all() and (t[np.isfinite(t)] <= t_max[np.isfinite(t)]).all()


def test_the_card_s_leaf_lists_are_the_host_s(sample_meshes, monkeypatch):
    """Every leaf each ray enters up to a t_max, front to back: the Triton walk and sort against the C++ kernel."""
    mesh = sample_meshes["bunny"]
    bvh = build_bvh(mesh, 255)
    o, d = _rays(bvh, 300, seed=4)
    t_max = np.random.default_rng(5).uniform(0.2, 3.0, 300).astype(np.float32)
    t_max[::3] = np.inf  # a third of the rays see every leaf they enter
    t_max = torch.from_numpy(t_max)
    want = leaves_along_rays(TorchBVH.from_bvh(bvh), torch.from_numpy(o), torch.from_numpy(d), t_max)
    monkeypatch.setattr(kernels, "leaf_list_kernel", lambda device: "triton")
    got = leaves_along_rays(TorchBVH.from_bvh(bvh, DEVICE), _on(o), _on(d), t_max.to(DEVICE))
    assert len(want) > 400 and (want.counts() > 4).sum() > 20  # rays of several leaves: their order counts
    for name in ("ray", "leaf", "node", "t_enter", "t_exit", "offsets"):
        assert torch.equal(getattr(got, name).cpu(), getattr(want, name)), name


@pytest.mark.parametrize("mode,normal_loss", [("consistent", "facing"), ("ownership", "oriented")])
def test_labels_made_on_the_card_are_the_host_s(mode, normal_loss, sample_meshes, monkeypatch):
    mesh = sample_meshes["gyroid"]
    bvh = build_bvh(mesh, 127)
    o, d = _rays(bvh, 256, seed=6)
    want = label_samples(bvh, ExactTracer(mesh), o, d, mode, normal_loss=normal_loss)
    monkeypatch.setattr(kernels, "leaf_list_kernel", lambda device: "triton")
    got = CardLabels(CardTracer(mesh, DEVICE)).label(bvh, o, d, mode, normal_loss=normal_loss)
    assert got.ray.device.type == torch.device(DEVICE).type and got.stats["labelled_on"] == "card"
    assert len(want) > 300 and want.hit.sum() > 100
    for name in ("rays_o", "rays_d", "ray", "leaf", "t_enter", "t_exit", "rank"):
        assert torch.equal(getattr(got, name).cpu(), getattr(want, name)), name
    hit = got.hit.cpu()
    assert (hit == want.hit).float().mean() >= 0.99
    both = hit & want.hit
    assert (got.t_hit.cpu()[both] - want.t_hit[both]).abs().max() <= 1e-5
    assert (got.normal.cpu()[both] - want.normal[both]).abs().max() <= 1e-6
    for key in ("rays", "rays_hit", "samples"):
        assert got.stats[key] == want.stats[key], key


def test_a_training_labels_on_the_card_where_the_plan_says_so(sample_meshes, monkeypatch):
    """The loop's batches come from the card labeller when `label_kernel` says 'card' (without a card the CPU stands
    in, its leaf lists the C++ kernel's): chunks split and served again in new orders on its device, and the plan says where
    labels were made."""
    from nbvh_core.neural.model import ModelConfig, NeuralBVH
    from nbvh_core.training.ray_batches import Batches
    from nbvh_core.training.train import TrainConfig, train

    mesh = sample_meshes["blob"]
    bvh = build_bvh(mesh, 31)
    monkeypatch.setattr(kernels, "label_kernel", lambda device: "card")
    monkeypatch.setattr(kernel_plan, "label_kernel", lambda device: "card")
    cfg = TrainConfig(steps=3, rays_per_step=64, label_steps=2, seed=0, label_reuse=2, device=DEVICE)
    tracer = ExactTracer(mesh)
    result = train(NeuralBVH(bvh.nodes, ModelConfig(), mesh.transform), bvh, tracer, cfg)
    assert result.kernel_plan["labels"] == "card" and "labels on the card" in result.compute_path
    assert tracer.on_card(DEVICE) is tracer.on_card(DEVICE)  # one card tracer per mesh
    batches = Batches(bvh, tracer, cfg, np.random.default_rng(0), reuse=2,
                      card_labels=CardLabels(tracer.on_card(DEVICE)))
    host = Batches(bvh, tracer, cfg, np.random.default_rng(0), reuse=2)
    for _ in range(4):  # two steps of the chunk, then the same rays in a new order
        got, want = batches.next(), host.next()
        assert got.stats["chunk"]["labelled_on"] == "card" and got.leaf.device.type == torch.device(DEVICE).type
        assert torch.equal(got.rays_o.cpu(), want.rays_o) and torch.equal(got.leaf.cpu(), want.leaf)
        assert (got.hit.cpu() == want.hit).float().mean() >= 0.99


def test_the_card_labels_by_default_and_the_host_where_asked(monkeypatch):
    monkeypatch.setattr(kernel_plan, "triton_serves", lambda device: torch.device(device).type == "cuda")
    assert kernel_plan.label_kernel("cuda") == "card" and kernel_plan.leaf_list_kernel("cuda") == "triton"
    assert kernel_plan.label_kernel("cpu") == "host"
    monkeypatch.setenv(kernel_plan.CARD_LABELS_ENV, "host")
    assert kernel_plan.label_kernel("cuda") == "host"
