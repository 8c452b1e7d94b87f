"""Nothing lost, nothing crafted gets in: one test per defect found by probing the product, and the reader's fuzz test.

Each crafted file has a *valid* checksum (`craft` recomputes it), so it reaches the header and structure checks.
"""
import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nbvh_core.app.cli import main
from nbvh_core.storage.fileformat import NBVHFileError, load_nbvh
from nbvh_core.protocol.outputs import OutputError, OutputLock, OutputSet, resolve_output
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.rendering.render import orbit_cameras, render_neural

from fuzzing import check_case, craft, fuzz_cases, split

ROOT = Path(__file__).resolve().parent.parent


def run_cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "nbvh_core", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=str(ROOT))


def write_obj(path: Path, mesh) -> Path:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def model_file(sample_meshes, tmp_path_factory):
    path = tmp_path_factory.mktemp("safety") / "blob.nbvh"
    compress_mesh(sample_meshes["blob"], preset("tiny").with_overrides(force=True), path, evaluate_quality=False)
    return path


def tensor(header: dict, name: str) -> dict:
    return next(t for t in header["tensors"] if t["name"] == name)


def patch_payload(payload: bytes, offset: int, data: bytes) -> bytes:
    return payload[:offset] + data + payload[offset + len(data):]


# ------------------------------------------------------------------------------ 1. the input is never overwritten
def test_output_naming_the_input_is_refused(tmp_path, sample_meshes):
    src = write_obj(tmp_path / "src.obj", sample_meshes["blob"])
    before = src.read_bytes()
    assert main(["compress", str(src), "--preset", "tiny", "--force", "-o", str(src)]) == 2
    assert src.read_bytes() == before
    # also through another spelling of the same path
    assert main(["compress", str(src), "--preset", "tiny", "--force", "-o", str(tmp_path / "." / "src.obj")]) == 2
    assert src.read_bytes() == before


