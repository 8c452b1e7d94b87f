"""Training checkpoints as data: a safetensors file (tensors only; the format cannot hold code) whose metadata
carries one JSON header, both validated before anything in them is used.

    write_checkpoint(path, state)      # atomically (outputs.write_atomic)
    read_checkpoint(path) -> Checkpoint(header, tensors)   # or CheckpointError, one line
    load_checkpoint(path, model, opt, device) -> the rest of the state   # into a model and its optimizer

Layout (safetensors, https://github.com/huggingface/safetensors: u64 header length, JSON header, tensor bytes):
* tensors: `model.NAME` (the model's state_dict), `optimizer.I.KEY` (Adam's state of parameter I:
  step, exp_avg, exp_avg_sq), `torch_rng` (uint8), `history` ((N, 2) float64 step, loss), and when present
  `leaf_errors`, `leaf_weights` (float64 per leaf), `cut` (int64 full-tree nodes), `qat_offset`, `qat_scale`
  ((L, F) float32);
* `__metadata__["nbvh"]`: JSON {kind, version, step, elapsed, numpy_rng {chunk_state, index},
  tree_cut_rounds_done, lr_scale (a recovery's lowered learning rate; absent: 1), train_config, extra (the caller's:
  the pipeline's {settings, mesh})}.

The reader trusts nothing: the file must be a regular file under MAX_BYTES; pickles (the format torch.save
writes) are recognised by their first bytes and refused without being opened; the header's length, JSON, names,
dtypes, shapes and offsets are checked against the file's size before a tensor is made, so allocations are
bounded by the file's own size; every header field is typed and ranged. What a tensor must look like for a given
model (shapes, dtypes) is checked as it is loaded into one (`load_checkpoint`), and the settings by
`settings.settings_from_dict`.
"""
from __future__ import annotations

import json
import math
import os
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

KIND = "nbvh-checkpoint"
VERSION = 1
#: A checkpoint holds a model, two Adam moments per parameter and small state: the largest preset's is ~40 MB.
MAX_BYTES = 4 << 30
MAX_HEADER_BYTES = 16 << 20
_DTYPES = {"F64": torch.float64, "F32": torch.float32, "F16": torch.float16, "I64": torch.int64,
           "I32": torch.int32, "I16": torch.int16, "U8": torch.uint8, "I8": torch.int8, "BOOL": torch.bool}
_NAME = re.compile(r"^(model\.[A-Za-z0-9_.]{1,120}|optimizer\.\d{1,6}\.(step|exp_avg|exp_avg_sq)|torch_rng|history|"
                   r"leaf_errors|leaf_weights|cut|qat_offset|qat_scale)$")
#: First bytes of what torch.save writes: a zip archive (torch >= 1.6) or a bare pickle (protocol 2-5).
_PICKLE_MAGIC = (b"PK\x03\x04", b"\x80\x02", b"\x80\x03", b"\x80\x04", b"\x80\x05")


class CheckpointError(ValueError):
    """A file that is not a usable checkpoint of this tool: one line saying which file and why."""


@dataclass
class Checkpoint:
    """A validated checkpoint: `header` (the JSON fields, typed and ranged) and `tensors` (name -> CPU tensor)."""

    header: dict
    tensors: dict[str, torch.Tensor]

    def get(self, name: str) -> torch.Tensor | None:
        return self.tensors.get(name)


# ------------------------------------------------------------------------------------------------- writing
def encode_checkpoint(state: dict) -> bytes:
    """A training state (see `training.checkpoints.checkpoint_state`) -> safetensors bytes. Keys of `state`: model (state_dict),
    optimizer (Adam's state_dict), step, elapsed, history [(step, loss)], numpy_rng {chunk_state, index,
    leaf_weights}, torch_rng, leaf_errors, cut, tree_cut_rounds_done, lr_scale, qat_affine, train_config, extra."""
    from safetensors.torch import save

    tensors = {f"model.{k}": v for k, v in state["model"].items()}
    for index, entry in state.get("optimizer", {}).get("state", {}).items():
        tensors.update({f"optimizer.{int(index)}.{k}": v for k, v in entry.items() if torch.is_tensor(v)})
    tensors["torch_rng"] = state["torch_rng"]
    tensors["history"] = torch.tensor(state.get("history") or [], dtype=torch.float64).reshape(-1, 2)
    rng = dict(state.get("numpy_rng") or {})
    optional = {"leaf_errors": state.get("leaf_errors"), "leaf_weights": rng.pop("leaf_weights", None),
                "cut": None if state.get("cut") is None else torch.tensor(state["cut"], dtype=torch.int64)}
    if state.get("qat_affine") is not None:
        optional["qat_offset"], optional["qat_scale"] = (torch.as_tensor(np.asarray(a)) for a in state["qat_affine"])
    tensors.update({k: torch.as_tensor(v) for k, v in optional.items() if v is not None})
    header = {"kind": KIND, "version": VERSION, "step": int(state.get("step", 0)),
              "elapsed": float(state.get("elapsed", 0.0)), "numpy_rng": _json_rng(rng),
              "tree_cut_rounds_done": int(state.get("tree_cut_rounds_done") or 0),
              "lr_scale": float(state.get("lr_scale", 1.0)),
              "train_config": state.get("train_config") or {}, "extra": state.get("extra") or {}}
    tensors = {k: v.detach().to("cpu").contiguous().clone() for k, v in tensors.items()}
    return save(tensors, metadata={"nbvh": json.dumps(header)})


