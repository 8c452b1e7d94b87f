"""Library batches on an embedded Ray (2 workers): every asset accounted for, bad ones recorded, nothing trained twice,
a killed worker retried, the report complete."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from meshes import icosphere
from nbvh_core.app.library_assets import discover
from nbvh_core.app.library_batch import Row, _cached, run_batch
from nbvh_core.app.ray_tasks import task_resources
from nbvh_core.geometry.mesh import load_mesh

ROOT = Path(__file__).resolve().parents[1]
TINY = {"preset": "tiny"}
#: Every asset's model shipped: a tiny model loses to a decimation of its bytes after training (the verdict every
#: fixed size now gets), and these tests are about the batch's accounting, not the verdict.
FORCED = {"preset": "tiny", "force": True}

pytest.importorskip("ray")


def _obj_text(mesh) -> str:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    return "\n".join(lines) + "\n"


def make_library(root: Path) -> Path:
    """6 tiny assets: three worth compressing (blob, a sphere as .npz, a sphere as .obj in a subfolder), a copy of
    the blob under another name, one not worth it (80 triangles), one broken file."""
    (root / "props").mkdir(parents=True)
    shutil.copy(ROOT / "assets" / "blob.ply.gz", root / "blob.ply.gz")
    shutil.copy(ROOT / "assets" / "blob.ply.gz", root / "props" / "blob_copy.ply.gz")
    ico4 = icosphere(5, noise=0.02, seed=1)  # 20,480 triangles: ~95 KB as a compact mesh, more than a tiny model
    np.savez(root / "sphere.npz", vertices=ico4.vertices, faces=ico4.faces)
    (root / "props" / "bumpy.obj").write_text(_obj_text(icosphere(5, noise=0.05, seed=2)))
    tiny = icosphere(1)
    np.savez(root / "pebble.npz", vertices=tiny.vertices, faces=tiny.faces)
    (root / "props" / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    return root


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    return make_library(tmp_path_factory.mktemp("library"))


def test_discover_folder_and_list_file(library, tmp_path):
    names = [a.name for a in discover(library, tmp_path)]
    assert names == ["blob", "pebble", "props__blob_copy", "props__broken", "props__bumpy", "sphere"]
    listing = tmp_path / "list.txt"
    listing.write_text(f"# two of them\n{library / 'blob.ply.gz'}\n\n{library / 'sphere.npz'}\n")
    assert [a.source for a in discover(listing, tmp_path)] == [str(library / "blob.ply.gz"), str(library / "sphere.npz")]
    with pytest.raises(ValueError, match="no such folder"):
        discover(tmp_path / "missing", tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no mesh files"):
        discover(tmp_path / "empty", tmp_path)


def test_blend_without_blender_is_a_failed_row(tmp_path, monkeypatch):
    monkeypatch.setenv("NBVH_BLENDER", str(tmp_path / "no-such-blender"))
    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "scene.blend").write_bytes(b"BLENDER-v304")
    (asset,) = discover(tmp_path / "lib", tmp_path / "work")
    assert asset.name == "scene" and "could not run Blender" in asset.error


def test_task_resources_follow_the_triangles_and_fit_a_node():
    small = task_resources(10_000, {"max_node_cpus": 4, "max_node_memory": 8e9})
    big = task_resources(2_000_000, {"max_node_cpus": 4, "max_node_memory": 8e9, "GPU": 1})
    assert small["num_cpus"] == 1 and big["num_cpus"] == 2 and big["num_gpus"] == 1 and "num_gpus" not in small
    assert small["memory"] < big["memory"] <= 8e9
    assert task_resources(2_000_000, {"max_node_cpus": 1, "max_node_memory": 2e9})["num_cpus"] == 1  # fits a node


def test_batch_accounts_for_every_asset_and_a_rerun_trains_nothing(library, tmp_path):
    out = tmp_path / "out"
    events = []
    summary = run_batch(library, out, FORCED, events.append, num_cpus=2)
    rows = {r["name"]: r for r in summary["rows"]}
    assert set(rows) == {"blob", "pebble", "props__blob_copy", "props__broken", "props__bumpy", "sphere"}
    assert rows["props__broken"]["status"] == "failed" and "props/broken.ply" in rows["props__broken"]["error"]
    assert rows["pebble"]["status"] == "done"  # forced: trained though the verdict says not worth it
    for name in ("blob", "sphere", "props__bumpy"):
        r = rows[name]
        assert r["status"] == "done" and r["model_bytes"] > 0 and 0 < r["saved_bytes"] < r["mesh_resident_bytes"]
        assert (out / r["files"]["model"]).stat().st_size == r["model_bytes"]
        # The same result bundle as `compress` and the add-on's job write (result_bundle): report and preview.
        stem = str(out / r["files"]["model"])[:-len(".nbvh")]
        bundle_report = json.loads(Path(f"{stem}.report.json").read_text())
        assert bundle_report["file_bytes"] == r["model_bytes"] and bundle_report["mesh_resident_bytes"]["total"] > 0
        assert Path(f"{stem}.preview.png").read_bytes() == (out / "thumbs" / r["thumb_neural"]).read_bytes()
        assert (out / "thumbs" / r["thumb_original"]).exists() and (out / "thumbs" / r["thumb_neural"]).exists()
    # The copy has the blob's content: trained once, shared.
    assert rows["props__blob_copy"]["status"] == "cached" and rows["props__blob_copy"]["key"] == rows["blob"]["key"]
    trained = [e["name"] for e in events if e.get("event") == "asset" and e["phase"] == "train" and e["status"] == "done"]
    assert sorted(trained) == ["blob", "pebble", "props__bumpy", "sphere"]
    report = json.loads((out / "report.json").read_text())
    assert report["totals"]["by_status"] == {"cached": 1, "done": 4, "failed": 1}
    assert report["totals"]["saved_bytes"] == sum(r["saved_bytes"] for r in summary["rows"]) > 0
    html = (out / "report.html").read_text()
    assert "props__broken" in html and "<svg" in html and "thumbs/blob.neural.png" in html
    csv_lines = (out / "report.csv").read_text().splitlines()
    assert len(csv_lines) == 7 and csv_lines[0].startswith("name,source,status")
    # A rerun: every model found by content and settings, nothing trained.
    events2 = []
    again = run_batch(library, out, FORCED, events2.append, num_cpus=2)
    assert not [e for e in events2 if e.get("event") == "asset" and e["phase"] == "train"]
    assert {r["name"]: r["status"] for r in again["rows"]} == {**{n: "cached" for n in ("blob", "sphere", "props__bumpy",
                                                                                          "props__blob_copy", "pebble")},
                                                               "props__broken": "failed"}
    # Another setting is another result.
    assert _cached(out, rows["blob"]["key"]) is not None


def test_an_incomplete_result_is_not_taken_for_a_finished_one(tmp_path):
    folder = tmp_path / "assets" / "k1"
    folder.mkdir(parents=True)
    (folder / "m.nbvh").write_bytes(b"x" * 10)
    (folder / "result.json").write_text(json.dumps({"files": {"model": "m.nbvh"}, "model_bytes": 99}))
    assert _cached(tmp_path, "k1") is None  # the model is shorter than recorded
    (folder / "result.json").write_text("{not json")
    assert _cached(tmp_path, "k1") is None
    assert _cached(tmp_path, "k2") is None


def _ray_task_pids(name: str) -> list[int]:
    out = subprocess.run(["ps", "-eo", "pid,args"], capture_output=True, text=True).stdout
    return [int(line.split()[0]) for line in out.splitlines() if line.split()[1:2] == [f"ray::{name}"]]


def test_a_killed_worker_is_retried_and_the_result_is_complete(tmp_path):
    lib = tmp_path / "lib"
    lib.mkdir()
    shutil.copy(ROOT / "assets" / "blob.ply.gz", lib / "blob.ply.gz")
    out = tmp_path / "out"
    # Long enough to be killed mid-training (a few seconds of the tiny model).
    cmd = [sys.executable, "-m", "nbvh_core", "batch", str(lib), "-o", str(out), "--preset", "tiny", "--steps", "1500",
           "--force", "--num-cpus", "2", "--events"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    killed = None
    deadline = time.monotonic() + 120
    while killed is None and time.monotonic() < deadline and proc.poll() is None:
        pids = _ray_task_pids("compress_asset")
        if pids:
            time.sleep(1.0)  # mid-task
            os.kill(pids[0], signal.SIGKILL)
            killed = pids[0]
        time.sleep(0.1)
    stdout, stderr = proc.communicate(timeout=300)
    assert killed is not None, stderr[-2000:]
    assert proc.returncode == 0, stderr[-2000:]
    events = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
    done = [e for e in events if e.get("event") == "asset" and e["phase"] == "train"]
    assert [e["status"] for e in done] == ["done"]
    row = next(r for r in json.loads((out / "report.json").read_text())["rows"] if r["name"] == "blob")
    assert row["status"] == "done" and int(row["worker"].rsplit(":", 1)[1]) != killed  # another worker finished it
    assert (out / row["files"]["model"]).stat().st_size == row["model_bytes"]
    from nbvh_core.storage.fileformat import load_nbvh

    assert load_nbvh(out / row["files"]["model"]).metadata["training"]["steps"] == 1500  # the whole budget, rerun
    assert not list(out.rglob("*.partial-*"))


def test_row_savings_are_counted_only_for_finished_models():
    r = Row(name="a", source="a", status="failed", mesh_resident_bytes=1000, model_resident_bytes=10)
    assert r.saved_bytes == 0
    r.status = "done"
    assert r.saved_bytes == 990


def test_the_job_protocol_runs_a_measure_only_batch(library, tmp_path):
    """What the add-on's "Scene memory report" sends: a job request of kind batch; events end with the result."""
    request = {"kind": "batch", "name": "scene-report", "library": str(library), "out_dir": str(tmp_path / "o"),
               "measure_only": True, "settings": {"preset": "tiny"}}
    (tmp_path / "request.json").write_text(json.dumps(request))
    proc = subprocess.run([sys.executable, "-m", "nbvh_core", "job", str(tmp_path / "request.json")],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    events = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert events[-1]["event"] == "result" and Path(events[-1]["report"]).exists()
    progress = [e for e in events if e["event"] == "progress"]
    assert progress and progress[-1]["fraction"] == 1.0 and progress[-1]["total"] == 6
    statuses = {e["name"]: e["status"] for e in events if e["event"] == "asset"}
    assert statuses["pebble"] == "not_worth" and statuses["props__broken"] == "failed" and statuses["blob"] == "measured"
    assert not (tmp_path / "o" / "assets").exists()  # nothing trained


def test_ctrl_c_stops_the_run_and_keeps_what_finished(tmp_path):
    """SIGINT after the first trained asset: exit 130, that asset's result and the report kept, the other one
    marked cancelled; a rerun trains only the one that was cancelled."""
    lib = tmp_path / "lib"
    lib.mkdir()
    shutil.copy(ROOT / "assets" / "blob.ply.gz", lib / "blob.ply.gz")
    ico = icosphere(5, noise=0.03, seed=5)  # more than a tiny model as a compact mesh
    np.savez(lib / "sphere.npz", vertices=ico.vertices, faces=ico.faces)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "nbvh_core", "batch", str(lib), "-o", str(out), "--preset", "tiny", "--steps", "1500",
           "--force", "--num-cpus", "1", "--events"]  # one slot: the assets train one after the other
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    first = None
    for line in proc.stdout:
        ev = json.loads(line) if line.startswith("{") else {}
        if ev.get("event") == "asset" and ev.get("phase") == "train" and ev.get("status") == "done":
            first = ev["name"]
            proc.send_signal(signal.SIGINT)
            break
    proc.stdout.read()
    assert proc.wait(timeout=120) == 130 and first is not None, proc.stderr.read()[-2000:]
    rows = {r["name"]: r for r in json.loads((out / "report.json").read_text())["rows"]}
    other = ({"blob", "sphere"} - {first}).pop()
    assert rows[first]["status"] == "done" and (out / rows[first]["files"]["model"]).exists()
    assert rows[other]["status"] == "cancelled"
    events = []
    run_batch(lib, out, {"preset": "tiny", "steps": 1500, "time_limit_s": 0, "force": True}, events.append, num_cpus=2)
    trained = [e["name"] for e in events if e.get("event") == "asset" and e["phase"] == "train"]
    assert trained == [other]


