"""The .nbvh header, checked: what a stored header must say, and the record (`Header`) the reader builds from it.

The reader trusts nothing: `check_header` validates every header field's type and range, derives the exact shape
and size of every tensor from the config (`layout.expected_tensors`) *before anything is allocated*, and refuses a
table that disagrees. Every refusal is an `NBVHFileError` (a ValueError) with one line saying which file and why.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

from .container import ALIGN, APPEARANCE_SINCE, PREFIX
from .errors import NBVHFileError
from .layout import expected_tensors, look_expected, nbytes
from ..geometry.bvh import MAX_NODES
from ..geometry.look import MAX_SLOTS, MAX_TEXTURE_SIDE
from ..neural.appearance import TARGETS, AppearanceConfig
from ..neural.encodings import ENCODINGS, EncodingConfig
from ..neural.model import ModelConfig
from ..neural.networks import NETWORKS, NetworkConfig
from ..neural.quantize import StorageConfig

#: Most patches an appearance head may tell apart (its slots are stored as uint16).
MAX_PATCHES = 65535
#: The reader's limits on header fields (far above any real model; they bound what a crafted header can ask).
LIMITS = {"levels": (1, 16), "n_min": (1, 1 << 16), "n_max": (1, 1 << 16), "features": (1, 64),
          "log2_table": (1, 24), "index_factor": (1, 1024), "candidates": (2, 256), "k": (2, 64),
          "hidden": (0, 16), "width": (1, 1024)}


@dataclass
class Header:
    """A checked header. fields: the JSON object as stored (config, transform, storage, tensors, metadata,
    appearance); version: the file's (major, minor); header_len: the stored header's bytes; config, storage: as
    parsed; expected: name -> (shape, kind) of every tensor (`layout`); look: (head config or None, materials) or
    None."""

    fields: dict
    version: tuple[int, int]
    header_len: int
    config: ModelConfig
    storage: StorageConfig
    expected: dict
    look: tuple | None

    @property
    def payload_start(self) -> int:
        """Offset of the first tensor in the file."""
        return PREFIX.size + self.header_len

    @property
    def tensors(self) -> list[dict]:
        return self.fields["tensors"]

    @property
    def metadata(self) -> dict:
        return self.fields.get("metadata", {})


def _int_field(d: dict, key: str, where: str, lo: int, hi: int) -> int:
    v = d.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise NBVHFileError(f"{where}: header field {key!r} must be an integer in [{lo}, {hi}], got {v!r:.40}")
    return v


def _config_from(d, cls, where: str, what: str):
    """A dataclass config from a header dict: known fields only, each of its default's type, ints in LIMITS."""
    if not isinstance(d, dict):
        raise NBVHFileError(f"{where}: header field {what!r} must be an object")
    known = {f.name: f for f in fields(cls)}
    unknown = set(d) - set(known)
    if unknown:
        raise NBVHFileError(f"{where}: unknown {what} field(s) {', '.join(sorted(map(str, unknown)))[:80]}")
    kw = {}
    default = cls()
    for name, v in d.items():
        want = type(getattr(default, name))
        if want is type(None) and v is not None:  # an optional count (None: its default meaning)
            want = int
        if want is int:
            lo, hi = LIMITS.get(name, (-(1 << 31), 1 << 31))
            kw[name] = _int_field(d, name, where, lo, hi)
        elif want is float:
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
                raise NBVHFileError(f"{where}: {what} field {name!r} must be a finite number, got {v!r:.40}")
            kw[name] = float(v)
        elif not isinstance(v, want):
            raise NBVHFileError(f"{where}: {what} field {name!r} must be a {want.__name__}, got {v!r:.40}")
        else:
            kw[name] = v
    try:  # the config's own checks (a loss or kind it does not know): still the reader's one-line refusal
        return cls(**kw)
    except ValueError as exc:
        raise NBVHFileError(f"{where}: {what}: {exc}") from None


def _model_config(header: dict, where: str) -> ModelConfig:
    cfg = header.get("config")
    if not isinstance(cfg, dict):
        raise NBVHFileError(f"{where}: header field 'config' must be an object")
    enc = _config_from(cfg.get("encoding"), EncodingConfig, where, "encoding")
    net = _config_from(cfg.get("network"), NetworkConfig, where, "network")
    if enc.kind not in ENCODINGS or net.kind not in NETWORKS:
        raise NBVHFileError(f"{where}: unknown encoding {enc.kind!r:.20} or network {net.kind!r:.20}")
    if enc.kind == "hashvqad" and enc.candidates & (enc.candidates - 1):
        raise NBVHFileError(f"{where}: HashVQAD candidates must be a power of two, got {enc.candidates}")
    if enc.n_max < enc.n_min:
        raise NBVHFileError(f"{where}: n_max {enc.n_max} < n_min {enc.n_min}")
    return ModelConfig(enc, net)


