"""Every file the product reads is data: checkpoints, mesh files, job requests, cached batch results, .blend
exports. For each reader, what it refuses (one line, nothing run, nothing allocated beyond the input's size)."""
import gzip
import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from nbvh_core.storage.checkpoint import CheckpointError, decode_checkpoint, encode_checkpoint, read_checkpoint
from nbvh_core.app.cli import main
from nbvh_core.geometry.mesh import MeshError, load_mesh
from nbvh_core.app.pipeline import compress_mesh, preset

ROOT = Path(__file__).resolve().parent.parent


class Payload:
    """Unpickling this runs `touch CANARY`: what an attacker would put in a checkpoint."""

    def __init__(self, canary: Path):
        self.canary = canary

    def __reduce__(self):
        return os.system, (f"touch {self.canary}",)


@pytest.fixture(scope="module")
def real_checkpoint(tmp_path_factory, sample_meshes):
    """A checkpoint of a real (tiny) compress run on the blob."""
    path = tmp_path_factory.mktemp("ck") / "blob.ckpt"
    compress_mesh(sample_meshes["blob"], preset("tiny").with_overrides(force=True, checkpoint_every_s=1e-9), None,
                  evaluate_quality=False, checkpoint_path=path)
    return path


# ------------------------------------------------------------------------------------------------ checkpoints
@pytest.mark.parametrize("form", ["torch.save", "pickle"])
def test_a_crafted_pickle_checkpoint_exits_2_in_one_line_and_runs_nothing(tmp_path, form):
    canary = tmp_path / "pwned"
    evil = tmp_path / "evil.ckpt"
    if form == "torch.save":
        torch.save({"x": Payload(canary)}, evil)
    else:
        import pickle

        evil.write_bytes(pickle.dumps({"x": Payload(canary)}, protocol=4))
    r = subprocess.run([sys.executable, "-m", "nbvh_core", "compress", "blob", "-o", str(tmp_path / "out") + "/",
                        "--resume", str(evil)], capture_output=True, text=True, cwd=str(ROOT), timeout=300)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "pickled checkpoint" in lines[0] and "without --resume" in lines[0], r.stderr
    assert not canary.exists(), "the payload ran"
    assert not (tmp_path / "out" / "blob.nbvh").exists()


def test_the_add_on_s_zip_pickle_is_recognised_without_torch(tmp_path):
    """The same refusal for a torch.save-like zip written without torch (as the Blender test crafts it)."""
    path = tmp_path / "z.ckpt"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("archive/data.pkl", b"\x80\x02cos\nsystem\nq\x00X\x04\x00\x00\x00trueq\x01\x85q\x02Rq\x03.")
    with pytest.raises(CheckpointError, match="pickled checkpoint"):
        read_checkpoint(path)


def _mutate(data: bytes, header=None, tensors=None) -> bytes:
    """Re-encode a checkpoint with its JSON header and/or tensors changed (a valid container: the checks below
    are the semantic ones)."""
    from safetensors.torch import load, save

    meta_len = int.from_bytes(data[:8], "little")
    meta = json.loads(data[8:8 + meta_len])["__metadata__"]["nbvh"]
    h = json.loads(meta)
    ts = load(data)
    if header:
        header(h)
    if tensors:
        tensors(ts)
    return save(ts, metadata={"nbvh": json.dumps(h)})


def _set(d: dict, path: str, value):
    keys = path.split(".")
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value


HEADER_CASES = {
    "version": ("version", 99, "version 99"),
    "kind": ("kind", "something-else", "not a checkpoint"),
    "step": ("step", -1, "'step'"),
    "elapsed": ("elapsed", "soon", "'elapsed'"),
    "learning rate scale": ("lr_scale", 1e300, "'lr_scale'"),
    "rng kind": ("numpy_rng.chunk_state.bit_generator", "MT19937", "PCG64"),
    "rng range": ("numpy_rng.chunk_state.state.inc", 1 << 130, "'inc'"),
    "huge table": ("extra.settings.log2_table", 30, "log2_table"),
    "odd type": ("extra.settings.nodes", "many", "nodes"),
    "unknown setting": ("extra.settings.run_this", "os.system", "unknown settings"),
    "no settings": ("extra", {}, "no settings"),
}


