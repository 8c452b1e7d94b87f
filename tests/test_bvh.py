import time

import numpy as np
import pytest

from nbvh_core.geometry.bvh import NODE_DTYPE, BVH, build_bvh, build_full_tree, cut_tree, resident_bvh_nodes

from meshes import icosphere


def check_layout(bvh: BVH, mesh):
    nodes = bvh.nodes
    assert nodes.dtype.itemsize == 32 and len(bvh.to_bytes()) == 32 * bvh.n_nodes
    internal = np.flatnonzero(nodes["left"] > 0)
    children = np.concatenate([nodes["left"][internal], nodes["left"][internal] + 1])
    # Every node except the root (and the padding node) is the child of exactly one internal node.
    expected = set(range(1, bvh.n_nodes)) - ({1} if bvh.n_nodes % 2 == 0 else set())
    assert sorted(children.tolist()) == sorted(expected)
    # Parents contain their children.
    for k in (0, 1):
        c = nodes["left"][internal] + k
        assert (nodes["lo"][c] >= nodes["lo"][internal]).all() and (nodes["hi"][c] <= nodes["hi"][internal]).all()
    # Leaves own disjoint triangle sets covering the mesh, and contain their triangles.
    assert np.array_equal(np.sort(bvh.tri_order), np.arange(mesh.n_triangles))
    assert bvh.leaf_tri_count.sum() == mesh.n_triangles and (bvh.leaf_tri_count > 0).all()
    lo, hi = bvh.leaf_boxes()
    tri = mesh.triangles()
    assert (tri.min(1) >= lo[bvh.tri_leaf]).all() and (tri.max(1) <= hi[bvh.tri_leaf]).all()
    for leaf in range(0, bvh.n_leaves, max(1, bvh.n_leaves // 50)):
        assert (bvh.tri_leaf[bvh.leaf_triangles(leaf)] == leaf).all()
    # Leaf ordinals are stored in the spare bytes.
    assert np.array_equal(nodes["leaf"][bvh.leaf_node], np.arange(bvh.n_leaves))


@pytest.fixture(scope="module")
def big_sphere():
    mesh = icosphere(6, noise=0.0005)  # 81920 triangles: enough leaves for any budget
    return mesh, build_full_tree(mesh)


@pytest.mark.parametrize("budget", [1, 2, 3, 4, 5, 6, 100, 101, 4096, 4097, 65534, 65535])
def test_exact_node_budget(big_sphere, budget):
    mesh, tree = big_sphere
    bvh = cut_tree(tree, budget)
    assert bvh.n_nodes == budget
    assert bvh.n_leaves == (budget + 1) // 2
    check_layout(bvh, mesh)


def test_even_budget_has_one_empty_padding_node():
    bvh = build_bvh(icosphere(3), 8)
    assert bvh.nodes["left"][1] == 0 and bvh.nodes["leaf"][1] == -1
    assert np.isinf(bvh.nodes["lo"][1]).all() and (bvh.nodes["lo"][1] > bvh.nodes["hi"][1]).all()
    assert (bvh.nodes["left"][bvh.nodes["left"] > 0] % 2 == 0).all()  # sibling pairs start at even indices


def test_samples_layout(sample_meshes, sample_bvhs):
    for name, bvh in sample_bvhs.items():
        assert bvh.n_nodes == 4096, name
        check_layout(bvh, sample_meshes[name])


def test_invalid_budget_and_too_few_triangles():
    mesh = icosphere(0)  # 20 triangles
    with pytest.raises(ValueError, match="node budget"):
        build_bvh(mesh, 0)
    with pytest.raises(ValueError, match="node budget"):
        build_bvh(mesh, 65536)
    with pytest.warns(UserWarning, match="too few triangles"):
        bvh = build_bvh(mesh, 4096)
    assert bvh.n_leaves == 20 and bvh.n_nodes == 39
    check_layout(bvh, mesh)


def test_sah_beats_median_split_cost():
    """On unevenly spread triangles, the SAH tree's cost (sum of area x triangles) beats object-median splits."""
    import trimesh

    from nbvh_core.geometry.mesh import mesh_from_arrays

    big, small = trimesh.creation.icosphere(2), trimesh.creation.icosphere(4)
    v = np.vstack([big.vertices, small.vertices * 0.05 + [3, 0, 0]])
    mesh = mesh_from_arrays(v, np.vstack([big.faces, small.faces + len(big.vertices)]))
    sah = build_full_tree(mesh, max_leaf_size=1, median_below=1)
    median = build_full_tree(mesh, max_leaf_size=1, median_below=10**9)

    def cost(t):
        d = np.maximum(t.hi.astype(float) - t.lo, 0)
        area = d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0]
        return (area * t.count).sum() / area[0]

    assert cost(sah) < cost(median) * 0.97


def test_nodes_roundtrip_bytes(sample_bvhs):
    bvh = sample_bvhs["blob"]
    again = BVH.nodes_from_bytes(bvh.to_bytes())
    assert again.dtype == NODE_DTYPE and again.tobytes() == bvh.to_bytes()
    with pytest.raises(ValueError):
        BVH.nodes_from_bytes(bvh.to_bytes()[:-3])


def test_resident_node_count_matches_leaf_size():
    mesh = icosphere(4)
    tree = build_full_tree(mesh, max_leaf_size=1)
    n4 = resident_bvh_nodes(tree, 4)
    tree4 = build_full_tree(mesh, max_leaf_size=4)
    assert n4 == tree4.n_nodes
    assert resident_bvh_nodes(tree, 1) == tree.n_nodes == 2 * mesh.n_triangles - 1


def test_build_is_fast_on_large_mesh(sample_meshes):
    # A loose bound (CI noise): the 211k-triangle sample builds well under a minute even on 2 slow cores.
    t = time.perf_counter()
    build_bvh(sample_meshes["studs"], 4096)
    assert time.perf_counter() - t < 60


def test_tree_cut_refinement_splits_the_worst_leaves_up_to_the_budget(sample_meshes):
    from nbvh_core.geometry.bvh import coarse_cut, refine_cut

    full = build_bvh(sample_meshes["blob"], 255)
    coarse = coarse_cut(full, 64)
    assert coarse.n_leaves == 64 and coarse.n_nodes == 127 and coarse.budget == 255
    scores = np.zeros(64)
    scores[[5, 9]] = [2.0, 1.0]  # the two worst leaves
    refined, parent = refine_cut(coarse, scores, 2)
    assert refined.n_leaves == 66 and refined.n_nodes == 131
    # The two new pairs come from leaves 5 and 9; every other leaf is carried over once.
    assert sorted(np.bincount(parent, minlength=64)[[5, 9]]) == [2, 2]
    assert np.bincount(parent, minlength=64).sum() == 66
    split_nodes = {int(coarse.leaf_full[5]), int(coarse.leaf_full[9])}
    assert not split_nodes & {int(n) for n in refined.leaf_full}
    # Every triangle still has exactly one owner, inside its leaf's box.
    assert np.bincount(refined.tri_leaf, minlength=refined.n_leaves).sum() == sample_meshes["blob"].n_triangles
    # Never beyond the budget: asking for 1000 splits stops at 128 leaves (255 nodes).
    full_cut, _ = refine_cut(refined, np.ones(refined.n_leaves), 1000)
    assert full_cut.n_leaves == 128 and full_cut.n_nodes == 255


def test_the_compiled_tree_builder_builds_the_numpy_tree_node_for_node(sample_meshes):
    """kernels/native/tree_build.cpp against the numpy build: the same boxes, links, ranges, depths and triangle
    order, on a scan, on every face twice (coincident centroids: the median split) and with 4 triangles per leaf."""
    from nbvh_core.kernels import library

    if library.load() is None:
        pytest.skip(f"no compiled kernels here: {library.describe()}")
    bunny, blob = sample_meshes["bunny"], sample_meshes["blob"]
    doubled = type(blob)(vertices=blob.vertices, faces=np.concatenate([blob.faces, blob.faces]),
                         transform=blob.transform, name="every face twice")
    for mesh, leaf in ((bunny, 1), (doubled, 1), (bunny, 4)):
        fast = build_full_tree(mesh, max_leaf_size=leaf)
        with library.using_path("reference"):
            ref = build_full_tree(mesh, max_leaf_size=leaf)
        for field in ("lo", "hi", "left", "start", "count", "depth", "tri_order"):
            assert np.array_equal(getattr(fast, field), getattr(ref, field)), (mesh.name, leaf, field)


def test_a_heavy_mesh_s_shared_tree_stops_at_four_triangles_with_the_same_nodes_above(monkeypatch, sample_meshes):
    """From SHALLOW_TREE_TRIANGLES the run's tree stops at 4 triangles per leaf: the same nodes of more than 4 (each
    the same range of the same triangles, in another order below), the same training cut; a third of the nodes."""
    from nbvh_core.geometry import bvh

    mesh = sample_meshes["bunny"]
    monkeypatch.setattr(bvh, "SHALLOW_TREE_TRIANGLES", mesh.n_triangles)  # the bunny as a heavy mesh
    shallow, full = bvh.shared_tree(mesh), build_full_tree(mesh)
    assert shallow.count[shallow.left < 0].max() <= 4 and shallow.n_nodes < 0.4 * full.n_nodes

    def above_four(tree):
        big = tree.count > 4
        return {(s, c, tuple(np.sort(tree.tri_order[s:s + c]).tolist()) if c > 1000 else None)
                for s, c in zip(tree.start[big].tolist(), tree.count[big].tolist())}
    assert above_four(shallow) == above_four(full)
    a, b = cut_tree(shallow, 2047), cut_tree(full, 2047)
    assert np.array_equal(a.nodes, b.nodes) and np.array_equal(a.tri_leaf, b.tri_leaf)
    monkeypatch.setattr(bvh, "SHALLOW_TREE_TRIANGLES", mesh.n_triangles + 1)  # below it: one triangle per leaf
    assert bvh.shared_tree(mesh).n_nodes == full.n_nodes
