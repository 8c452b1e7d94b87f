"""Quantized storage keeps its promises: an 8-bit node box always contains its exact box (so traversal never misses a
leaf the float32 BVH would enter), and a model's quantized storage scores within 10% of the same training in
float32."""
import dataclasses

import numpy as np
import torch
import pytest

from nbvh_core.geometry.bvh import NODE_DTYPE
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.neural.quantize import decode_nodes, encode_nodes, snap_nodes


def _random_tree(rng: np.random.Generator, internal: int, span: float) -> np.ndarray:
    """NODE_DTYPE nodes of a random binary tree (children of node i at left[i], left[i] + 1, as the BVH stores them)
    whose boxes nest: each child a random sub-box of its parent, some flush with a parent's face, some flat (zero
    width on an axis), some a float32 ulp wide. The root spans [-span, span] around a random offset."""
    lo = [rng.uniform(-span, 0, 3).astype(np.float32)]
    hi = [(lo[0] + np.float32(span) * rng.uniform(0.5, 2.0, 3)).astype(np.float32)]
    left, queue = [0], [0]
    while queue and len(left) < 2 * internal + 1:
        parent = queue.pop(0)
        left[parent] = len(left)
        for _ in range(2):
            a, b = rng.uniform(lo[parent], hi[parent], (2, 3)).astype(np.float32)
            c_lo, c_hi = np.minimum(a, b), np.maximum(a, b)
            style = rng.random(3)
            c_lo = np.where(style < 0.15, lo[parent], c_lo)  # flush with the parent's lower face
            c_hi = np.where((style > 0.15) & (style < 0.3), hi[parent], c_hi)  # or its upper one
            c_hi = np.where((style > 0.3) & (style < 0.4), c_lo, c_hi)  # flat
            c_hi = np.where((style > 0.4) & (style < 0.5), np.nextafter(c_lo, np.float32(np.inf)), c_hi)  # one ulp
            lo.append(c_lo.astype(np.float32))
            hi.append(np.minimum(c_hi, hi[parent]).astype(np.float32))
            left.append(0)
            queue.append(len(left) - 1)
    nodes = np.zeros(len(left), NODE_DTYPE)
    nodes["lo"], nodes["hi"], nodes["left"] = np.array(lo), np.array(hi), left
    nodes["leaf"] = -1
    leaves = nodes["left"] == 0
    nodes["leaf"][leaves] = np.arange(int(leaves.sum()))
    return nodes


def _parents(nodes: np.ndarray) -> np.ndarray:
    parent = np.full(len(nodes), -1, np.int64)
    internal = np.flatnonzero(nodes["left"] != 0)
    parent[nodes["left"][internal]] = internal
    parent[nodes["left"][internal] + 1] = internal
    return parent


def _assert_conservative_and_tight(nodes: np.ndarray) -> None:
    enc = encode_nodes(nodes)
    assert enc is not None
    dec = decode_nodes(enc["root"], enc["boxes"], enc["left"], enc["leaf"])
    assert np.array_equal(dec["left"], nodes["left"]) and np.array_equal(dec["leaf"], nodes["leaf"])
    assert (dec["lo"] <= nodes["lo"]).all() and (dec["hi"] >= nodes["hi"]).all()  # contains the exact box
    # ... and not by just being the parent: each face within one code step (1/255 of the decoded parent) of exact
    parent = _parents(nodes)
    kids = np.flatnonzero(parent >= 0)
    step = (dec["hi"][parent[kids]] - dec["lo"][parent[kids]]) / 255
    slack = 1e-6 * np.abs(dec["hi"][parent[kids]]).max(axis=1, keepdims=True) + 1e-30
    assert (nodes["lo"][kids] - dec["lo"][kids] <= step + slack).all()
    assert (dec["hi"][kids] - nodes["hi"][kids] <= step + slack).all()
    assert np.array_equal(snap_nodes(nodes)["lo"], dec["lo"])  # what the pipeline trains on


@pytest.mark.parametrize("seed,span", [(0, 1.0), (1, 1e-3), (2, 1e4), (3, 1.0), (4, 37.5)])
def test_quantized_boxes_contain_their_exact_boxes_in_random_trees(seed, span):
    _assert_conservative_and_tight(_random_tree(np.random.default_rng(seed), 1500, span))


def test_quantized_boxes_contain_their_exact_boxes_in_real_bvhs(sample_bvhs):
    for bvh in sample_bvhs.values():
        _assert_conservative_and_tight(bvh.nodes)