def _json_rng(rng: dict) -> dict | None:
    """numpy's generator state (ints, possibly 128-bit) as JSON: Python's json keeps big integers exact."""
    if not rng:
        return None
    return {"chunk_state": rng["chunk_state"], "index": int(rng["index"])}


def write_checkpoint(path: str | os.PathLike, state: dict) -> None:
    """Encode `state` and write it atomically: a kill mid-write keeps the previous checkpoint."""
    from ..protocol.outputs import write_atomic

    write_atomic(Path(path), encode_checkpoint(state))


# ------------------------------------------------------------------------------------------------- reading
def read_checkpoint(path: str | os.PathLike) -> Checkpoint:
    """Read and validate a checkpoint. Raises CheckpointError (one line) for anything that is not one: a missing,
    special or oversized file, a pickle, a damaged container, a header field of the wrong type or range."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path}: no such checkpoint")
    if not path.is_file():
        raise CheckpointError(f"{path}: not a regular file")
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise CheckpointError(f"{path}: {size} bytes is larger than any checkpoint ({MAX_BYTES} at most)")
    with open(path, "rb") as f:
        data = f.read(size + 1)  # the size just read (a file that grew since is refused by its table)
    return decode_checkpoint(data, str(path))


def decode_checkpoint(data: bytes, where: str = "<bytes>") -> Checkpoint:
    """Validate and decode checkpoint bytes (see `read_checkpoint`)."""
    if data[:4] in _PICKLE_MAGIC or data[:2] in _PICKLE_MAGIC:
        raise CheckpointError(f"{where}: a pickled checkpoint (an older version's format, which can run code when "
                              "loaded); it is never opened: run again without --resume")
    entries, meta = _parse_container(data, where)
    header = _check_header(meta, where)
    from safetensors.torch import load

    try:
        tensors = load(data)
    except Exception as exc:  # the container was checked above; safetensors' own checks are a second line
        raise CheckpointError(f"{where}: damaged tensor data ({type(exc).__name__})") from None
    if set(tensors) != set(entries):
        raise CheckpointError(f"{where}: damaged tensor table")
    _check_tensors(tensors, where)
    return Checkpoint(header, tensors)


def _parse_container(data: bytes, where: str) -> tuple[dict, str]:
    """The safetensors table checked against the file: (entries, the 'nbvh' metadata string)."""
    if len(data) < 8:
        raise CheckpointError(f"{where}: too short to be a checkpoint ({len(data)} bytes)")
    (hlen,) = struct.unpack_from("<Q", data, 0)
    if not 2 <= hlen <= min(MAX_HEADER_BYTES, len(data) - 8):
        raise CheckpointError(f"{where}: not a checkpoint of this tool (header length {hlen} does not fit "
                              f"{len(data)} bytes)")
    try:
        table = json.loads(bytes(data[8:8 + hlen]))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise CheckpointError(f"{where}: not a checkpoint of this tool (unreadable header: {str(exc)[:60]})") from None
    if not isinstance(table, dict) or not isinstance(table.get("__metadata__"), dict):
        raise CheckpointError(f"{where}: not a checkpoint of this tool (no metadata)")
    meta = table.pop("__metadata__").get("nbvh")
    if not isinstance(meta, str):
        raise CheckpointError(f"{where}: not a checkpoint of this tool (a safetensors file without its header)")
    payload = len(data) - 8 - hlen
    spans = []
    for name, entry in table.items():
        spans.append(_check_entry(name, entry, payload, where))
    spans.sort()
    if any(a[1] > b[0] for a, b in zip(spans, spans[1:])):
        raise CheckpointError(f"{where}: damaged tensor table (overlapping tensors)")
    return table, meta


def _check_entry(name, entry, payload: int, where: str) -> tuple[int, int]:
    if not isinstance(name, str) or not _NAME.match(name):
        raise CheckpointError(f"{where}: unexpected tensor {str(name)[:60]!r}")
    if not isinstance(entry, dict) or set(entry) != {"dtype", "shape", "data_offsets"}:
        raise CheckpointError(f"{where}: damaged tensor table entry {name!r}")
    dtype, shape, offsets = entry["dtype"], entry["shape"], entry["data_offsets"]
    if not isinstance(dtype, str) or dtype not in _DTYPES:
        raise CheckpointError(f"{where}: tensor {name!r} has an unsupported dtype {str(dtype)[:20]!r}")
    if (not isinstance(shape, list) or len(shape) > 4
            or not all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n <= payload for n in shape)):
        raise CheckpointError(f"{where}: tensor {name!r} has a bad shape {str(shape)[:60]}")
    if (not isinstance(offsets, list) or len(offsets) != 2
            or not all(isinstance(n, int) and not isinstance(n, bool) for n in offsets)
            or not 0 <= offsets[0] <= offsets[1] <= payload):
        raise CheckpointError(f"{where}: tensor {name!r} lies outside the file")
    itemsize = torch.empty((), dtype=_DTYPES[dtype]).element_size()
    if math.prod(shape) * itemsize != offsets[1] - offsets[0]:
        raise CheckpointError(f"{where}: tensor {name!r}: shape {shape} does not match its {offsets[1] - offsets[0]} "
                              "bytes")
    return offsets[0], offsets[1]


def _int(d: dict, key: str, where: str, lo: int, hi: int) -> int:
    v = d.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise CheckpointError(f"{where}: header field {key!r} must be an integer in [{lo}, {hi}], got {str(v)[:40]}")
    return v


def _check_header(meta: str, where: str) -> dict:
    try:
        header = json.loads(meta)
    except (ValueError, RecursionError) as exc:
        raise CheckpointError(f"{where}: unreadable checkpoint header ({str(exc)[:60]})") from None
    if not isinstance(header, dict) or header.get("kind") != KIND:
        raise CheckpointError(f"{where}: not a checkpoint of this tool (kind {str(header.get('kind') if isinstance(header, dict) else None)[:30]!r})")
    if header.get("version") != VERSION:
        raise CheckpointError(f"{where}: checkpoint version {str(header.get('version'))[:20]} is not readable "
                              f"(this tool reads {VERSION}): run again without --resume")
    _int(header, "step", where, 0, 1 << 40)
    _int(header, "tree_cut_rounds_done", where, 0, 1 << 20)
    elapsed = header.get("elapsed")
    if not isinstance(elapsed, (int, float)) or isinstance(elapsed, bool) or not 0 <= elapsed < 1e9:
        raise CheckpointError(f"{where}: header field 'elapsed' must be a number of seconds, got {str(elapsed)[:40]}")
    scale = header.setdefault("lr_scale", 1.0)  # absent before recoveries (read as the schedule's own rate)
    if not isinstance(scale, (int, float)) or isinstance(scale, bool) or not 1e-9 <= scale <= 1.0:
        raise CheckpointError(f"{where}: header field 'lr_scale' must be a number in (0, 1], got {str(scale)[:40]}")
    for key in ("train_config", "extra"):
        if not isinstance(header.get(key), dict):
            raise CheckpointError(f"{where}: header field {key!r} must be an object")
    header["numpy_rng"] = _check_rng(header.get("numpy_rng"), where)
    return header


def _check_rng(rng, where: str) -> dict | None:
    """numpy's PCG64 state, every number in its range (numpy would accept some out-of-range values silently)."""
    if rng is None:
        return None
    bad = CheckpointError(f"{where}: header field 'numpy_rng' is not a PCG64 generator state")
    if not isinstance(rng, dict) or set(rng) != {"chunk_state", "index"}:
        raise bad
    _int(rng, "index", where, -1, 1 << 20)
    st = rng["chunk_state"]
    if (not isinstance(st, dict) or st.get("bit_generator") != "PCG64"
            or set(st) != {"bit_generator", "state", "has_uint32", "uinteger"}
            or not isinstance(st["state"], dict) or set(st["state"]) != {"state", "inc"}):
        raise bad
    _int(st["state"], "state", where, 0, (1 << 128) - 1)
    _int(st["state"], "inc", where, 0, (1 << 128) - 1)
    _int(st, "has_uint32", where, 0, 1)
    _int(st, "uinteger", where, 0, (1 << 32) - 1)
    return rng


