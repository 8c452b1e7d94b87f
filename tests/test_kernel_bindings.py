"""The typed kernel boundary: nbvh_kernels.h is the one declaration of every C entry, bindings.py checks each call
against it, and the ABI version is the header's hash."""
from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from nbvh_core import kernels
from nbvh_core.kernels import bindings, library
from nbvh_core.neural.encodings.base import EncodingConfig
from nbvh_core.neural.encodings.fused import GridSpec


def _defined_entries() -> set[str]:
    """The `nbvh_*` functions the C++ sources define (inside their extern "C" blocks)."""
    names = set()
    for src in library.sources():
        names |= set(re.findall(r"^(?:extern \"C\" )?(?:void\s*\*|void|int|uint64_t)\s+(nbvh_\w+)\(", src.read_text(),
                                re.M))
    return names


def test_every_entry_is_declared_once_in_the_header_and_defined_once():
    declared = bindings.declarations()
    assert set(declared) == _defined_entries()
    text = re.sub(r"//.*", "", library.HEADER.read_text())
    for name in declared:
        assert len(re.findall(rf"\b{name}\(", text)) == 1, name
    train = declared["nbvh_net_train"].params
    assert len(train) == 38 and train[0].name == "rays_o" and train[-1].name == "threads"
    loss = next(p for p in train if p.name == "loss_out")
    assert loss.shape == ("4 + kmlp",) and loss.dtypes == ("float64",) and not loss.nullable
    table = next(p for p in declared["nbvh_net_segments"].params if p.name == "table")
    assert table.dtypes == ("float32", "float16", "uint8")


def test_a_made_up_header_is_parsed_and_a_bad_annotation_refused():
    fake = ("extern \"C\" {\n// prose: void nbvh_not_this(int a);\n"
            "void nbvh_x(const float* a /* (n, 3) */, int64_t n, const void* t /* (?) f16 null */,\n"
            "            double w, void* handle);\n}")
    entry = bindings.declarations(fake)["nbvh_x"]
    assert [p.name for p in entry.params] == ["a", "n", "t", "w", "handle"]
    assert entry.params[0].shape == ("n", "3") and entry.params[2].dtypes == ("float16",) and entry.params[2].nullable
    assert entry.params[4].shape is None and set(bindings.declarations(fake)) == {"nbvh_x"}
    with pytest.raises(ValueError, match="shape expression"):
        bindings.declarations("void nbvh_y(const float* a /* (os.system) */);")
    with pytest.raises(ValueError, match="element types"):
        bindings.declarations("void nbvh_y(const void* a /* (n) */, int n);")


def test_the_abi_version_is_the_headers_hash_and_the_library_carries_it():
    data = library.HEADER.read_bytes()
    assert library.abi_hash(data) == library.abi_hash() and library.abi_hash(data + b" ") != library.abi_hash(data)
    assert "abi_version" not in library.HEADER.read_text()  # no hand-kept number
    lib = kernels.load()
    if lib is None:
        pytest.skip(kernels.describe())
    assert lib.nbvh_abi_hash() == library.abi_hash()


def _encode_args(n: int = 5) -> dict:
    cfg = EncodingConfig(levels=2, features=2, log2_table=6)
    spec = GridSpec(cfg, 1 << cfg.log2_table)
    table = torch.randn(cfg.levels, 1 << cfg.log2_table, cfg.features)
    return dict(points=torch.rand(n, 3), n=n, table=table, out=torch.empty(n, cfg.levels * cfg.features),
                **spec.args(table.shape[1], None, 0))


def test_a_well_formed_call_runs_and_each_kind_of_mistake_is_refused_before_c():
    if kernels.load() is None:
        pytest.skip(kernels.describe())
    args = _encode_args()
    bindings.encode_forward(**args)
    assert torch.isfinite(args["out"]).all() and args["out"].abs().sum() > 0
    swapped = {**args, "points": args["out"], "out": args["points"]}  # two float32 tensors swapped
    with pytest.raises(bindings.KernelArgumentError, match="points must have .* 15 elements, got 20"):
        bindings.encode_forward(**swapped)
    mistakes = [
        ({"table": args["table"].half()}, "table must be float32, got float16"),
        ({"res": args["res"].to(torch.int32)}, "res must be int64"),
        ({"points": torch.rand(3, 5).t()}, "contiguous"),
        ({"scales": None}, "scales may not be None"),
        ({"n": True}, "n must be a number"),
        ({"levels": 2.0}, "levels must be a number"),
        ({"table": torch.randn(127)}, "table must have .* multiple of 2"),
        ({"out": [0.0] * 20}, "tensor or numpy array"),
    ]
    for change, message in mistakes:
        with pytest.raises(bindings.KernelArgumentError, match=message):
            bindings.encode_forward(**{**args, **change})
    with pytest.raises(bindings.KernelArgumentError, match=r"missing \['out'\]"):
        bindings.encode_forward(**{k: v for k, v in args.items() if k != "out"})
    with pytest.raises(bindings.KernelArgumentError, match=r"unknown \['outt'\]"):
        bindings.encode_forward(**args, outt=1)
    with pytest.raises(AttributeError):
        bindings.no_such_kernel  # noqa: B018


def test_numpy_arrays_pass_like_tensors_and_nullable_pointers_take_none():
    if kernels.load() is None:
        pytest.skip(kernels.describe())
    args = _encode_args()
    ref = args["out"]
    bindings.encode_forward(**args)
    out = np.zeros((5, 4), np.float32)
    bindings.encode_forward(**{**args, "points": args["points"].numpy(), "out": out, "codes": None})
    assert np.array_equal(out, ref.numpy())
