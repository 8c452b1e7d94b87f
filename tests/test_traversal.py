import numpy as np
import pytest
import torch

from nbvh_core.training.rays import RayConfig, root_box, sample_rays
from nbvh_core.geometry.traversal import LeafStream, TorchBVH, leaves_along_rays


def brute_force_leaves(bvh, rays_o, rays_d, chunk=4096):
    """Every (ray, leaf) whose box the ray enters, testing every leaf box (no hierarchy), float32 slab test."""
    lo, hi = bvh.leaf_boxes()
    lo, hi = torch.from_numpy(lo), torch.from_numpy(hi)
    o_all, inv_all = torch.from_numpy(rays_o), 1.0 / torch.from_numpy(rays_d)
    rays, leaves, t_in, t_out = [], [], [], []
    for s in range(0, len(rays_o), chunk):
        o, inv = o_all[s:s + chunk, None], inv_all[s:s + chunk, None]
        t0, t1 = (lo[None] - o) * inv, (hi[None] - o) * inv
        near = torch.fmin(t0, t1).nan_to_num(nan=-torch.inf).amax(-1).clamp_min(0)
        far = torch.fmax(t0, t1).nan_to_num(nan=torch.inf).amin(-1)
        r, l = torch.nonzero(near <= far, as_tuple=True)
        rays.append(r + s)
        leaves.append(l)
        t_in.append(near[r, l])
        t_out.append(far[r, l])
    return torch.cat(rays), torch.cat(leaves), torch.cat(t_in), torch.cat(t_out)


def random_rays(bvh, n, seed):
    lo, hi = root_box(bvh)
    o, d = sample_rays(lo, hi, n, np.random.default_rng(seed), RayConfig())
    # A few axis-parallel rays and rays through box faces: the slab test's hard cases.
    d[:300] = np.eye(3, dtype=np.float32)[np.arange(300) % 3] * np.where(np.arange(300) % 2, 1, -1)[:, None]
    return o, d


@pytest.mark.parametrize("name", ["blob", "studs", "gyroid", "terrain", "bunny"])
def test_complete_list_matches_brute_force(sample_bvhs, name):
    bvh = sample_bvhs[name]
    o, d = random_rays(bvh, 100_000, seed=1)
    tree = TorchBVH.from_bvh(bvh)
    lh = leaves_along_rays(tree, torch.from_numpy(o), torch.from_numpy(d))
    r, l, te, tx = brute_force_leaves(bvh, o, d)
    key_trav = lh.ray * bvh.n_leaves + lh.leaf
    key_bf = r * bvh.n_leaves + l
    assert torch.equal(torch.sort(key_trav).values, torch.sort(key_bf).values)
    # Same segments for the same pairs.
    o1, o2 = torch.argsort(key_trav), torch.argsort(key_bf)
    assert torch.equal(lh.t_enter[o1], te[o2]) and torch.equal(lh.t_exit[o1], tx[o2])
    # Front to back: within every ray, t_enter never decreases; offsets delimit rays.
    same = lh.ray[1:] == lh.ray[:-1]
    assert (lh.t_enter[1:][same] >= lh.t_enter[:-1][same]).all()
    assert torch.equal(lh.counts(), torch.bincount(r, minlength=len(o)))
    assert (lh.rank() >= 0).all()


def _drain(stream):
    pairs = []
    while True:
        ray, leaf, te, tx = stream.next()
        if ray.numel() == 0:
            break
        assert ray.unique().numel() == ray.numel()  # at most one leaf per ray per step
        pairs.append(torch.stack((ray, leaf, te.view(torch.int32).long(), tx.view(torch.int32).long()), 1))
    return torch.cat(pairs) if pairs else torch.empty(0, 4, dtype=torch.long)


@pytest.mark.parametrize("name", ["blob", "gyroid", "bunny"])
def test_stream_yields_the_complete_list(sample_bvhs, name):
    bvh = sample_bvhs[name]
    o, d = random_rays(bvh, 20_000, seed=2)
    tree = TorchBVH.from_bvh(bvh)
    lh = leaves_along_rays(tree, torch.from_numpy(o), torch.from_numpy(d))
    got = _drain(LeafStream(tree, torch.from_numpy(o), torch.from_numpy(d)))
    want = torch.stack((lh.ray, lh.leaf, lh.t_enter.view(torch.int32).long(), lh.t_exit.view(torch.int32).long()), 1)
    as_set = lambda x: set(map(tuple, x.tolist()))
    assert len(got) == len(want) and as_set(got) == as_set(want)


def test_stream_shorten_skips_boxes_beyond_t_max(sample_bvhs):
    bvh = sample_bvhs["gyroid"]
    o, d = random_rays(bvh, 5000, seed=3)
    tree = TorchBVH.from_bvh(bvh)
    o_t, d_t = torch.from_numpy(o), torch.from_numpy(d)
    lh = leaves_along_rays(tree, o_t, d_t)
    stream = LeafStream(tree, o_t, d_t)
    ray, leaf, te, tx = stream.next()
    # Pretend every ray hit at the exit of its first leaf: later leaves must start before that point.
    stream.shorten(ray, tx)
    rest = _drain(stream)
    t_cut = torch.full((len(o),), torch.inf)
    t_cut[ray] = tx
    rest_te = rest[:, 2].int().view(torch.float32)
    assert (rest_te <= t_cut[rest[:, 0]]).all()
    # And all such leaves are still visited (the hit could be beaten by an overlapping box).
    expect = (lh.t_enter <= t_cut[lh.ray]).sum() - len(ray)
    assert len(rest) == int(expect)
    # stop() ends a ray.
    s2 = LeafStream(tree, o_t, d_t)
    r2, *_ = s2.next()
    s2.stop(r2)
    assert s2.done.all()


def test_rays_starting_inside_boxes_get_t_enter_zero(sample_bvhs):
    bvh = sample_bvhs["blob"]
    tree = TorchBVH.from_bvh(bvh)
    lo, hi = bvh.leaf_boxes()
    o = torch.from_numpy((lo[:100] + hi[:100]) / 2)
    d = torch.nn.functional.normalize(torch.randn(100, 3), dim=1)
    lh = leaves_along_rays(tree, o, d)
    own = lh.leaf == lh.ray  # ray i starts at the centre of leaf i
    assert own.sum() == 100 and (lh.t_enter[own] == 0).all()


def test_t_max_limits_the_list(sample_bvhs):
    bvh = sample_bvhs["blob"]
    tree = TorchBVH.from_bvh(bvh)
    o, d = random_rays(bvh, 2000, seed=4)
    t_max = torch.full((2000,), 1.0)
    lh = leaves_along_rays(tree, torch.from_numpy(o), torch.from_numpy(d), t_max)
    full = leaves_along_rays(tree, torch.from_numpy(o), torch.from_numpy(d))
    assert (lh.t_enter <= 1.0).all() and len(lh) == int((full.t_enter <= 1.0).sum())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(sample_bvhs):
    bvh = sample_bvhs["bunny"]
    o, d = random_rays(bvh, 50_000, seed=5)
    cpu = leaves_along_rays(TorchBVH.from_bvh(bvh), torch.from_numpy(o), torch.from_numpy(d))
    gpu = leaves_along_rays(TorchBVH.from_bvh(bvh, "cuda"), torch.from_numpy(o).cuda(), torch.from_numpy(d).cuda())
    assert torch.equal(cpu.ray, gpu.ray.cpu()) and torch.equal(cpu.leaf, gpu.leaf.cpu())
    assert torch.allclose(cpu.t_enter, gpu.t_enter.cpu(), atol=1e-6)