def _storage(header: dict, major: int, where: str) -> StorageConfig:
    if major == 1:
        fb = header.get("float_bytes")
        if fb not in (2, 4) or isinstance(fb, bool):
            raise NBVHFileError(f"{where}: header field 'float_bytes' must be 2 or 4, got {fb!r:.40}")
        bits = 8 * fb
        return StorageConfig(table_bits=bits, network_bits=bits, node_bits=32)
    st = header.get("storage")
    if not isinstance(st, dict) or set(st) != {"table_bits", "network_bits", "node_bits"}:
        raise NBVHFileError(f"{where}: header field 'storage' must name table_bits, network_bits and node_bits")
    try:
        return StorageConfig(**st)
    except (TypeError, ValueError) as exc:
        raise NBVHFileError(f"{where}: bad storage: {exc}") from None


def check_header(header: dict, version: tuple[int, int], header_len: int, payload: int, where: str) -> Header:
    """The stored header `header` of a file of `version` whose payload holds `payload` bytes, checked: every field
    the reader uses (types, ranges) and a tensor table that matches the config exactly. Raises NBVHFileError."""
    cfg = _model_config(header, where)
    storage = _storage(header, version[0], where)
    tf = header.get("transform")
    if (not isinstance(tf, dict) or not isinstance(tf.get("scale"), (int, float)) or isinstance(tf.get("scale"), bool)
            or not (math.isfinite(tf["scale"]) and tf["scale"] > 0) or not isinstance(tf.get("offset"), list)
            or len(tf["offset"]) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                       for v in tf["offset"])):
        raise NBVHFileError(f"{where}: header field 'transform' must be {{scale > 0, offset: 3 finite numbers}}")
    meta = header.get("metadata", {})
    if not isinstance(meta, dict):
        raise NBVHFileError(f"{where}: header field 'metadata' must be an object")
    _check_metadata(meta, where)
    tensors = header.get("tensors")
    if not isinstance(tensors, list):
        raise NBVHFileError(f"{where}: header field 'tensors' must be a list")
    by_name = {}
    for t in tensors:
        if not isinstance(t, dict) or not isinstance(t.get("name"), str) or not isinstance(t.get("component"), str):
            raise NBVHFileError(f"{where}: every tensor entry needs a name and a component")
        for key in ("offset", "nbytes"):
            _int_field(t, key, where, 0, payload)
        # a dimension cannot exceed the payload's bits (packed codes: down to 1 bit each); the exact size per
        # tensor is checked against the config below
        if not isinstance(t.get("shape"), list) or not all(isinstance(v, int) and not isinstance(v, bool) and
                                                          0 <= v <= 8 * payload for v in t["shape"]):
            raise NBVHFileError(f"{where}: tensor {t['name'][:40]!r} has a bad shape")
        if t["offset"] % ALIGN or t["offset"] + t["nbytes"] > payload:
            raise NBVHFileError(f"{where}: tensor {t['name'][:40]!r} extends past the end of the file or is "
                                "misaligned")
        if t["name"] in by_name:
            raise NBVHFileError(f"{where}: tensor {t['name'][:40]!r} appears twice")
        by_name[t["name"]] = t
    node_tensor = by_name.get("bvh" if storage.node_bits == 32 else "bvh.boxes")
    if node_tensor is None or not node_tensor["shape"] or not 1 <= node_tensor["shape"][0] <= MAX_NODES:
        raise NBVHFileError(f"{where}: the BVH tensor is missing or its node count is not in [1, {MAX_NODES}]")
    expected = expected_tensors(cfg, storage, node_tensor["shape"][0], version, shape_only="bvh.shape" in by_name)
    look = _look_spec(header, version, where)
    expected.update(look_expected(look, storage, by_name, where))
    if set(expected) != set(by_name):
        missing, extra = sorted(set(expected) - set(by_name)), sorted(set(by_name) - set(expected))
        raise NBVHFileError(f"{where}: tensors do not match the config (missing {missing[:3]}, unexpected "
                            f"{[e[:40] for e in extra[:3]]})")
    end = 0
    for t in tensors:  # in file order, non-overlapping
        shape, kind = expected[t["name"]]
        if tuple(t["shape"]) != shape or t["nbytes"] != nbytes(shape, kind):
            raise NBVHFileError(f"{where}: tensor {t['name']!r} is {t['shape']} / {t['nbytes']} B; the config "
                                f"says {list(shape)} / {nbytes(shape, kind)} B")
        if t["offset"] < end:
            raise NBVHFileError(f"{where}: tensor {t['name']!r} overlaps the one before it")
        end = t["offset"] + t["nbytes"]
    return Header(header, version, header_len, cfg, storage, expected, look)