def test_without_ray_the_batch_says_what_to_install(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(ValueError, match="pip install ray==2.60.0"):
        run_batch(tmp_path, tmp_path / "out", TINY)


def test_a_decimation_verdict_writes_the_decimation_and_the_report_lists_it(tmp_path):
    """With a quality target the blob's verdict is a decimation: the head writes it beside the results, the report
    row names it with its triangles and compact bytes (measure only: nothing trained)."""
    import csv

    from nbvh_core.geometry.bundled_samples import sample_path

    lib = tmp_path / "lib"
    lib.mkdir()
    shutil.copy(sample_path("blob"), lib / "blob.ply.gz")
    out = tmp_path / "out"
    run_batch(lib, out, {"preset": "preview", "target_mse": 0.01}, num_cpus=2, measure_only=True)
    row = next(csv.DictReader(open(out / "report.csv")))
    assert row["status"] == "not_worth" and int(row["decimation_triangles"]) > 0, row
    assert 0 < int(row["decimation_compact_bytes"]) < int(row["compact_bytes"]) < int(row["mesh_resident_bytes"])
    written = list(out.glob("assets/*/blob.glb"))
    assert len(written) == 1 and load_mesh(written[0]).n_triangles == int(row["decimation_triangles"])
    assert "blob.glb" in (out / "report.html").read_text()
    # the compact mesh written beside it is the bytes the verdict counted
    cmsh = list(out.glob("assets/*/blob.compact.cmsh"))
    assert len(cmsh) == 1 and cmsh[0].stat().st_size == int(row["decimation_compact_bytes"]) \
        == int(row["decimation_written_bytes"])


def test_a_fixed_size_kept_after_training_writes_the_decimation_it_was_weighed_against(tmp_path):
    """A preset (no target) is weighed after its training, as in a single run: the blob's 20-step model loses to the
    decimation of its bytes, the row says so and the decimation written is the bytes counted."""
    from nbvh_core.geometry.bundled_samples import sample_path

    lib = tmp_path / "lib"
    lib.mkdir()
    shutil.copy(sample_path("blob"), lib / "blob.ply.gz")
    (row,) = run_batch(lib, tmp_path / "out", TINY, num_cpus=2)["rows"]
    assert row["status"] == "not_worth" and row["recommendation"] == "decimate" and "the model needs" in row["verdict"]
    assert row["model_bytes"] is None and row["decimation_triangles"] > 0
    cmsh = tmp_path / "out" / row["files"]["decimation_compact"]
    assert cmsh.stat().st_size == row["decimation_compact_bytes"] == row["decimation_written_bytes"]
