"""Fuzz the checkpoint and mesh readers: truncations, bit flips, header and table mutations, huge declared sizes and
pickles carrying a payload, each case read in its own (forked) process under a time and a memory cap.

    .venv/bin/python -m bench.fuzzing.fuzz_files --kind checkpoint --cases 5000   # -> bench/results/fuzz_files.csv
    .venv/bin/python -m bench.fuzzing.fuzz_files --kind mesh --cases 5000

A checkpoint case goes the whole way `compress --resume` goes before training (`pipeline.resume_settings`, the
model its settings describe, `training.checkpoints.load_checkpoint` into it); a mesh case through `batch.load_asset` (every mesh
format `load_mesh` reads, and the job's .npz arrays). Outcomes: read (a usable result), refused (a ValueError,
one line), other (any other exception: a reader bug), crash (the process died of a signal), hang (past the time
cap), executed (a payload created the canary file), over_memory (peak resident memory grew by more than
128 MB + 20 x the input's size: a forked reader pages in ~60 MB of shared code on its first read). The run passes when the last five are all 0.
"""
from __future__ import annotations

import argparse
import gzip
import io
import json
import os
import pickle
import resource
import signal
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np
from bench.harness import RESULTS, append_rows

# Every case runs in a forked child: a parent with OpenMP worker threads would hand its children locks no thread
# will release (they hang), so the parent computes on one thread.
os.environ["OMP_NUM_THREADS"] = "1"
ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT / "tests")]  # the test suite's mesh makers and mutators, shared
CASE_SECONDS = 20
MEMORY_CAP = 4 << 30  # address space a case may add (a runaway allocation fails instead of swapping)


class Payload:
    def __init__(self, canary: str):
        self.canary = canary

    def __reduce__(self):
        return os.system, (f"touch {self.canary}",)


def _pickles(canary: str, rng) -> bytes:
    """A pickle that creates the canary when loaded, in one of the forms a crafted checkpoint or mesh could take."""
    import torch

    form = int(rng.integers(4))
    if form == 0:
        buf = io.BytesIO()
        torch.save({"model": Payload(canary)}, buf)
        return buf.getvalue()
    if form == 1:
        return pickle.dumps({"x": Payload(canary)}, protocol=int(rng.integers(2, 6)))
    if form == 2:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as z:
            z.writestr("archive/data.pkl", pickle.dumps(Payload(canary), protocol=2))
        return buf.getvalue()
    body = pickle.dumps(Payload(canary))  # behind a plausible safetensors length prefix
    return len(body).to_bytes(8, "little") + body


def _flip(data: bytes, rng) -> bytes:
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 9))):
        pos = int(rng.integers(0, len(b)))
        b[pos] ^= 1 << int(rng.integers(8))
    return bytes(b)


# --------------------------------------------------------------------------------------------------- checkpoints
def checkpoint_seed(folder: Path):
    """A real checkpoint of a tiny compress run on the blob, and the mesh it belongs to."""
    from nbvh_core.geometry.mesh import load_mesh
    from nbvh_core.app.pipeline import compress_mesh, preset
    from nbvh_core.geometry.bundled_samples import sample_path

    mesh = load_mesh(sample_path("blob"))
    path = folder / "seed.ckpt"
    compress_mesh(mesh, preset("tiny").with_overrides(force=True, checkpoint_every_s=1e-9), None,
                  evaluate_quality=False, checkpoint_path=path)
    return path.read_bytes(), mesh


