import numpy as np
import pytest
import torch

from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.mesh import mesh_from_arrays
from nbvh_core.training.rays import (SEGMENT_EPS, RayConfig, generate_training_samples, label_samples, root_box,
                               sample_rays)

EPS = 2 * SEGMENT_EPS


def overlapping_siblings_case():
    """Two triangles in two sibling leaves; B's box lies inside A's box, A itself is not on the ray."""
    v = np.array([[0, 0, 0], [1, 0, 1], [0, 1, 1],              # A: big slanted triangle, box = unit cube
                  [0.65, 0.65, 0.2], [0.75, 0.65, 0.2], [0.7, 0.75, 0.2]], float)  # B: small, flat, z = 0.2
    mesh = mesh_from_arrays(v, np.array([[0, 1, 2], [3, 4, 5]]), name="overlap")
    bvh = build_bvh(mesh, 3)
    assert bvh.n_leaves == 2
    o = mesh.transform.to_normalised(np.array([[0.7, 0.7, 2.0]])).astype(np.float32)
    d = np.array([[0, 0, -1]], np.float32)
    return mesh, bvh, o, d


def test_ownership_and_consistent_differ_on_overlapping_siblings():
    mesh, bvh, o, d = overlapping_siblings_case()
    tracer = ExactTracer(mesh)
    leaf_a, leaf_b = bvh.tri_leaf[0], bvh.tri_leaf[1]
    t_b = tracer.first_hit(o, d).t[0]
    assert t_b == pytest.approx(1.8, abs=1e-5)
    own = label_samples(bvh, tracer, o, d, "ownership")
    con = label_samples(bvh, tracer, o, d, "consistent")
    for s in (own, con):
        assert sorted(s.leaf.tolist()) == sorted([leaf_a, leaf_b])  # A's box entered at t = 1, B's at 1.8
    a_own, a_con = own.leaf == leaf_a, con.leaf == leaf_a
    # Ownership: A's leaf is a miss although the hit point lies inside A's box.
    assert not own.hit[a_own].item() and own.hit[~a_own].item()
    # Consistent: A's leaf is labelled with B's hit point, the nearest hit inside its box.
    assert con.hit[a_con].item() and con.t_hit[a_con].item() == pytest.approx(t_b, abs=1e-5)
    p = con.points()[a_con][0].numpy()
    lo, hi = bvh.leaf_boxes()
    assert (p >= lo[leaf_a] - EPS).all() and (p <= hi[leaf_a] + EPS).all()
    assert con.hit[~a_con].item()
    assert torch.allclose(con.normal[a_con], torch.tensor([[0.0, 0.0, 1.0]]))


@pytest.mark.parametrize("name", ["blob", "gyroid", "terrain", "bunny"])
def test_consistent_labels_are_nearest_hit_inside_leaf_box(sample_bvhs, sample_tracers, name):
    bvh, tracer = sample_bvhs[name], sample_tracers[name]
    s = generate_training_samples(bvh, tracer, 5000, "consistent", seed=7)
    assert len(s) > 1000 and s.hit.any() and (~s.hit).any()
    lo, hi = (torch.from_numpy(a) for a in bvh.leaf_boxes())
    p = s.points()[s.hit]
    leaf = s.leaf[s.hit]
    assert (p >= lo[leaf] - EPS).all() and (p <= hi[leaf] + EPS).all()
    # Brute force per sample against all hits of its ray.
    allh = tracer.all_hits(s.rays_o.numpy(), s.rays_d.numpy())
    for i in range(0, len(s), 7):
        r = int(s.ray[i])
        ts = allh.t[allh.offsets[r]:allh.offsets[r + 1]]
        inside = ts[(ts >= s.t_enter[i].item() - SEGMENT_EPS) & (ts <= s.t_exit[i].item() + SEGMENT_EPS)]
        if s.hit[i]:
            assert inside.size and s.t_hit[i].item() == pytest.approx(float(inside.min()), abs=EPS)
        else:
            assert inside.size == 0
    # Every sample is entered up to and including the ray's first hit.
    first = tracer.first_hit(s.rays_o.numpy(), s.rays_d.numpy()).t
    assert (s.t_enter.numpy() <= first[s.ray.numpy()] + EPS).all()
    assert ((s.t_hit >= s.t_enter) & (s.t_hit <= s.t_exit)).all()
    n_len = s.normal[s.hit].norm(dim=1)
    assert torch.allclose(n_len, torch.ones_like(n_len), atol=1e-5)