def _check_tensors(tensors: dict, where: str) -> None:
    """The tensors every checkpoint holds, with the dtypes and shapes that do not depend on the model."""
    expected_rng = torch.get_rng_state()
    rng = tensors.get("torch_rng")
    if rng is None or rng.dtype != torch.uint8 or rng.shape != expected_rng.shape:
        raise CheckpointError(f"{where}: the torch generator state is missing or not {tuple(expected_rng.shape)} uint8")
    history = tensors.get("history")
    if history is None or history.dtype != torch.float64 or history.dim() != 2 or history.shape[1] != 2:
        raise CheckpointError(f"{where}: the loss history is missing or not (N, 2) float64")
    for name in ("leaf_errors", "leaf_weights", "qat_offset", "qat_scale"):
        t = tensors.get(name)
        if t is not None and (not t.is_floating_point() or not torch.isfinite(t).all() or (t < 0).any()
                              and name != "qat_offset"):
            raise CheckpointError(f"{where}: tensor {name!r} holds negative or non-finite values")
    if (tensors.get("qat_offset") is None) != (tensors.get("qat_scale") is None):
        raise CheckpointError(f"{where}: the quantization map needs both its offset and its scale")
    for name, t in tensors.items():
        if name.startswith(("model.", "optimizer.")) and t.is_floating_point() and not torch.isfinite(t).all():
            raise CheckpointError(f"{where}: tensor {name!r} holds NaN or infinite values")


