import gzip
import warnings

import numpy as np
import pytest
import trimesh

from nbvh_core.geometry.mesh import MeshError, MeshWarning, load_mesh, mesh_from_arrays

TET_V = np.array([[0, 0, 0], [2, 0, 0], [0, 3, 0], [0, 0, 4]], float)
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def test_arrays_normalised_into_unit_box_and_transform_maps_back():
    m = mesh_from_arrays(TET_V + 10, TET_F)
    assert m.vertices.dtype == np.float32 and m.faces.dtype == np.int32
    assert m.vertices.min() >= 0 and m.vertices.max() <= 1
    ext = m.vertices.max(0) - m.vertices.min(0)
    assert ext.max() == pytest.approx(1.0)
    # Centred in the box.
    assert np.allclose((m.vertices.max(0) + m.vertices.min(0)) / 2, 0.5, atol=1e-6)
    assert np.allclose(m.transform.to_original(m.vertices), TET_V + 10, atol=1e-5)
    assert m.transform.distance_to_original(1.0) == pytest.approx(4.0)


def test_input_arrays_not_modified():
    v, f = TET_V.copy(), TET_F.copy()
    mesh_from_arrays(v, f)
    assert np.array_equal(v, TET_V) and np.array_equal(f, TET_F)


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "off", "glb"])
def test_load_formats(tmp_path, ext):
    src = trimesh.Trimesh(TET_V, TET_F, process=False)
    path = tmp_path / f"tet.{ext}"
    src.export(path)
    m = load_mesh(path)
    assert m.n_triangles == 4
    corners = np.unique(np.round(m.transform.to_original(m.vertices), 4), axis=0)  # STL repeats corners
    assert np.allclose(corners, np.unique(TET_V, axis=0), atol=1e-4)


def test_load_gltf_scene_with_transforms(tmp_path):
    scene = trimesh.Scene()
    a = trimesh.creation.box()
    scene.add_geometry(a, transform=trimesh.transformations.translation_matrix([5, 0, 0]))
    scene.add_geometry(a.copy())
    path = tmp_path / "two.gltf"
    scene.export(path)
    m = load_mesh(path)
    assert m.n_triangles == 24
    orig = m.transform.to_original(m.vertices)
    assert orig[:, 0].max() == pytest.approx(5.5, abs=1e-5)


def test_load_gzip(tmp_path):
    path = tmp_path / "tet.ply"
    trimesh.Trimesh(TET_V, TET_F, process=False).export(path)
    gz = tmp_path / "tet.ply.gz"
    gz.write_bytes(gzip.compress(path.read_bytes()))
    assert load_mesh(gz).n_triangles == 4


@pytest.mark.parametrize("vertices,faces,message", [
    (np.zeros((0, 3)), np.zeros((0, 3), int), "empty"),
    (TET_V, np.zeros((0, 3), int), "empty"),
    (np.where(np.arange(12).reshape(4, 3) == 4, np.nan, TET_V), TET_F, "NaN or infinite"),
    (np.where(np.arange(12).reshape(4, 3) == 7, np.inf, TET_V), TET_F, "NaN or infinite"),
    (TET_V, TET_F + 1, "out of range"),
    (TET_V, TET_F - 1, "out of range"),
    (TET_V, np.array([[0, 1, 2, 3]]), "triangles"),
    (TET_V, np.array([[0.5, 1, 2]]), "integers"),
    (TET_V[:, :2], TET_F, r"\(V, 3\)"),
    (np.zeros((4, 3)), TET_F, "degenerate"),
])
def test_bad_arrays_refused(vertices, faces, message):
    with pytest.raises(MeshError, match=message), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh_from_arrays(vertices, faces, name="bad")


def test_degenerate_triangles_dropped_with_count():
    faces = np.vstack([TET_F, [[0, 0, 1], [1, 2, 2], [0, 1, 1]]])
    with pytest.warns(MeshWarning, match="dropped 3 degenerate"):
        m = mesh_from_arrays(TET_V, faces)
    assert m.n_triangles == 4
    assert "dropped 3" in m.repairs[0]


def test_collinear_triangle_dropped():
    v = np.vstack([TET_V, [[1, 0, 0]]])  # vertex 4 on the edge 0-1: triangle (0, 1, 4) has zero area
    with pytest.warns(MeshWarning, match="dropped 1"):
        m = mesh_from_arrays(v, np.vstack([TET_F, [[0, 1, 4]]]))
    assert m.n_triangles == 4


def test_file_errors(tmp_path):
    with pytest.raises(MeshError, match="no such file"):
        load_mesh(tmp_path / "missing.obj")
    with pytest.raises(MeshError, match="unsupported format"):
        (tmp_path / "x.blend").write_bytes(b"BLENDER")
        load_mesh(tmp_path / "x.blend")
    (tmp_path / "empty.ply").write_bytes(b"")
    with pytest.raises(MeshError, match="empty"):
        load_mesh(tmp_path / "empty.ply")
    (tmp_path / "broken.glb").write_bytes(b"glTF\x02\x00\x00\x00garbage")
    with pytest.raises(MeshError, match="broken.glb"):
        load_mesh(tmp_path / "broken.glb")
    (tmp_path / "broken.ply.gz").write_bytes(b"\x1f\x8b\x08\x00garbage")
    with pytest.raises(MeshError, match="gzip"):
        load_mesh(tmp_path / "broken.ply.gz")
    # A point cloud has no triangles.
    trimesh.PointCloud(TET_V).export(tmp_path / "points.ply")
    with pytest.raises(MeshError, match="no triangles"):
        load_mesh(tmp_path / "points.ply")


def test_nan_in_file_refused(tmp_path):
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="NaN"):
        load_mesh(tmp_path / "nan.obj")


def test_bundled_samples_have_their_character(sample_meshes):
    assert set(sample_meshes) == {"blob", "studs", "gyroid", "terrain", "bunny"}
    assert max(m.n_triangles for m in sample_meshes.values()) >= 200_000
    for m in sample_meshes.values():
        assert m.vertices.min() >= 0 and m.vertices.max() <= 1
    # terrain is open: boundary edges exist (edges used by one face only).
    f = sample_meshes["terrain"].faces
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 1).sum() > 100


def test_the_normals_of_some_triangles_are_those_of_the_whole_mesh(sample_meshes):
    """Normals of chosen triangles (the tracer's hits) are the same bits as the whole mesh's."""
    from nbvh_core.geometry.exact import ExactTracer

    mesh = sample_meshes["bunny"]
    pick = np.random.default_rng(0).integers(0, mesh.n_triangles, 5000)
    assert np.array_equal(mesh.face_normals(pick), mesh.face_normals()[pick])
    assert np.array_equal(ExactTracer(mesh, backend="numpy").normals(pick), mesh.face_normals()[pick])