def checkpoint_cases(seed: bytes, n: int, rng_seed: int, canary: str):
    from fuzzing import _mutate_header
    from safetensors.torch import load, save

    rng = np.random.default_rng(rng_seed)
    hlen = int.from_bytes(seed[:8], "little")
    table = json.loads(seed[8:8 + hlen])
    tensors = load(seed)
    kinds = ("truncate", "flip", "header", "table", "tensor", "pickle", "huge")
    for i in range(n):
        kind = kinds[i % len(kinds)]
        if kind == "truncate":
            yield kind, seed[:int(rng.integers(0, len(seed)))]
        elif kind == "flip":
            yield kind, _flip(seed, rng)
        elif kind == "header":
            header = _mutate_header(json.loads(table["__metadata__"]["nbvh"]), rng)
            yield kind, save(tensors, metadata={"nbvh": json.dumps(header)})
        elif kind == "table":
            mutated = _mutate_header(json.loads(json.dumps(table)), rng)
            text = json.dumps(mutated).encode()
            yield kind, len(text).to_bytes(8, "little") + text + seed[8 + hlen:]
        elif kind == "tensor":
            yield kind, _tensor_case(tensors, table, rng, save)
        elif kind == "pickle":
            yield kind, _pickles(canary, rng)
        else:
            yield kind, _huge_case(seed, table, hlen, rng)


def _tensor_case(tensors: dict, table: dict, rng, save) -> bytes:
    import torch

    ts = dict(tensors)
    name = sorted(ts)[int(rng.integers(len(ts)))]  # safetensors returns tensors in no fixed order
    shape = [int(s) for s in rng.integers(0, 5, size=int(rng.integers(0, 4)))]
    dtype = [torch.float32, torch.float64, torch.uint8, torch.int64, torch.float16][int(rng.integers(5))]
    choice = int(rng.integers(4))
    if choice == 0:
        ts[name] = torch.zeros(shape, dtype=dtype)
    elif choice == 1 and ts[name].is_floating_point() and ts[name].numel():
        ts[name] = ts[name].clone().view(-1).index_fill(0, torch.tensor([0]), float("nan")).view(ts[name].shape)
    elif choice == 2:
        ts.pop(name)
    else:
        ts[f"optimizer.{int(rng.integers(0, 64))}.exp_avg"] = torch.randn(shape)
    return save(ts, metadata=table["__metadata__"])


def _huge_case(seed: bytes, table: dict, hlen: int, rng) -> bytes:
    """A declared header length or tensor shape far beyond the file."""
    if rng.random() < 0.3:
        lengths = [1 << 40, (1 << 64) - 1, len(seed), hlen + 1]
        return lengths[int(rng.integers(len(lengths)))].to_bytes(8, "little") + seed[8:]
    t = json.loads(json.dumps(table))
    name = next(k for k in t if k != "__metadata__")
    t[name]["shape"] = [[1 << 20, 1 << 31, 1 << 40][int(rng.integers(3))]] * int(rng.integers(1, 4))
    t[name]["data_offsets"][1] = [t[name]["data_offsets"][1], 1 << 40][int(rng.integers(2))]
    text = json.dumps(t).encode()
    return len(text).to_bytes(8, "little") + text + seed[8 + hlen:]


def read_checkpoint_case(path: Path, mesh) -> str:
    import torch

    from nbvh_core import kernels
    from nbvh_core.geometry.bvh import build_bvh
    from nbvh_core.neural.model import NeuralBVH
    from nbvh_core.app.pipeline import resume_settings
    from nbvh_core.storage.checkpoint import load_checkpoint
    from nbvh_core.training.train import make_optimizer

    settings = resume_settings(path, mesh)
    bvh = build_bvh(mesh, settings.nodes)
    model = NeuralBVH(bvh.nodes, settings.model_config(), mesh.transform)
    opt = make_optimizer(model, settings.train_config(), kernels.plan(model))
    load_checkpoint(path, model, opt, torch.device("cpu"))
    return "read"


# --------------------------------------------------------------------------------------------------- meshes
def mesh_seeds(folder: Path) -> dict[str, bytes]:
    """The blob in every format the readers take: {file name: bytes} (a glTF's .bin is written beside it)."""
    import trimesh

    from nbvh_core.geometry.mesh import load_mesh
    from nbvh_core.geometry.bundled_samples import sample_path

    m = load_mesh(sample_path("blob"))
    tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
    seeds = {}
    for name, kind in (("m.obj", "obj"), ("m.ply", "ply"), ("m.stl", "stl"), ("m.off", "off"), ("m.glb", "glb")):
        buf = io.BytesIO()
        tm.export(buf, file_type=kind)
        seeds[name] = buf.getvalue()
    ascii_ply = io.BytesIO()
    tm.export(ascii_ply, file_type="ply", encoding="ascii")
    seeds["a.ply"] = ascii_ply.getvalue()
    gltf = tm.export(file_type="gltf")  # {"model.gltf": json bytes, "gltf_buffer_0.bin": bytes}
    for k, v in gltf.items():
        (folder / k).write_bytes(v)
    seeds["model.gltf"] = gltf["model.gltf"]
    seeds["m.ply.gz"] = gzip.compress(seeds["m.ply"])
    npz = io.BytesIO()
    np.savez(npz, vertices=m.vertices, faces=m.faces)
    seeds["m.npz"] = npz.getvalue()
    return seeds