def test_a_child_outside_its_parent_keeps_float32_nodes():
    nodes = _random_tree(np.random.default_rng(5), 50, 1.0)
    nodes["hi"][3, 1] = nodes["hi"][0, 1] + 0.5  # pokes out of the root: no code can hold it
    assert encode_nodes(nodes) is None
    assert snap_nodes(nodes) is nodes  # the file keeps the exact float32 boxes


def test_quantized_storage_scores_within_10_percent_of_its_float32_training(sample_meshes):
    """The default preset's storage (6-bit tables, int8 network rows, 8-bit nodes) against the same training scored
    before its storage is quantized: the image MSE moves by under 10% (measured +3.1% at 400 steps)."""
    s = preset("default").with_overrides(steps=400, force=True, eval_views=6, eval_resolution=64, seed=0)
    s.time_limit_s = None
    res = compress_mesh(sample_meshes["bunny"], s, None, compare_float32=True)
    assert (s.table_bits, s.network_bits, s.node_bits) == (6, 8, 8)
    model = res.model
    assert model.encoding.quantized and model._nodes is None  # the stored forms are the ones scored
    f32, q = res.seconds["mse_float32"], res.quality.mse
    assert 0 < f32 < 0.05  # a trained model, not noise
    assert abs(q - f32) <= 0.10 * f32, (q, f32)


@pytest.mark.parametrize("low", [4, 6])
def test_low_bit_tables_shrink_the_features_and_read_back_exactly(sample_meshes, low):
    """table_bits 4 or 6: the file's feature codes take low/8 of the bytes of 8-bit ones (the grid's affine map is
    kept), the codes stay under 2^low, the network trained its last steps on that grid (quantization-aware), and the
    file decodes to the very model that was scored."""
    from nbvh_core.rendering.metrics import MetricConfig, view_sets
    from nbvh_core.storage.fileformat import decode_nbvh

    mesh = sample_meshes["bunny"]
    runs = {}
    for bits in (8, low):
        s = preset("tiny").with_overrides(steps=60, force=True, table_bits=bits, log2_table=10, levels=8, features=4)
        runs[bits] = compress_mesh(mesh, s, None)
    f8, fl = runs[8].components["features"], runs[low].components["features"]
    affine = 2 * 4 * 8 * 4  # float32 offset and scale per (level, feature)
    assert fl - affine == (f8 - affine) * low // 8, (f8, fl)
    res = runs[low]
    assert int(res.model.encoding.qcodes.max()) < (1 << low) and res.settings.table_bits == low
    assert int(res.model.encoding.qcodes.max()) >= (1 << (low - 1))  # the grid's upper half is used
    decoded = decode_nbvh(res.data)
    assert torch.equal(decoded.encoding.qcodes.cpu(), res.model.encoding.qcodes.cpu())
    checks, held = view_sets(res.tracer, mesh.transform, MetricConfig(2, 32))
    assert held.score_model(decoded)[0].mse == pytest.approx(held.score_model(res.model)[0].mse, rel=1e-4)


def test_a_four_bit_file_keeps_its_appearance_head_at_eight_bits():
    """The head trains no quantization-aware phase, so a 4-bit geometry table leaves the head's table at 8 bits: the
    file's head bytes are what the estimate before training counted, and the head reads back code for code."""
    from nbvh_core.geometry.demo_assets import crate
    from nbvh_core.storage.fileformat import decode_nbvh
    from nbvh_core.storage.layout import look_stored_bytes

    mesh = crate(cells=2, texture=64)
    s = preset("tiny").with_overrides(steps=30, force=True, table_bits=4)
    res = compress_mesh(mesh, s, None, evaluate_quality=False)
    head = res.model.appearance
    assert head is not None and head.encoding.quantized
    assert int(head.encoding.qcodes.max()) > 15  # 8-bit codes (the grid spans each feature's range: code 255)
    storage = res.settings.storage()
    expected = look_stored_bytes(head.cfg, res.model.materials, storage)
    eight = look_stored_bytes(head.cfg, res.model.materials, dataclasses.replace(storage, table_bits=8))
    assert res.components["appearance"] == expected["appearance"] == eight["appearance"]
    decoded = decode_nbvh(res.data).appearance
    assert torch.equal(decoded.encoding.qcodes.cpu(), head.encoding.qcodes.cpu())