@pytest.mark.parametrize("name", ["blob", "studs", "bunny"])
def test_ownership_labels_only_owner_leaf(sample_bvhs, sample_tracers, name):
    bvh, tracer = sample_bvhs[name], sample_tracers[name]
    own = generate_training_samples(bvh, tracer, 5000, "ownership", seed=8)
    con = generate_training_samples(bvh, tracer, 5000, "consistent", seed=8)
    fh = tracer.first_hit(own.rays_o.numpy(), own.rays_d.numpy())
    # At most one hit sample per ray, in the leaf owning the first-hit triangle, at the first hit.
    hit_rays = own.ray[own.hit]
    assert hit_rays.unique().numel() == hit_rays.numel()
    assert np.array_equal(bvh.tri_leaf[fh.tri[hit_rays.numpy()]], own.leaf[own.hit].numpy())
    assert own.stats["first_hits_unlabelled"] == 0 and int(own.hit.sum()) == int(fh.hit.sum())
    # Same rays, same entered leaves in both modes; consistent labels every owner hit too, plus more.
    assert torch.equal(own.ray, con.ray) and torch.equal(own.leaf, con.leaf)
    assert (con.hit[own.hit]).all()
    assert torch.allclose(con.t_hit[own.hit], own.t_hit[own.hit], atol=EPS)
    assert int(con.hit.sum()) >= int(own.hit.sum())


def test_ray_distribution_covers_enlarged_box(sample_bvhs):
    lo, hi = root_box(sample_bvhs["blob"])
    o, d = sample_rays(lo, hi, 20000, np.random.default_rng(0), RayConfig(outside_fraction=0.5))
    assert o.shape == d.shape == (20000, 3) and o.dtype == np.float32
    assert np.allclose(np.linalg.norm(d, axis=1), 1, atol=1e-5)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    inside_big = np.all(np.abs(o - centre) <= half * 1.5 + 1e-6, axis=1)
    # About half the rays start inside the enlarged box, the rest outside it; each kind reaches every octant.
    assert 0.35 < inside_big.mean() < 0.65
    octant = ((o - centre) > 0) @ np.array([1, 2, 4])
    assert len(np.unique(octant[inside_big])) == 8 and len(np.unique(octant[~inside_big])) == 8
    # Reproducible.
    o2, _ = sample_rays(lo, hi, 20000, np.random.default_rng(0), RayConfig(outside_fraction=0.5))
    assert np.array_equal(o, o2)


def test_bad_mode():
    mesh, bvh, o, d = overlapping_siblings_case()
    with pytest.raises(ValueError, match="label mode"):
        label_samples(bvh, ExactTracer(mesh), o, d, "nearest")


def test_rays_in_leaves_start_in_the_leaves_drawn_by_weight(sample_bvhs):
    from nbvh_core.training.rays import sample_rays_in_leaves

    bvh = sample_bvhs["blob"]
    lo, hi = bvh.leaf_boxes()
    weights = np.full(len(lo), 1e-9)
    weights[7] = 1.0  # (almost) all the weight on leaf 7
    o, d = sample_rays_in_leaves(lo, hi, weights, 2000, np.random.default_rng(0))
    assert o.shape == d.shape == (2000, 3) and o.dtype == np.float32
    inside = np.all((o >= lo[7] - 1e-6) & (o <= hi[7] + 1e-6), axis=1)
    assert inside.mean() > 0.99
    assert np.allclose(np.linalg.norm(d, axis=1), 1, atol=1e-5)
    assert np.abs(d.mean(0)).max() < 0.1  # directions uniform on the sphere


def test_leaf_errors_follow_the_batches_and_keep_a_floor():
    import torch

    from nbvh_core.training.train import LeafErrors

    le = LeafErrors(4, floor=0.1)
    leaf = torch.tensor([0, 0, 1, 3])
    err = torch.tensor([2.0, 4.0, 0.0, 1.0])
    le.update(leaf, err)
    e = le.error.numpy()
    assert np.allclose(e, [0.9 + 0.1 * 3.0, 0.9, 1.0, 1.0])  # leaf 2 unseen: unchanged
    for _ in range(200):
        le.update(torch.tensor([1]), torch.tensor([0.0]))
    w = le.weights()
    assert w[1] == pytest.approx(0.1 * le.error.numpy().mean())  # a solved leaf keeps the floor


@pytest.mark.parametrize("mode", ["ownership", "consistent"])
def test_facing_normals_are_the_geometric_ones_turned_toward_the_ray(sample_bvhs, sample_tracers, mode):
    bvh, tracer = sample_bvhs["blob"], sample_tracers["blob"]
    o, d = sample_rays(*root_box(bvh), 3000, np.random.default_rng(5))
    wound = label_samples(bvh, tracer, o, d, mode)
    facing = label_samples(bvh, tracer, o, d, mode, normal_loss="facing")
    hit = wound.hit
    dots = (facing.normal[hit] * facing.rays_d[facing.ray[hit]]).sum(-1)
    assert bool((dots <= 0).all())
    same = (facing.normal[hit] == wound.normal[hit]).all(-1)
    flipped = (facing.normal[hit] == -wound.normal[hit]).all(-1)
    assert bool((same | flipped).all()) and bool(flipped.any()) and bool(same.any())  # rays start inside and out
    assert torch.equal(facing.hit, wound.hit) and torch.equal(facing.t_hit, wound.t_hit)