def mesh_cases(seeds: dict[str, bytes], n: int, rng_seed: int, canary: str):
    rng = np.random.default_rng(rng_seed)
    names = sorted(seeds)
    kinds = ("truncate", "flip", "numbers", "counts", "pickle", "bomb")
    for i in range(n):
        kind = kinds[i % len(kinds)]
        name = names[(i // len(kinds)) % len(names)]
        data = seeds[name]
        if kind == "truncate":
            yield kind, name, data[:int(rng.integers(0, len(data)))]
        elif kind == "flip":
            yield kind, name, _flip(data, rng)
        elif kind in ("numbers", "counts"):
            yield kind, name, _text_mutation(name, data, rng, counts=kind == "counts")
        elif kind == "pickle":
            if name.endswith(".npz") and rng.random() < 0.5:
                buf = io.BytesIO()
                np.savez(buf, vertices=np.array([Payload(canary)], dtype=object), faces=np.zeros((1, 3), np.int32))
                yield kind, name, buf.getvalue()
            else:
                yield kind, name, _pickles(canary, rng)
        else:
            yield kind, "b.ply.gz", gzip.compress(b"ply\nformat ascii 1.0\n" + b"0 " * int(rng.integers(1 << 24, 1 << 26)),
                                                  compresslevel=9)


def _text_mutation(name: str, data: bytes, rng, counts: bool) -> bytes:
    """Numbers in the file's text part (a glTF's JSON, a PLY/OFF header, OBJ lines) replaced by extreme ones; with
    counts, the first numbers (element counts, accessor counts, STL's triangle count) by huge ones."""
    import re

    extreme = [b"nan", b"inf", b"-1", b"0", b"4294967295", b"2000000000", b"1e308", b"-2147483648", b"99999999999"]
    if name.endswith(".stl") and counts:
        return data[:80] + int(rng.choice([0, 1 << 31, (1 << 32) - 1])).to_bytes(4, "little") + data[84:]
    cut = data.find(b"end_header") if name.endswith(".ply") else (data.find(b"BIN") if name.endswith(".glb") else -1)
    head, tail = (data[:cut], data[cut:]) if cut > 0 else (data, b"")
    spans = [m.span() for m in re.finditer(rb"-?\d+(\.\d+)?(e-?\d+)?", head)]
    if not spans:
        return _flip(data, rng)
    pool = spans[:12] if counts else spans
    out = bytearray(head)
    for _ in range(int(rng.integers(1, 4))):
        a, b = pool[int(rng.integers(len(pool)))]
        if b <= len(out):
            value = extreme[int(rng.integers(len(extreme)))]
            out[a:b] = value.ljust(b - a) if len(value) <= b - a and name.endswith(".glb") else value
            if not name.endswith(".glb"):
                break  # offsets after an edit moved; one edit per case in text files
    return bytes(out) + tail


def read_mesh_case(path: Path, mesh) -> str:
    from nbvh_core.app.library_assets import load_asset

    load_asset(str(path), "m")
    return "read"


# --------------------------------------------------------------------------------------------------- the runner
def _status_kb(field: str) -> int:
    for line in open("/proc/self/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def run_case(reader, path: Path, data: bytes, mesh, canary: Path) -> tuple[str, int, str]:
    """(outcome, peak KB the case added to its process, detail) of one case, read in a forked child. The growth is
    the child's peak resident size (its own wait4 rusage) less its resident size when it started."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: read, report one line, exit without cleanup
        os.close(r)
        os.write(w, (json.dumps({"start_kb": _status_kb("VmRSS")}) + "\n").encode())
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        vm = int(open("/proc/self/statm").read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
        resource.setrlimit(resource.RLIMIT_AS, (vm + MEMORY_CAP, hard))
        signal.alarm(CASE_SECONDS)
        try:
            path.write_bytes(data)
            out, detail = reader(path, mesh), ""
        except ValueError as exc:  # MeshError, CheckpointError, NBVHFileError: the one-line refusals
            msg = str(exc)
            out, detail = ("refused" if msg and "\n" not in msg else "other"), msg[:200]
        except BaseException as exc:  # noqa: BLE001  (anything else is a reader bug, counted)
            out, detail = "other", f"{type(exc).__name__}: {str(exc)[:200]}"
        os.write(w, json.dumps({"out": out, "detail": detail}).encode())
        os._exit(0)
    os.close(w)
    _, status, usage = os.wait4(pid, 0)
    reply = b""
    while chunk := os.read(r, 65536):
        reply += chunk
    os.close(r)
    lines = reply.decode().splitlines()
    start_kb = json.loads(lines[0])["start_kb"] if lines else 0
    grown = max(0, usage.ru_maxrss - start_kb)
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        return ("hang" if sig == signal.SIGALRM else "crash"), grown, f"signal {sig}"
    result = json.loads(lines[1]) if len(lines) > 1 else {"out": "crash", "detail": "no reply"}
    if canary.exists():
        canary.unlink()
        return "executed", grown, result["detail"]
    if grown > 128 * 1024 + 20 * len(data) // 1024:
        return "over_memory", grown, result["detail"]
    return result["out"], grown, result["detail"]


def main() -> None:
    import warnings

    warnings.simplefilter("ignore")  # repairs of mutated meshes (dropped triangles) are expected, not findings
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kind", choices=("checkpoint", "mesh"), required=True)
    ap.add_argument("--cases", type=int, default=5000)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--out", default=str(RESULTS / "fuzz_files.csv"))
    ap.add_argument("--failures", default=None, help="write the failing cases' details here (JSON lines)")
    args = ap.parse_args()
    counts: dict[str, int] = {}
    peak, failures = 0, []
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        canary = folder / "canary"
        if args.kind == "checkpoint":
            seed, mesh = checkpoint_seed(folder)
            read_checkpoint_case(folder / "seed.ckpt", mesh)  # warm: every lazy import done before forking
            cases = ((kind, "case.ckpt", data) for kind, data in checkpoint_cases(seed, args.cases, args.seed,
                                                                                 str(canary)))
            reader = read_checkpoint_case
        else:
            seeds, mesh = mesh_seeds(folder), None
            for name, data in seeds.items():
                (folder / name).write_bytes(data)
                read_mesh_case(folder / name, None)
            cases = mesh_cases(seeds, args.cases, args.seed, str(canary))
            reader = read_mesh_case
        for i, (kind, name, data) in enumerate(cases):
            out, grown, detail = run_case(reader, folder / f"case_{name}", data, mesh, canary)
            counts[out] = counts.get(out, 0) + 1
            peak = max(peak, grown)
            if out not in ("read", "refused"):
                failures.append({"i": i, "kind": kind, "file": name, "out": out, "detail": detail})
            if (i + 1) % 500 == 0:
                print(f"{i + 1} cases: {counts}", flush=True)

    row = {"date": time.strftime("%Y-%m-%d %H:%M"), "reader": args.kind, "cases": args.cases, "seed": args.seed,
           **{k: counts.get(k, 0) for k in ("read", "refused", "other", "crash", "hang", "executed", "over_memory")},
           "max_added_rss_mb": round(peak / 1024, 1), "seconds": round(time.time() - t0, 1)}
    print(row)
    for f in failures[:20]:
        print(f)
    if args.failures:
        Path(args.failures).write_text("".join(json.dumps(f) + "\n" for f in failures))
    append_rows(args.out, [row])


if __name__ == "__main__":
    main()