def test_finished_result_replaced_only_with_overwrite(tmp_path, capsys):
    out = tmp_path / "m.nbvh"
    assert main(["compress", "blob", "--preset", "tiny", "--force", "-o", str(out)]) == 0
    first = out.read_bytes()
    assert main(["compress", "blob", "--preset", "tiny", "--force", "--seed", "3", "-o", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err and out.read_bytes() == first
    assert main(["compress", "blob", "--preset", "tiny", "--force", "--seed", "3", "-o", str(out),
                 "--overwrite"]) == 0
    assert out.read_bytes() != first


# ------------------------------------------------------------------------------ 2. the add-on keeps earlier results
def test_failed_or_cancelled_rerun_keeps_the_previous_result(tmp_path, sample_meshes):
    sys.path.insert(0, str(ROOT))
    from addon.job import JobQueue
    from test_job import make_request

    q = JobQueue(sys.executable)
    first = q.submit("blob", make_request(tmp_path, sample_meshes, steps=40, force=True))
    q.wait(timeout=300)
    assert first.state == "done", first.error
    files = {k: Path(v) for k, v in first.result["files"].items()}
    before = {k: p.read_bytes() for k, p in files.items()}
    # A re-run that fails (bad settings) and one that is cancelled mid-training: the result stays as it was.
    failing = q.submit("blob", make_request(tmp_path, sample_meshes, steps=40, force=True, lr=-1.0, nodes=0))
    q.wait(timeout=300)
    assert failing.state == "failed"
    slow = q.submit("blob", make_request(tmp_path, sample_meshes, steps=100000, time_limit_s=600, force=True))
    t0 = time.monotonic()
    while slow.progress.get("step", 0) < 2 and time.monotonic() - t0 < 120:
        q.step()
        time.sleep(0.1)
    slow.cancel()
    assert slow.state == "cancelled"
    # A --load job with a damaged model fails and deletes nothing.
    damaged = tmp_path / "damaged.nbvh"
    damaged.write_bytes(b"NBVH\0\r\n\x1a\x02\x00\x00\x00" + b"\0" * 64)
    load = q.submit("blob", dict(make_request(tmp_path, sample_meshes), model=str(damaged)))
    q.wait(timeout=300)
    assert load.state == "failed" and damaged.exists()
    assert {k: p.read_bytes() for k, p in files.items()} == before
    leftovers = [p.name for p in files["model"].parent.iterdir() if ".partial-" in p.name or p.name.endswith(".lock")]
    assert leftovers == []


# ------------------------------------------------------------------------------ 3-5. crafted files are refused
def with_links(path: Path) -> bytes:
    """The model file as format 2.4 wrote it: the BVH's links and leaf ordinals (2.5 stores the builder's layout as
    shape bits, which hold no link to break)."""
    import nbvh_core.storage.container as container
    from nbvh_core.storage.fileformat import encode_nbvh

    model, minor = load_nbvh(path), container.VERSION_MINOR
    container.VERSION_MINOR = 4
    try:
        return encode_nbvh(model, {}, model.storage)
    finally:
        container.VERSION_MINOR = minor


def test_bvh_cycle_is_refused(model_file):
    header, payload = split(with_links(model_file))
    t = tensor(header, "bvh.left")
    left = np.frombuffer(payload[t["offset"]:t["offset"] + t["nbytes"]], "<u2").copy()
    internal = np.nonzero(left)[0]
    left[internal[-1]] = 0 + 2  # a deep internal node points back at the root's children: a cycle
    data = craft(header, patch_payload(payload, t["offset"], left.tobytes()))
    with pytest.raises(NBVHFileError, match="cycle"):
        from nbvh_core.storage.fileformat import decode_nbvh

        decode_nbvh(data)


def test_a_config_the_model_does_not_know_is_the_readers_refusal(model_file):
    """Found by bench/fuzzing/fuzz_reader.py (3 of 6,000 cases): a network config's own check raised a bare ValueError
    through the reader; every refusal is an NBVHFileError, so callers that catch the reader's errors catch it."""
    from nbvh_core.storage.fileformat import decode_nbvh

    header, payload = split(model_file.read_bytes())
    header["config"]["network"]["normal_loss"] = "x"
    with pytest.raises(NBVHFileError, match="normal loss 'x'"):
        decode_nbvh(craft(header, payload))


@pytest.mark.parametrize("case", ["child_1e8", "negative_offset", "log2_table_15", "log2_table_20", "header_list",
                                  "string_offset", "string_quality", "leaf_out_of_range", "shape_not_a_tree", "nan_box",
                                  "unknown_normal_loss"])
def test_crafted_headers_and_nodes_refused_by_the_cli(model_file, tmp_path, case, capsys):
    header, payload = split(model_file.read_bytes())
    if case == "child_1e8":  # a 32-bit node file whose root points far outside the node array
        from nbvh_core.storage.fileformat import encode_nbvh
        from nbvh_core.neural.quantize import StorageConfig

        header, payload = split(encode_nbvh(load_nbvh(model_file), {}, StorageConfig(8, 16, 32)))
        t = tensor(header, "bvh")
        payload = patch_payload(payload, t["offset"] + 24, np.array([100_000_000], "<i4").tobytes())
    elif case == "negative_offset":
        header["tensors"][1]["offset"] = -64
    elif case == "log2_table_15":
        header["config"]["encoding"]["log2_table"] = 15
    elif case == "log2_table_20":
        header["config"]["encoding"]["log2_table"] = 20
    elif case == "header_list":
        header = [header]
    elif case == "string_offset":
        header["tensors"][0]["offset"] = "0"
    elif case == "string_quality":
        header["metadata"]["quality"] = {"mse": "good", "silhouette_iou": 1.0}
    elif case == "leaf_out_of_range":
        header, payload = split(with_links(model_file))
        t = tensor(header, "bvh.leaf")
        leaf = np.frombuffer(payload[t["offset"]:t["offset"] + t["nbytes"]], "<u2").copy()
        leaf[np.nonzero(leaf != 65535)[0][0]] = 60000
        payload = patch_payload(payload, t["offset"], leaf.tobytes())
    elif case == "shape_not_a_tree":  # every node marked internal
        t = tensor(header, "bvh.shape")
        payload = patch_payload(payload, t["offset"], b"\xff" * t["nbytes"])
    elif case == "unknown_normal_loss":  # found by bench/fuzzing/fuzz_reader.py: a ValueError escaped the reader
        header["config"]["network"]["normal_loss"] = "x"
    elif case == "nan_box":
        t = tensor(header, "bvh.root")
        payload = patch_payload(payload, t["offset"], np.array([np.nan], "<f4").tobytes())
    bad = tmp_path / f"{case}.nbvh"
    bad.write_bytes(craft(header, payload))
    t0 = time.monotonic()
    peak0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for argv in (["render", str(bad), "-o", str(tmp_path / "x.png"), "--width", "16"], ["info", str(bad)]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error: ") and len(err.splitlines()) == 1, err
    assert time.monotonic() - t0 < 10
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak0 < 200_000  # KB: nothing sized by the header


def test_format_1_files_still_load(model_file, sample_meshes, tmp_path, monkeypatch):
    """A file as the previous release wrote it (format 1.0: float32 nodes, tables and weights) loads and renders."""
    import nbvh_core.storage.container as container
    from nbvh_core.storage.fileformat import encode_nbvh

    model = load_nbvh(model_file)
    monkeypatch.setattr(container, "VERSION_MINOR", 1)  # HashVQAD's index for all L x H entries, as 1.0 had it
    v2 = encode_nbvh(model, {}, None)  # float32 everywhere: the v1 tensor set
    monkeypatch.undo()
    header, payload = split(v2)
    header.pop("storage")
    header["float_bytes"] = 4
    old = tmp_path / "old.nbvh"
    old.write_bytes(craft(header, payload, major=1))
    loaded = load_nbvh(old)
    cam = orbit_cameras(2)[0]
    assert np.array_equal(render_neural(loaded, cam, 24, 24).hit, render_neural(model, cam, 24, 24).hit)


# ------------------------------------------------------------------------------ 6. periodic checkpoints, --resume
def test_kill_loses_at_most_one_checkpoint_period_and_resume_finishes(tmp_path):
    out = tmp_path / "k.nbvh"
    ck = tmp_path / ".k.nbvh.checkpoint"
    proc = subprocess.Popen([sys.executable, "-m", "nbvh_core", "compress", "blob", "-o", str(out), "--preset", "tiny",
                             "--force", "--steps", "100000000", "--time-limit", "8", "--checkpoint-every", "0.5"],
                            cwd=str(ROOT),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t0 = time.monotonic()
    while not ck.exists() and time.monotonic() - t0 < 120:
        time.sleep(0.1)
    time.sleep(1.5)
    proc.send_signal(signal.SIGKILL)  # no handler runs: only the periodic checkpoint survives
    proc.wait()
    assert ck.exists() and not out.exists()
    from nbvh_core.storage.checkpoint import read_checkpoint

    step = read_checkpoint(ck).header["step"]
    assert step > 0
    r = run_cli("compress", "blob", "-o", str(out), "--resume", str(ck))
    assert r.returncode == 0, r.stderr
    meta = load_nbvh(out).metadata
    assert meta["training"]["steps"] > step and meta["training"]["seconds"] >= 7.9 and "resumed" in meta["why"]
    assert not ck.exists()


def test_resume_refuses_another_mesh(tmp_path, sample_meshes):
    ck = tmp_path / "c.ckpt"
    compress_mesh(sample_meshes["blob"], preset("tiny").with_overrides(force=True, checkpoint_every_s=1e-9), None,
                  evaluate_quality=False, checkpoint_path=ck)
    assert ck.exists()
    assert main(["compress", "studs", "-o", str(tmp_path / "s.nbvh"), "--resume", str(ck)]) == 2


# ------------------------------------------------------------------------------ 7. outputs checked first, one unit
def test_unwritable_output_fails_before_training(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    t0 = time.monotonic()
    assert main(["compress", "blob", "--preset", "tiny", "--force", "--steps", "100000",
                 "-o", str(blocker / "sub" / "m.nbvh")]) == 2
    assert time.monotonic() - t0 < 20 and "cannot write" in capsys.readouterr().err


def test_result_files_appear_together_or_not_at_all(tmp_path, monkeypatch):
    targets = [tmp_path / n for n in ("m.nbvh", "m.report.json", "m.preview.png")]
    for t in targets:
        t.write_bytes(b"old " + t.name.encode())
    # A full disk while staging the preview: nothing replaced, no partial file left.
    staged = OutputSet()
    staged.stage(targets[0], b"new model")
    staged.stage(targets[1], b"new report")
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(OSError(28, "No space left on device")))
    with pytest.raises(OSError):
        staged.stage(targets[2], b"new preview")
    monkeypatch.setattr(os, "fsync", real_fsync)
    assert [t.read_bytes() for t in targets] == [b"old " + t.name.encode() for t in targets]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(t.name for t in targets)
    # A rename that fails half-way through the commit: the ones already renamed are rolled back.
    staged = OutputSet()
    for t in targets:
        staged.stage(t, b"new " + t.name.encode())
    real_replace, calls = os.replace, []

    def flaky(a, b):
        calls.append(b)
        if len(calls) == 5:
            raise OSError(5, "I/O error")
        return real_replace(a, b)

    monkeypatch.setattr(os, "replace", flaky)
    with pytest.raises(OSError):
        staged.commit()
    monkeypatch.setattr(os, "replace", real_replace)
    assert [t.read_bytes() for t in targets] == [b"old " + t.name.encode() for t in targets]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(t.name for t in targets)
    staged = OutputSet()
    for t in targets:
        staged.stage(t, b"new")
    staged.commit()
    assert all(t.read_bytes() == b"new" for t in targets)


# ------------------------------------------------------------------------------ 8. folders, races, error events
def test_trailing_slash_means_a_folder(tmp_path):
    assert resolve_output(f"{tmp_path}/new/", "bunny") == tmp_path / "new" / "bunny.nbvh"
    assert main(["compress", "blob", "--preset", "tiny", "--force", "-o", f"{tmp_path}/new/"]) == 0
    assert (tmp_path / "new" / "blob.nbvh").is_file()


def test_second_writer_of_the_same_output_is_refused(tmp_path):
    out = tmp_path / "m.nbvh"
    with OutputLock(out):
        with pytest.raises(OutputError, match="being written by another run"):
            OutputLock(out).acquire()
    lock = tmp_path / ".m.nbvh.lock"
    lock.write_text("999999999")  # a dead run's lock is taken over
    with OutputLock(out):
        assert lock.read_text() == str(os.getpid())
    assert not lock.exists()


def test_events_end_with_an_error_event_on_failure(tmp_path):
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n")
    r = run_cli("compress", str(nan), "-o", str(tmp_path / "o.nbvh"), "--preset", "tiny", "--events")
    assert r.returncode == 2
    events = [json.loads(line) for line in r.stdout.splitlines() if line.startswith("{")]
    assert events and events[-1]["event"] == "error" and "NaN" in events[-1]["message"]


# ------------------------------------------------------------------------------ 9. not worth it ends in seconds
def test_not_worth_compressing_ends_in_seconds_unless_forced(tmp_path):
    import trimesh

    cube = tmp_path / "cube.obj"
    trimesh.creation.box().export(cube)
    out = tmp_path / "cube.nbvh"
    t0 = time.monotonic()
    r = run_cli("compress", str(cube), "-o", str(out), "--target-mse", "0.002")
    assert r.returncode == 4 and time.monotonic() - t0 < 60, r.stderr
    assert "not worth compressing" in r.stderr and "--force" in r.stderr and not out.exists()
    r = run_cli("compress", str(cube), "-o", str(out), "--preset", "tiny", "--force")
    assert r.returncode == 0 and out.exists(), r.stderr


# ------------------------------------------------------------------------------ the reader's fuzz test
def test_fuzzed_files_end_in_a_model_or_a_clear_refusal(model_file):
    data = model_file.read_bytes()
    peak0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    counts = {"model": 0, "refused": 0}
    for kind, blob in fuzz_cases(data, 160, seed=1):
        counts[check_case(blob)] += 1
    assert counts["refused"] > 100  # most damage is caught; what loads must still render without crashing
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak0 < 300_000  # KB


def test_the_peak_memory_reported_is_the_run_s_own_not_its_parent_s():
    """A run spawned by a process that once held much memory (a benchmark that generated a heavy mesh) reports its
    own peak: getrusage's ru_maxrss counts the parent's after vfork and exec (a 20M-triangle run read 17.8 GB where
    it peaked 5.1 GB)."""
    import subprocess
    import sys

    held = np.ones(600 * 2**20 // 8)  # 600 MiB resident in this process
    code = ("import resource; from nbvh_core.app.pipeline import peak_resident_bytes; "
            "print(peak_resident_bytes(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)")
    own, maxrss = map(int, subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                          check=True).stdout.split())
    del held
    assert own < 400 * 2**20, (own, maxrss)  # the child's imports: ~250 MB
