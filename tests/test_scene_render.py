"""The render engine's compute (nbvh_core.rendering.scene_render), its worker process (nbvh_core.app.render_worker) and the
add-on's torch-free client (addon/render_client.py), outside Blender."""
import math
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nbvh_core.rendering import scene_render as sr
from nbvh_core.rendering.scene_render import look_at, perspective
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.geometry.mesh import mesh_from_arrays
from nbvh_core.app.pipeline import compress_mesh
from nbvh_core.planning.settings import preset

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from addon.render_client import RenderWorker, WorkerError  # noqa: E402


def camera(eye=(0.0, -4.0, 2.0), target=(0.0, 0.0, 0.0), width=64, height=48):
    return sr.view_projection(look_at(eye, target), perspective(math.radians(40), width / height))


def trs(translate=(0, 0, 0), rot_z=0.0, scale=1.0) -> np.ndarray:
    c, s = math.cos(rot_z), math.sin(rot_z)
    m = np.eye(4)
    m[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) * scale
    m[:3, 3] = translate
    return m


def save_mesh(path: Path, vertices, faces) -> str:
    np.savez(path, vertices=np.asarray(vertices, np.float32), faces=np.asarray(faces, np.int32))
    return str(path)


PLANE_V = [[-3, -3, 0], [3, -3, 0], [3, 3, 0], [-3, 3, 0]]
PLANE_F = [[0, 1, 2], [0, 2, 3]]