@pytest.mark.parametrize("case", list(HEADER_CASES))
def test_crafted_checkpoint_headers_are_refused_in_one_line(real_checkpoint, tmp_path, case, capsys):
    field, value, message = HEADER_CASES[case]
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(_mutate(real_checkpoint.read_bytes(), header=lambda h: _set(h, field, value)))
    assert main(["compress", "blob", "-o", str(tmp_path / "o.nbvh"), "--resume", str(bad)]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and message in err[0], err


_SMALLER = "describe a .* B model but it holds"


def _first_matrix(ts):
    return next(k for k in sorted(ts) if k.startswith("model.") and ts[k].dim() == 2 and ts[k].shape[0] != ts[k].shape[1])


def _first_model_tensor(ts):
    return next(k for k in sorted(ts) if k.startswith("model.") and ts[k].numel() > 1 and ts[k].is_floating_point())


def _largest_network_tensor(ts):
    return max((k for k in ts if k.startswith("model.network.")), key=lambda k: (ts[k].numel(), k))


TENSOR_CASES = {
    # refused on the meta device when the file then holds fewer bytes than the settings' model, else where the
    # model is known (which comes first depends on the tensor's size against HashVQAD's codes)
    "wrong shape": (lambda ts: ts.update({_first_model_tensor(ts): torch.zeros(3)}), f"{_SMALLER}|this model's"),
    "missing": (lambda ts: ts.pop(_first_model_tensor(ts)), f"{_SMALLER}|does not hold this model's tensors"),
    "big one missing": (lambda ts: ts.pop(_largest_network_tensor(ts)), _SMALLER),
    # as large, but not this model's layout: refused where the model is known
    "transposed": (lambda ts: ts.update({k: ts[k].t().contiguous() for k in [_first_matrix(ts)]}), "this model's"),
    "nan": (lambda ts: ts[_first_model_tensor(ts)].view(-1).__setitem__(0, float("nan")), "NaN"),
    "rng size": (lambda ts: ts.update({"torch_rng": torch.zeros(7, dtype=torch.uint8)}), "generator state"),
    "foreign param": (lambda ts: ts.update({"optimizer.999.exp_avg": torch.zeros(1)}), "does not have"),
    "moment shape": (lambda ts: ts.update({next(k for k in sorted(ts) if k.endswith("exp_avg")): torch.zeros(2, 2)}),
                     "this model's"),
    "odd name": (lambda ts: ts.update({"__reduce__": torch.zeros(1)}), "unexpected tensor"),
}


@pytest.mark.parametrize("case", list(TENSOR_CASES))
def test_checkpoint_tensors_that_do_not_fit_the_model_are_refused(real_checkpoint, tmp_path, case, capsys):
    change, message = TENSOR_CASES[case]
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(_mutate(real_checkpoint.read_bytes(), tensors=change))
    assert main(["compress", "blob", "-o", str(tmp_path / "o.nbvh"), "--resume", str(bad)]) == 2
    err = capsys.readouterr().err
    # refused where the model is known (after the 'resuming ...' line): the error is the last line, no traceback
    assert re.search(message, err.strip().splitlines()[-1]) and "Traceback" not in err, err


def test_container_damage_is_refused_before_allocating(real_checkpoint):
    data = real_checkpoint.read_bytes()
    n = int.from_bytes(data[:8], "little")
    for blob, message in [(data[: len(data) // 2], "outside the file"), (b"\xff" * 8 + data[8:], "header length"),
                          (data[:8] + b"[" + data[9:], "unreadable header"), (b"", "too short")]:
        with pytest.raises(CheckpointError, match=message):
            decode_checkpoint(blob)
    # A declared shape of 2^40 floats in a small file: refused from the table, nothing of that size made.
    table = json.loads(data[8:8 + n])
    name = next(k for k in table if k != "__metadata__")
    table[name]["shape"] = [1 << 20, 1 << 20]
    text = json.dumps(table).encode()
    with pytest.raises(CheckpointError, match="bad shape|does not match"):
        decode_checkpoint(len(text).to_bytes(8, "little") + text + data[8 + n:])


def test_a_checkpoint_round_trips_exactly(real_checkpoint):
    ck = read_checkpoint(real_checkpoint)
    again = decode_checkpoint(_mutate(real_checkpoint.read_bytes()))
    assert ck.header == again.header and all(torch.equal(ck.tensors[k], again.tensors[k]) for k in ck.tensors)
    state = {"model": {"w": torch.arange(3.0)}, "step": 3, "torch_rng": torch.get_rng_state(),
             "history": [(1, 0.5), (2, 0.25)], "numpy_rng": {"chunk_state": np.random.default_rng(5).bit_generator.state,
                                                             "index": 0, "leaf_weights": np.ones(4)},
             "qat_affine": (np.zeros((2, 2), np.float32), np.ones((2, 2), np.float32)), "cut": [1, 2]}
    back = decode_checkpoint(encode_checkpoint(state))
    assert back.header["numpy_rng"]["chunk_state"] == state["numpy_rng"]["chunk_state"]  # 128-bit ints exact
    assert back.tensors["history"].tolist() == [[1, 0.5], [2, 0.25]] and back.tensors["cut"].tolist() == [1, 2]


def test_special_files_are_never_read(tmp_path):
    fifo = tmp_path / "pipe.ckpt"
    os.mkfifo(fifo)
    with pytest.raises(CheckpointError, match="not a regular file"):
        read_checkpoint(fifo)
    mesh_fifo = tmp_path / "pipe.ply"
    os.mkfifo(mesh_fifo)
    with pytest.raises(MeshError, match="not a regular file"):
        load_mesh(mesh_fifo)


# ------------------------------------------------------------------------------------------------ mesh files
def test_a_gzip_bomb_is_refused_before_it_is_inflated(tmp_path):
    bomb = tmp_path / "bomb.ply.gz"
    with gzip.open(bomb, "wb", compresslevel=9) as f:
        f.write(b"ply\nformat ascii 1.0\n")
        chunk = b"\0" * (1 << 20)
        for _ in range(512):  # 512 MB of zeros in ~0.5 MB
            f.write(chunk)
    import resource

    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(MeshError, match="decompression bomb"):
        load_mesh(bomb)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 300 * 1024  # KB: far below 512 MB


GLTF = ('{"asset":{"version":"2.0"},"buffers":[{"uri":"%s","byteLength":36}],"bufferViews":[{"buffer":0,'
        '"byteLength":36}],"accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3",'
        '"min":[0,0,0],"max":[1,1,0]}],"meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}],"nodes":[{"mesh":0}],'
        '"scenes":[{"nodes":[0]}]}')


@pytest.mark.parametrize("uri", ["/dev/zero", "../../../../../dev/zero", "link.bin", "pipe.bin", "/etc/hostname"])
def test_gltf_buffers_must_be_regular_files_beside_the_mesh(tmp_path, uri):
    os.symlink("/dev/zero", tmp_path / "link.bin")
    os.mkfifo(tmp_path / "pipe.bin")
    (tmp_path / "m.gltf").write_text(GLTF % uri)
    with pytest.raises(MeshError, match="could not read"):
        load_mesh(tmp_path / "m.gltf")
    (tmp_path / "ok.bin").write_bytes(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32).tobytes())
    (tmp_path / "ok.gltf").write_text(GLTF % "ok.bin")
    assert load_mesh(tmp_path / "ok.gltf").n_triangles == 1  # a buffer beside it is read


def test_an_obj_material_library_outside_its_folder_is_not_read(tmp_path):
    os.mkfifo(tmp_path / "pipe.mtl")
    for lib in ("/dev/zero", "pipe.mtl", "../../../../../etc/shadow"):
        (tmp_path / "m.obj").write_text(f"mtllib {lib}\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
        assert load_mesh(tmp_path / "m.obj").n_triangles == 1  # the geometry loads; the library is skipped


@pytest.mark.parametrize("text", [
    b"ply\nformat binary_little_endian 1.0\nelement vertex 2000000000\nproperty float x\nproperty float y\n"
    b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n" + b"\0" * 64,
    b"OFF\n2000000000 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
])
def test_huge_declared_counts_are_refused_without_allocating_them(tmp_path, text):
    import resource

    path = tmp_path / ("m.ply" if text.startswith(b"ply") else "m.off")
    path.write_bytes(text)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(MeshError):
        load_mesh(path)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 100 * 1024


# ------------------------------------------------------------------------------------------------ job protocol
@pytest.mark.parametrize("request_, message", [
    ([], "JSON object"),
    ({"name": "a", "mesh": "m.npz", "out_dir": "o", "run": "x"}, "unknown request field"),
    ({"name": "a", "mesh": 3, "out_dir": "o"}, "'mesh' must be a str"),
    ({"name": "../a", "mesh": "m.npz", "out_dir": "o"}, "plain object name"),
    ({"name": "a", "mesh": "m.npz", "out_dir": "o", "settings": {"log2_table": 40}}, "log2_table"),
    ({"name": "a", "mesh": "m.npz", "out_dir": "o", "settings": {"preset": "default", "nodes": 1e9}}, "nodes"),
    ({"name": "a", "mesh": "m.npz", "out_dir": "o", "settings": {"preset": "nope"}}, "unknown preset"),
    ({"name": "a", "out_dir": "o"}, "needs mesh"),
])
def test_job_requests_are_checked_before_anything_runs(request_, message):
    from nbvh_core.app.job import check_request

    with pytest.raises(ValueError, match=message):
        check_request(request_)


def test_a_job_mesh_with_pickled_arrays_is_refused(tmp_path, capsys):
    from nbvh_core.app.job import main as job_main

    canary = tmp_path / "pwned"
    mesh = tmp_path / "m.npz"
    np.savez(mesh, vertices=np.array([Payload(canary)], dtype=object), faces=np.zeros((1, 3), np.int32))
    request = tmp_path / "r.json"
    request.write_text(json.dumps({"name": "m", "mesh": str(mesh), "out_dir": str(tmp_path / "o")}))
    assert job_main([str(request)]) == 2
    assert not canary.exists() and "must be a numeric array" in capsys.readouterr().out


def test_a_cached_batch_result_naming_a_file_elsewhere_is_not_trusted(tmp_path):
    from nbvh_core.app.library_batch import _cached

    folder = tmp_path / "assets" / "a"
    folder.mkdir(parents=True)
    elsewhere = tmp_path / "secret.nbvh"
    elsewhere.write_bytes(b"x" * 10)
    for name in ("../../secret.nbvh", str(elsewhere), "m.txt"):
        (folder / "result.json").write_text(json.dumps({"files": {"model": name}, "model_bytes": 10}))
        assert _cached(tmp_path, "a") is None
    (folder / "m.nbvh").write_bytes(b"x" * 10)
    (folder / "result.json").write_text(json.dumps({"files": {"model": "m.nbvh"}, "model_bytes": 10}))
    assert _cached(tmp_path, "a") is not None


# ------------------------------------------------------------------------------------------------ .blend files
BLEND_WITH_SCRIPT = r"""
import bpy, sys
canary = sys.argv[-1]
bpy.ops.wm.read_factory_settings(use_empty=True)
mesh = bpy.data.meshes.new("T")
mesh.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
bpy.context.scene.collection.objects.link(bpy.data.objects.new("T", mesh))
text = bpy.data.texts.new("evil.py")
text.write(f"open({canary!r}, 'w').write('ran')\n")
text.use_module = True  # 'Register': runs when the file is opened with scripts allowed
bpy.ops.wm.save_as_mainfile(filepath=sys.argv[-2])
"""


@pytest.mark.skipif(shutil.which("blender") is None, reason="needs Debian's blender binary")
def test_a_blend_file_s_own_scripts_never_run_on_export(tmp_path):
    from nbvh_core.app.blend_export import export_blend

    blend, canary = tmp_path / "evil.blend", tmp_path / "pwned"
    script = tmp_path / "make.py"
    script.write_text(BLEND_WITH_SCRIPT)
    made = subprocess.run(["blender", "-b", "--factory-startup", "--python", str(script), "--", str(blend),
                           str(canary)], capture_output=True, text=True, timeout=300)
    assert blend.exists(), made.stdout[-500:] + made.stderr[-500:]
    # The text block does run when scripts are allowed: the test can fail.
    subprocess.run(["blender", "-b", "--enable-autoexec", str(blend)], capture_output=True, timeout=300)
    assert canary.exists(), "the crafted .blend's script did not run even with autoexec (test is void)"
    canary.unlink()
    exported = export_blend(blend, tmp_path / "out")
    assert [name for name, _ in exported] == ["T"] and not canary.exists()


# ------------------------------------------------------------------------------------------------ the fuzz harness
@pytest.mark.parametrize("kind, cases", [("checkpoint", 14), ("mesh", 12)])
def test_the_fuzz_harness_runs_and_finds_no_failure_in_a_short_run(tmp_path, kind, cases):
    """bench/fuzzing/fuzz_files.py at a tiny budget (the long runs' results are in bench/results/fuzz_files.csv)."""
    import csv

    out = tmp_path / "fuzz.csv"
    r = subprocess.run([sys.executable, "-m", "bench.fuzzing.fuzz_files", "--kind", kind, "--cases", str(cases),
                        "--out", str(out)], capture_output=True, text=True, timeout=600, cwd=str(ROOT))
    assert r.returncode == 0, r.stderr[-2000:]
    row = next(csv.DictReader(out.open()))
    assert int(row["read"]) + int(row["refused"]) == cases, row
    assert all(row[k] == "0" for k in ("other", "crash", "hang", "executed", "over_memory")), row
