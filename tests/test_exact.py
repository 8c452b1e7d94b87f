import numpy as np
import pytest

from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.training.rays import RayConfig, root_box, sample_rays

from meshes import icosphere


def test_sphere_distances_are_exact():
    mesh = icosphere(5)
    tracer = ExactTracer(mesh)
    assert tracer.backend == "embree"
    n = 2000
    rng = np.random.default_rng(0)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.full((n, 3), 0.5) - 2 * d  # aimed at the centre from distance 2
    fh = tracer.first_hit(o.astype(np.float32), d.astype(np.float32))
    assert fh.hit.all()
    # An icosphere's faces lie within (1 - cos(edge angle)) of the unit sphere; radius is 0.5 here.
    assert np.allclose(fh.t, 1.5, atol=2e-3)
    # Geometric normals of the hit faces point outward, against the ray.
    assert (np.einsum("ij,ij->i", fh.normal, d) < -0.99).all()
    allh = tracer.all_hits(o.astype(np.float32), d.astype(np.float32))
    assert (np.diff(allh.offsets) == 2).all()
    assert np.allclose(allh.t[1::2], 2.5, atol=2e-3)


@pytest.mark.parametrize("name", ["blob", "gyroid", "terrain"])
def test_numpy_fallback_agrees_with_embree(sample_meshes, sample_bvhs, name):
    mesh = sample_meshes[name]
    emb = ExactTracer(mesh, backend="embree")
    ref = ExactTracer(mesh, backend="numpy")
    lo, hi = root_box(sample_bvhs[name])
    o, d = sample_rays(lo, hi, 3000, np.random.default_rng(1), RayConfig())
    a, b = emb.first_hit(o, d), ref.first_hit(o, d)
    assert np.array_equal(a.hit, b.hit)
    assert np.allclose(a.t[a.hit], b.t[b.hit], atol=1e-5)
    # Same triangle except at shared edges, where the normal may differ; compare the hit points instead.
    assert (a.tri == b.tri).mean() > 0.995
    A, B = emb.all_hits(o, d), ref.all_hits(o, d)
    assert np.array_equal(A.offsets, B.offsets)
    assert np.allclose(A.t, B.t, atol=1e-4)


@pytest.mark.parametrize("name", ["blob", "gyroid"])
def test_all_hits_from_a_known_first_hit_are_the_same(sample_meshes, sample_bvhs, name):
    tracer = ExactTracer(sample_meshes[name], backend="embree")
    o, d = sample_rays(*root_box(sample_bvhs[name]), 3000, np.random.default_rng(2), RayConfig())
    t_max = np.random.default_rng(3).uniform(0.0, 2.0, len(o))  # some first hits lie beyond t_max
    plain = tracer.all_hits(o, d, t_max=t_max)
    reused = tracer.all_hits(o, d, t_max=t_max, first=tracer.first_hit(o, d))
    assert len(plain.t) > 500 and (np.diff(plain.offsets) > 1).any()  # rays with several hits
    for field in ("ray", "t", "tri", "offsets"):
        assert np.array_equal(getattr(plain, field), getattr(reused, field)), field


def test_t_max_respected(sample_meshes):
    tracer = ExactTracer(sample_meshes["blob"])
    o = np.array([[0.5, 0.5, -1.0]], np.float32)
    d = np.array([[0, 0, 1.0]], np.float32)
    full = tracer.first_hit(o, d)
    assert full.hit[0]
    short = tracer.first_hit(o, d, t_max=full.t[0] * 0.9)
    assert not short.hit[0] and np.isinf(short.t[0]) and short.tri[0] == -1
    allh = tracer.all_hits(o, d, t_max=full.t[0] * 1.0001)
    assert len(allh.t) == 1


def test_empty_batch(sample_meshes):
    tracer = ExactTracer(sample_meshes["blob"])
    z = np.zeros((0, 3), np.float32)
    assert tracer.first_hit(z, z).t.shape == (0,)
    assert tracer.all_hits(z, z).offsets.tolist() == [0]


@pytest.mark.parametrize("compact", [False, True])
def test_the_shared_embree_scene_answers_as_embreex(sample_meshes, sample_bvhs, compact):
    """The scene on the mesh's own arrays (embree_scene.py, traced by native/embree_rays.cpp) against embreex's:
    the same triangles and distances, in both of its layouts."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    from nbvh_core.geometry.embree_scene import EmbreeScene, embree_library

    mesh = sample_meshes["gyroid"]
    ours = EmbreeScene(embree_library(), mesh.vertices, mesh.faces, compact=compact)
    theirs = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=theirs, vertices=mesh.vertices, indices=mesh.faces)
    o, d = sample_rays(*root_box(sample_bvhs["gyroid"]), 4000, np.random.default_rng(4), RayConfig())
    t_max = np.random.default_rng(5).uniform(0.2, 2.0, len(o)).astype(np.float32)
    t, prim = ours.intersect(o, d, t_max)
    ref = theirs.run(o, d, dists=t_max.copy(), query="INTERSECT", output=1)
    hit = prim >= 0
    assert 500 < hit.sum() < len(o)  # hits, misses, and hits cut by t_max
    assert np.array_equal(prim, ref["primID"])
    assert np.allclose(t[hit], ref["tfar"][hit], rtol=0, atol=1e-6)
    assert (t[hit] <= t_max[hit]).all()


def test_the_tracer_pads_a_vertex_array_that_lacks_the_spare_row(sample_meshes):
    """Embree reads 4 bytes past the last shared vertex: a mesh's loaded vertices carry a spare row (no copy); an
    array without one is copied into one that has it, and traces the same."""
    import dataclasses

    from nbvh_core.geometry.embree_scene import padded_vertices

    mesh = sample_meshes["blob"]
    assert padded_vertices(mesh.vertices) is mesh.vertices or np.shares_memory(padded_vertices(mesh.vertices),
                                                                               mesh.vertices)
    bare = dataclasses.replace(mesh, vertices=mesh.vertices.copy())  # exactly (V, 3): nothing after it
    padded = padded_vertices(bare.vertices)
    assert not np.shares_memory(padded, bare.vertices) and np.array_equal(padded, bare.vertices)
    o = np.full((50, 3), 0.5, np.float32) + np.float32(2) * np.eye(3, dtype=np.float32)[np.arange(50) % 3]
    d = (np.full((50, 3), 0.5, np.float32) - o).astype(np.float32)
    a, b = ExactTracer(mesh).first_hit(o, d), ExactTracer(bare).first_hit(o, d)
    assert a.hit.all() and np.array_equal(a.tri, b.tri) and np.array_equal(a.t, b.t)