# ------------------------------------------------------------------------------------- into a model
def load_checkpoint(path: str | os.PathLike, model: torch.nn.Module, opt: torch.optim.Optimizer,
                    device: torch.device) -> dict:
    """Load a checkpoint's model (a NeuralBVH), optimizer moments and torch RNG state into `model` and `opt`, after
    checking every tensor against what this model holds (names, shapes, dtypes); returns the rest for the other
    parts of a training (`training.checkpoints` gathers them when it writes): step,
    elapsed, history [(step, loss)], numpy_rng {chunk_state, index, leaf_weights}, leaf_errors, cut,
    tree_cut_rounds_done, lr_scale, qat_affine. Raises CheckpointError (one line) for a file that does not fit."""
    ck = read_checkpoint(path)
    where = str(path)
    codes = ck.get("model.encoding.codes")
    if codes is not None and codes.numel() and model.encoding.learned_index:
        model.encoding.freeze()  # the checkpoint is past the freeze: same structure before loading
    model.load_state_dict(_matching(ck.tensors, "model.", model.state_dict(), where))
    opt.load_state_dict(_optimizer_state(ck.tensors, opt, where))
    torch.set_rng_state(ck.tensors["torch_rng"])
    h = ck.header
    rng = None if h["numpy_rng"] is None else dict(h["numpy_rng"], leaf_weights=_numpy(ck.get("leaf_weights")))
    qat = ck.get("qat_offset"), ck.get("qat_scale")
    return {"step": h["step"], "elapsed": float(h["elapsed"]),
            "history": [(int(s), float(v)) for s, v in ck.tensors["history"].tolist()], "numpy_rng": rng,
            "leaf_errors": ck.get("leaf_errors"), "cut": None if ck.get("cut") is None else ck.get("cut").tolist(),
            "tree_cut_rounds_done": h["tree_cut_rounds_done"], "lr_scale": h["lr_scale"],
            "qat_affine": None if qat[0] is None else (qat[0].numpy(), qat[1].numpy())}


def _numpy(t: torch.Tensor | None) -> np.ndarray | None:
    return None if t is None else t.numpy()


def _matching(tensors: dict, prefix: str, expected: dict, where: str) -> dict:
    """The checkpoint's tensors under `prefix`, refused unless they are exactly `expected`'s names, shapes, dtypes."""
    got = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
    if set(got) != set(expected):
        odd = sorted(set(got) ^ set(expected))[:3]
        raise CheckpointError(f"{where}: the checkpoint does not hold this model's tensors (differs in {odd})")
    for name, want in expected.items():
        if got[name].shape != want.shape or got[name].dtype != want.dtype:
            raise CheckpointError(f"{where}: tensor {name!r} is {tuple(got[name].shape)} {got[name].dtype}, this "
                                  f"model's is {tuple(want.shape)} {want.dtype}")
    return got


def _optimizer_state(tensors: dict, opt: torch.optim.Optimizer, where: str) -> dict:
    """Adam's state_dict: the structure and hyperparameters of `opt` (this run's own: nothing of the file's but
    numbers), the moments and step counts of the file, each checked against its parameter."""
    own = opt.state_dict()
    params = [p for g in opt.param_groups for p in g["params"]]
    state = {}
    for i, p in enumerate(params):
        entry = {k.split(".")[-1]: v for k, v in tensors.items() if k.startswith(f"optimizer.{i}.")}
        if not entry:
            continue
        want = {"step": torch.zeros((), dtype=torch.float32), "exp_avg": p.detach().cpu(),
                "exp_avg_sq": p.detach().cpu()}
        state[i] = _matching({f"{k}": v for k, v in entry.items()}, "", want, where)
    if any(int(k.split(".")[1]) >= len(params) for k in tensors if k.startswith("optimizer.")):
        raise CheckpointError(f"{where}: optimizer state for a parameter this model does not have")
    return {"state": state, "param_groups": own["param_groups"]}
