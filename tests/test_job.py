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
    job = q.submit("blob", make_request(tmp_path, sample_meshes, steps=150, rays_per_step=1024, force=True))
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


def test_job_eta_covers_every_phase_and_every_training_of_a_target_search(monkeypatch):
    """The whole-job ETA: a retrain target search may train TARGET_TRAININGS times, each its time limit, each followed
    by an evaluation (timed in this job once seen), then the preview; the default growing search trains once."""
    import addon.job as job_mod

    now = [100.0]
    monkeypatch.setattr(job_mod.time, "monotonic", lambda: now[0])
    req = {"settings": {"time_limit_s": 60, "target_mse": 0.01, "size_search": "retrain"}}
    clock = job_mod.JobClock()
    g, f = job_mod.EVAL_GUESS_S, job_mod.FINISH_GUESS_S
    assert clock.estimate(req) == 3 * (60 + g) + f
    assert clock.estimate({"settings": {"time_limit_s": 60, "target_mse": 0.01}}) == 60 + g + f
    assert clock.estimate({"settings": {"time_limit_s": 60}}) == 60 + g + f
    assert clock.remaining(req) == 3 * (60 + g) + f  # planning: nothing trained yet
    clock.see({"event": "phase", "phase": "train", "message": "hashgrid+mlp"})
    clock.see({"event": "progress", "phase": "train", "eta_s": 40.0})
    assert clock.remaining(req) == 40 + g + 2 * (60 + g) + f
    now[0] += 10  # the ETA runs down between progress events
    assert clock.remaining(req) == 30 + g + 2 * (60 + g) + f
    clock.see({"event": "phase", "phase": "eval", "message": "16 views"})
    now[0] += 7
    clock.see({"event": "phase", "phase": "search", "message": "trying T=2^12"})
    assert clock.eval_seconds == 7
    clock.see({"event": "phase", "phase": "train", "message": "hashgrid+mlp"})
    clock.see({"event": "progress", "phase": "train", "eta_s": 50.0})
    assert clock.remaining(req) == 50 + 7 + (60 + 7) + f  # one training may follow, evaluations timed
    clock.see({"event": "phase", "phase": "preview", "message": "256x256"})
    assert clock.remaining(req) == f
    # A run by steps (no time limit) has no ETA until training reports one.
    steps = job_mod.JobClock()
    assert steps.estimate({"settings": {"steps": 500}}) is None
    steps.see({"event": "phase", "phase": "train", "message": "x"})
    assert steps.remaining({"settings": {"steps": 500}}) is None
    steps.see({"event": "progress", "phase": "train", "eta_s": 12.0})
    assert steps.remaining({"settings": {"steps": 500}}) == 12 + g + f