def box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6], [0, 2, 6],
         [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return v, np.array(f)


@pytest.fixture(scope="module")
def blob_files(sample_meshes, tmp_path_factory):
    """The blob as an object-local mesh (original units) and a quickly trained model of it."""
    d = tmp_path_factory.mktemp("scene")
    mesh = sample_meshes["blob"]
    local = mesh.transform.to_original(mesh.vertices)
    mesh_path = save_mesh(d / "blob.npz", local, mesh.faces)
    model_path = d / "blob.nbvh"
    compress_mesh(mesh, preset("preview").with_overrides(force=True, time_limit_s=None, steps=400), model_path,
                  evaluate_quality=False)
    return {"mesh": mesh_path, "model": str(model_path), "dir": d, "extent": float(np.ptp(local, axis=0).max())}


def test_camera_rays_follow_blenders_matrices():
    cam = camera(eye=(0, -4, 0), target=(0, 0, 0), width=3, height=3)
    o, d = sr.camera_rays(cam, 3, 3)
    centre = d[4]
    assert np.allclose(centre, [0, 1, 0], atol=1e-9)  # the middle pixel looks at the target
    assert d[0, 2] < 0 and d[8, 2] > 0  # row 0 is the bottom of the image
    assert np.allclose(o[4], [0, -4 + 0.05, 0], atol=1e-6)  # rays start on the near plane


def test_mesh_object_at_its_transform_matches_tracing_the_world_mesh(tmp_path, sample_meshes):
    mesh = sample_meshes["bunny"]
    local = mesh.transform.to_original(mesh.vertices)
    matrix = trs((0.3, -0.2, 0.1), rot_z=0.7, scale=1.7 / float(np.ptp(local, axis=0).max()))
    spec = sr.SceneSpec.from_dict({"objects": [{"name": "bunny", "matrix": matrix.tolist(),
                                                "mesh": save_mesh(tmp_path / "b.npz", local, mesh.faces)}],
                                   "lights": [], "shading": "cosine"})
    r = sr.SceneRenderer()
    assert r.set_scene(spec) == []
    cam = camera(width=80, height=60)
    o, d = sr.camera_rays(cam, 80, 60)
    got = r.nearest(o, d)
    world = (np.c_[local, np.ones(len(local))] @ matrix.T)[:, :3]
    exact = ExactTracer(mesh_from_arrays(world, mesh.faces))
    on = exact.mesh.transform.to_normalised(o)
    want = exact.first_hit(on.astype(np.float32), d.astype(np.float32))
    assert (got.hit == want.hit).mean() > 0.999 and got.hit.sum() > 300
    both = got.hit & want.hit
    assert np.allclose(got.t[both], exact.mesh.transform.distance_to_original(want.t[both]), rtol=1e-4, atol=1e-4)


def test_lambert_units_shadows_and_ambient(tmp_path):
    """A white plane under a sun of strength S: radiance albedo * (world + S cos / pi); the box's shadow is
    only the ambient term; without shadows it is lit."""
    v, f = box((-0.5, -0.5, 0.5), (0.5, 0.5, 1.5))
    objects = [{"name": "plane", "matrix": np.eye(4).tolist(), "mesh": save_mesh(tmp_path / "p.npz", PLANE_V, PLANE_F),
                "color": [0.5, 0.5, 0.5]},
               {"name": "box", "matrix": np.eye(4).tolist(), "mesh": save_mesh(tmp_path / "b.npz", v, f)}]
    sun = {"kind": "sun", "color": [1, 1, 1], "power": 2.0, "direction": [0, 0, -1]}
    world = [0.1, 0.1, 0.1]
    r = sr.SceneRenderer()
    r.set_scene(sr.SceneSpec.from_dict({"objects": objects, "lights": [sun], "world": world}))
    down = sr.view_projection(look_at((0, 0, 10), (0, 0, 0), up=(0, 1, 0)), perspective(math.radians(30), 1.0))
    img = r.render(down, 41, 41)
    lit, shadow = img[2, 2, :3], img[20, 20, :3]  # corner: the plane in the sun; centre: the box's top face
    assert np.allclose(lit, 0.5 * (0.1 + 2.0 / math.pi), rtol=1e-4)
    assert np.allclose(shadow, 0.8 * (0.1 + 2.0 / math.pi), rtol=1e-4)  # the box top is lit, albedo 0.8
    # Light travelling toward +y and down: the box's shadow falls on the plane at y > 0.5.
    slanted = dict(sun, direction=[0, 0.6, -0.8])
    r.set_scene(sr.SceneSpec.from_dict({"objects": objects, "lights": [slanted], "world": world}))
    o, d = np.array([[0.0, 0.9, 5.0], [0.0, -0.9, 5.0]]), np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    in_shadow, in_sun = r._shade(o, d, None)[:, :3]
    assert np.allclose(in_shadow, 0.5 * 0.1, rtol=1e-4)  # ambient only
    assert np.allclose(in_sun, 0.5 * (0.1 + 2.0 * 0.8 / math.pi), rtol=1e-4)
    r.set_scene(sr.SceneSpec.from_dict({"objects": objects, "lights": [slanted], "world": world, "shadows": False}))
    assert np.allclose(r._shade(o, d, None)[0, :3], in_sun, rtol=1e-4)


def test_point_light_falls_off_with_distance_squared(tmp_path):
    objects = [{"name": "plane", "matrix": np.eye(4).tolist(), "color": [1, 1, 1],
                "mesh": save_mesh(tmp_path / "p.npz", PLANE_V, PLANE_F)}]
    r = sr.SceneRenderer()
    o, d = np.array([[0.0, 0.0, 5.0], [2.0, 0.0, 5.0]]), np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    r.set_scene(sr.SceneSpec.from_dict({"objects": objects, "world": [0, 0, 0],
                                        "lights": [{"kind": "point", "power": 100.0, "position": [0, 0, 2]}]}))
    below, aside = r._shade(o, d, None)[:, 0]
    assert below == pytest.approx(100 / (4 * math.pi * 4) / math.pi, rel=1e-4)
    # 2 m aside: distance^2 = 8, cos = 2 / sqrt(8)
    assert aside == pytest.approx(100 / (4 * math.pi * 8) * (2 / math.sqrt(8)) / math.pi, rel=1e-4)


def test_neural_object_matches_its_mesh_at_a_transform(blob_files):
    """The same object drawn from its model and from its mesh (a rotated, scaled, moved instance beside another
    copy): the silhouettes and the shading agree."""
    s = 1.2 / blob_files["extent"]
    objects = [{"name": f"blob{i}", "matrix": trs((1.0 * i - 0.5, 0, 0), rot_z=0.9 * i, scale=s).tolist(),
                "model": blob_files["model"], "mesh": blob_files["mesh"]} for i in range(2)]
    scene = {"objects": objects, "lights": [{"kind": "point", "power": 400.0, "position": [2, -3, 3]}]}
    cam = camera(width=96, height=72)
    images = {}
    for geometry in ("neural", "mesh"):
        r = sr.SceneRenderer()
        assert r.set_scene(sr.SceneSpec.from_dict(dict(scene, geometry=geometry))) == []
        images[geometry] = r.render(cam, 96, 72)
        assert len(r._cache) == 1  # one file loaded for both instances
    a, b = images["neural"], images["mesh"]
    fg_a, fg_b = a[..., 3] > 0, b[..., 3] > 0
    assert fg_b.sum() > 500
    assert (fg_a & fg_b).sum() / (fg_a | fg_b).sum() > 0.95
    # on the pixels both draw (the background would dilute it): recorded 0.000197; a 2x regression fails
    both = fg_a & fg_b
    assert float(((np.clip(a[..., :3], 0, 1) - np.clip(b[..., :3], 0, 1))[both] ** 2).mean()) < 0.00035


def test_bad_objects_are_left_out_with_a_reason(tmp_path, blob_files):
    broken = tmp_path / "broken.nbvh"
    broken.write_bytes(b"not a model")
    r = sr.SceneRenderer()
    warnings = r.set_scene(sr.SceneSpec.from_dict({"objects": [
        {"name": "good", "matrix": np.eye(4).tolist(), "mesh": blob_files["mesh"]},
        {"name": "broken", "matrix": np.eye(4).tolist(), "model": str(broken)},
        {"name": "flat", "matrix": np.diag([1, 1, 0, 1]).tolist(), "mesh": blob_files["mesh"]},
        {"name": "nothing", "matrix": np.eye(4).tolist()}]}))
    assert [w.split(":")[0] for w in warnings] == ["broken", "flat", "nothing"]
    assert [p.name for p in r.placed] == ["good"]
    with pytest.raises(ValueError, match="shading"):
        sr.SceneSpec.from_dict({"objects": [], "shading": "phong"})


def test_worker_progressive_frames_supersede_and_survive_errors(blob_files):
    worker = RenderWorker(sys.executable)
    try:
        sid = worker.set_scene({"objects": [{"name": "blob", "matrix": trs(scale=1 / blob_files["extent"]).tolist(),
                                             "model": blob_files["model"]}],
                                "lights": [{"kind": "sun", "power": 3.0, "direction": [0, 0.5, -1]}]})
        assert worker.wait(lambda: worker.scene_done >= sid, timeout=60) and worker.warnings == []
        frames = []
        ch = None
        worker.request("view", camera(width=160, height=120), 160, 120, levels=(4, 2, 1))
        ch = worker.channels["view"]
        deadline = time.monotonic() + 60
        while ch.pending and time.monotonic() < deadline:
            if worker.poll():
                frames.append((ch.frame.level, ch.frame.pixels.shape))
            time.sleep(0.01)
        assert not ch.pending and ch.error is None
        assert frames[-1] == (1, (120, 160, 4)) and all(s == (120 // lv, 160 // lv, 4) for lv, s in frames)
        assert [lv for lv, _ in frames] == sorted([lv for lv, _ in frames], reverse=True)  # coarse first
        assert not list(Path(worker.frames_dir).iterdir())  # every frame file taken and removed
        # A burst of requests (the view moving): only the newest is answered in full.
        ids = [worker.request("view", camera(eye=(x, -4, 2), width=320, height=240), 320, 240, levels=(4, 2, 1))
               for x in np.linspace(-1, 1, 6)]
        assert worker.wait(lambda: not ch.pending, timeout=120)
        assert ch.frame.id == ids[-1] and ch.frame.last
        # A bad request and a bad scene: errors, and the worker goes on.
        worker.request("view", camera(), 0, 10)
        assert worker.wait(lambda: not ch.pending, timeout=30) and "out of range" in ch.error
        sid = worker.set_scene({"objects": [], "shading": "phong"})
        assert worker.wait(lambda: worker.scene_done >= sid, timeout=30) and "shading" in worker.warnings[0]
        assert worker.alive
    finally:
        worker.stop()
    assert not worker.alive and not Path(worker.frames_dir).exists()


def test_worker_death_is_reported():
    worker = RenderWorker(sys.executable)
    worker._proc.kill()
    worker._proc.wait()
    with pytest.raises(WorkerError, match="not running|stopped"):
        worker.set_scene({"objects": []})
    worker.stop()
    with pytest.raises(WorkerError, match="cannot start"):
        RenderWorker("/nonexistent/python")
