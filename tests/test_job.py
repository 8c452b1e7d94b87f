"""The add-on's job runner (addon/job.py, no bpy) driving real `python -m nbvh_core job` processes."""
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from addon.job import JobQueue, check_python  # noqa: E402


def make_request(tmp_path, sample_meshes, name="blob", **settings):
    mesh = sample_meshes["blob"]
    mesh_path = tmp_path / f"{name}.npz"
    np.savez(mesh_path, vertices=mesh.vertices, faces=mesh.faces)
    return {"name": name, "mesh": str(mesh_path), "out_dir": str(tmp_path / "out"), "proxy_points": 500,
            "settings": {"preset": "tiny", **settings},
            "camera": {"position": [2.0, 1.5, 2.0], "target": [0.5, 0.5, 0.5], "up": [0, 1, 0], "fov_deg": 40,
                       "width": 40, "height": 30}}


def test_check_python():
    ok, msg = check_python(sys.executable)
    assert ok, msg
    bad, msg = check_python("/nonexistent/python")
    assert not bad and "cannot run" in msg


def test_job_produces_all_outputs_and_result(tmp_path, sample_meshes):
    q = JobQueue(sys.executable)
    # Enough training that the model predicts surface hits (20 tiny steps may predict none: an empty proxy).
    job = q.submit("blob", make_request(tmp_path, sample_meshes, steps=150, rays_per_step=1024))
    seen = []
    q.wait(on_event=lambda j, e: seen.append(e), timeout=300)
    assert job.state == "done", job.error
    files = job.result["files"]
    for key in ("model", "preview", "reference", "points", "report"):
        assert Path(files[key]).exists(), key
    pts = np.load(files["points"])
    assert pts.shape[1] == 6 and 0 < len(pts) <= 500
    report = json.loads(Path(files["report"]).read_text())
    assert report["file_bytes"] == Path(files["model"]).stat().st_size
    from PIL import Image

    assert Image.open(files["preview"]).size == (40, 30)
    assert any(e["event"] == "progress" for e in seen)
    assert not job.workdir.exists()  # temporary folder removed


def test_jobs_run_one_at_a_time_and_cancel_cleans_up(tmp_path, sample_meshes):
    q = JobQueue(sys.executable)
    first = q.submit("slow", make_request(tmp_path, sample_meshes, name="slow", steps=100000, time_limit_s=600))
    second = q.submit("next", make_request(tmp_path, sample_meshes, name="next"))
    t0 = time.monotonic()
    while first.progress.get("step", 0) < 2 and time.monotonic() - t0 < 120:
        q.step()
        assert second.state == "queued"  # never two at once
        time.sleep(0.1)
    assert first.state == "running"
    q.cancel_all()
    assert first.state == second.state == "cancelled"
    assert not first.workdir.exists() and not second.workdir.exists()
    out = tmp_path / "out"
    # Nothing half-written left behind; only the cancelled training's checkpoint stays (the panel offers Resume).
    left = sorted(p.name for p in out.iterdir()) if out.exists() else []
    assert left in ([], [".slow.nbvh.checkpoint"]), left


def test_damaged_model_and_bad_mesh_fail_with_message(tmp_path, sample_meshes):
    q = JobQueue(sys.executable)
    damaged = tmp_path / "damaged.nbvh"
    damaged.write_bytes(b"NBVH\0\r\n\x1a" + b"\x01\x00\x00\x00" + b"\0" * 64)  # right magic and version, bad body
    a = q.submit("load", dict(make_request(tmp_path, sample_meshes, name="load"), model=str(damaged)))
    bad = make_request(tmp_path, sample_meshes, name="nan")
    np.savez(bad["mesh"], vertices=np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], np.float32),
             faces=np.array([[0, 1, 2]], np.int32))
    b = q.submit("nan", bad)
    q.wait(timeout=300)
    assert a.state == "failed" and "checksum" in a.error
    assert b.state == "failed" and "NaN" in b.error
    assert damaged.exists()  # the user's file is never deleted