def _look_spec(header: dict, version: tuple[int, int], where: str) -> tuple[AppearanceConfig | None, list[dict]] | None:
    """The header's `appearance` (format 2.3), checked: (head config or None, materials), or None when absent."""
    look = header.get("appearance")
    if look is None:
        return None
    if version < APPEARANCE_SINCE:
        raise NBVHFileError(f"{where}: an 'appearance' field in a format {version[0]}.{version[1]} file")
    if not isinstance(look, dict) or set(look) != {"config", "materials"}:
        raise NBVHFileError(f"{where}: header field 'appearance' must hold exactly 'config' and 'materials'")
    mats = look["materials"]
    if not isinstance(mats, list) or not 1 <= len(mats) <= MAX_SLOTS:
        raise NBVHFileError(f"{where}: appearance.materials must be a list of 1 to {MAX_SLOTS} materials")
    for m in mats:
        color = m.get("base_color") if isinstance(m, dict) else None
        image = m.get("image") if isinstance(m, dict) else None
        if (not isinstance(m, dict) or set(m) != {"name", "base_color", "image"} or not isinstance(m["name"], str)
                or len(m["name"]) > 256 or not isinstance(color, list) or len(color) != 4
                or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and 0 <= c <= 1 for c in color)):
            raise NBVHFileError(f"{where}: a material needs a name and a base_color of 4 numbers in [0, 1]")
        if image is not None and not (isinstance(image, list) and len(image) == 3 and all(
                isinstance(v, int) and not isinstance(v, bool) for v in image) and 1 <= image[0] <= MAX_TEXTURE_SIDE
                and 1 <= image[1] <= MAX_TEXTURE_SIDE and image[2] in (3, 4)):
            raise NBVHFileError(f"{where}: material {m['name'][:40]!r}: image must be [height, width, 3|4] with "
                                f"sides up to {MAX_TEXTURE_SIDE}")
    cfg = None
    if look["config"] is not None:
        cfg = _config_from(look["config"], AppearanceConfig, where, "appearance config")
        if (cfg.slots != len(mats) or not 1 <= cfg.patches <= MAX_PATCHES or cfg.outputs == 0
                or cfg.patch_degree not in (1, 2, 3) or cfg.target not in TARGETS
                or not (cfg.mapped_patches is None or (isinstance(cfg.mapped_patches, int)
                                                       and 0 <= cfg.mapped_patches <= cfg.patches))):
            raise NBVHFileError(f"{where}: the appearance head's {cfg.slots} slots and {cfg.patches} patches do not "
                                f"match {len(mats)} materials (1 to {MAX_PATCHES} patches)")
    return cfg, mats


def _check_metadata(meta: dict, where: str) -> None:
    """The metadata fields tools print must have the types they print."""
    def number(v):
        return v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))

    for key in ("source", "quality", "training", "settings", "assessment"):
        if key in meta and meta[key] is not None and not isinstance(meta[key], dict):
            raise NBVHFileError(f"{where}: metadata field {key!r} must be an object")
    q = meta.get("quality") or {}
    for key in ("mse", "silhouette_iou", "depth_error"):
        if key in q and not number(q[key]):
            raise NBVHFileError(f"{where}: metadata quality.{key} must be a number")
    s = meta.get("source") or {}
    if "triangles" in s and not (isinstance(s["triangles"], int) and not isinstance(s["triangles"], bool)):
        raise NBVHFileError(f"{where}: metadata source.triangles must be an integer")
    if "name" in s and not isinstance(s["name"], str):
        raise NBVHFileError(f"{where}: metadata source.name must be a string")
    tr = meta.get("training") or {}
    for key in ("steps", "seconds", "samples", "samples_per_s", "final_loss"):
        if key in tr and not number(tr[key]):
            raise NBVHFileError(f"{where}: metadata training.{key} must be a number")
