"""The one module that calls the compiled kernels: every entry point of `native/nbvh_kernels.h`, called by keyword.

`call("net_train", rays_o=..., ...)` (or `bindings.net_train(...)`) checks the arguments against the header's
declaration before anything reaches C: every parameter named exactly once; pointers given as contiguous CPU
arrays (torch tensors or numpy arrays) of the declared element type and size (the header's `/* (shape) */`
comments, evaluated in the call's own scalar arguments), or None where the header says `null`; integers and
floats as numbers. Two tensors swapped, a float16 table where float32 is read, a stack one row short: each is
refused with the entry, the parameter and what was expected, instead of corrupting memory. `threads` defaults to
`library.threads()`.

The check costs ~2.6 us per argument (measured: 44 us for a 15-argument call against 5 us bare; the training
step's 38 arguments: ~0.1 ms of a ~30 ms step; docs/results.md).
"""
from __future__ import annotations

import ast
import ctypes
import re
from dataclasses import dataclass
from functools import lru_cache
from numbers import Integral, Real

import numpy as np
import torch

from . import library

#: C element type -> array dtype name (torch's and numpy's names agree).
_ELEMENT = {"float": "float32", "double": "float64", "int64_t": "int64", "int32_t": "int32", "uint8_t": "uint8",
            "uint16_t": "uint16"}
#: `void*` data annotations -> dtype names.
_TAGS = {"f32": "float32", "f16": "float16", "u8": "uint8"}
_SCALAR = {"int": ctypes.c_int, "int64_t": ctypes.c_int64, "uint64_t": ctypes.c_uint64, "float": ctypes.c_float,
           "double": ctypes.c_double}


class KernelArgumentError(TypeError):
    """An argument does not match the entry's declaration in nbvh_kernels.h."""


@dataclass(frozen=True)
class Param:
    """One parameter as the header declares it. ctype: 'float', 'int64_t', ... (without const and *)."""

    name: str
    ctype: str
    pointer: bool
    shape: tuple[str, ...] | None = None  # dimension expressions; None: an opaque pointer (a handle)
    dtypes: tuple[str, ...] = ()         # the array dtypes accepted
    nullable: bool = False


@dataclass(frozen=True)
class Entry:
    """One C entry point: its name, return type ('void', 'void*', 'uint64_t') and parameters in order."""

    name: str
    returns: str
    params: tuple[Param, ...]


_DECL = re.compile(r"^(void\s*\*|void|int|uint64_t)\s+(nbvh_\w+)\((.*?)\);", re.M | re.S)
_PARAM = re.compile(r"\s*(?:const\s+)?(\w+)\s*(\*?)\s*(\w+)\s*(?:/\*(.*?)\*/)?\s*(?:,|$)", re.S)
_ANNOTATION = re.compile(r"^\(([^)]*)\)\s*(.*)$")


def _check_expression(expr: str, where: str) -> None:
    """A shape dimension may use only integers, parameter names, +, - and *."""
    allowed = (ast.Expression, ast.BinOp, ast.Add, ast.Sub, ast.Mult, ast.Name, ast.Load, ast.Constant)
    for node in ast.walk(ast.parse(expr, mode="eval")):
        if not isinstance(node, allowed) or isinstance(node, ast.Constant) and not isinstance(node.value, int):
            raise ValueError(f"{where}: unsupported shape expression {expr!r}")


def _param(ctype: str, star: str, name: str, note: str | None, where: str) -> Param:
    if not star:
        if ctype not in _SCALAR:
            raise ValueError(f"{where}: unsupported scalar type {ctype}")
        return Param(name, ctype, pointer=False)
    if note is None:  # an opaque pointer: a handle the library returned
        return Param(name, ctype, pointer=True)
    m = _ANNOTATION.match(note.strip())
    if m is None:
        raise ValueError(f"{where}: parameter {name}: annotation {note!r} is not '(shape) [dtypes] [null]'")
    shape = tuple(d.strip() for d in m.group(1).split(",") if d.strip())
    for dim in shape:
        if dim != "?":
            _check_expression(dim, f"{where}.{name}")
    words = m.group(2).split()
    tags = [w for w in words if w != "null"]
    if ctype == "void":
        if not tags or any(w not in _TAGS for w in tags):
            raise ValueError(f"{where}: void* parameter {name} needs its element types ({' '.join(_TAGS)})")
        dtypes = tuple(_TAGS[w] for w in tags)
    else:
        if tags:
            raise ValueError(f"{where}: parameter {name} is typed by C ({ctype}); unexpected {tags}")
        dtypes = (_ELEMENT[ctype],)
    return Param(name, ctype, pointer=True, shape=shape, dtypes=dtypes, nullable="null" in words)


def declarations(header: str | None = None) -> dict[str, Entry]:
    """{name: Entry} of every `nbvh_*` entry the header declares (`header`: its text; default the package's)."""
    text = header if header is not None else library.HEADER.read_text()
    text = re.sub(r"^\s*//.*$", "", text, flags=re.M)  # line comments: prose, not declarations
    out = {}
    for m in _DECL.finditer(text):
        returns, name, params = m.group(1).replace(" ", ""), m.group(2), m.group(3)
        parsed = tuple(_param(*p.groups()[:4], where=name) for p in _PARAM.finditer(params) if p.group(3))
        out[name] = Entry(name, returns, parsed)
    return out


@lru_cache(maxsize=1)
def _entries() -> dict[str, Entry]:
    return declarations()


@lru_cache(maxsize=None)
def _function(name: str):
    """The library's function `name`, its ctypes argument and return types set from the header."""
    lib = library.load()
    if lib is None:
        raise RuntimeError(f"the fused kernels are unavailable: {library.describe()}")
    entry = _entries()[name]
    fn = getattr(lib, name)
    fn.argtypes = [ctypes.c_void_p if p.pointer else _SCALAR[p.ctype] for p in entry.params]
    fn.restype = {"void": None, "void*": ctypes.c_void_p, **_SCALAR}[entry.returns]
    return fn


@lru_cache(maxsize=None)
def _compiled(expr: str):
    """A shape dimension compiled once (`_check_expression` allowed it when the header was read)."""
    return compile(expr, "<nbvh_kernels.h>", "eval")


def _dtype_name(array) -> str:
    return str(array.dtype).removeprefix("torch.")


def _address(entry: Entry, p: Param, value, scalars: dict) -> int | None:
    """The address of an array argument after checking it against its declaration."""
    where = f"{entry.name}: {p.name}"
    if value is None:
        if p.nullable or p.shape is None:
            return None
        raise KernelArgumentError(f"{where} may not be None")
    if p.shape is None:  # an opaque handle
        if not isinstance(value, Integral):
            raise KernelArgumentError(f"{where} is a handle (an int), got {type(value).__name__}")
        return int(value)
    if isinstance(value, torch.Tensor):
        if value.device.type != "cpu" or not value.is_contiguous():
            raise KernelArgumentError(f"{where} must be a contiguous CPU tensor")
        address, count = value.data_ptr(), value.numel()
    elif isinstance(value, np.ndarray):
        if not value.flags.c_contiguous:
            raise KernelArgumentError(f"{where} must be a C-contiguous array")
        address, count = value.ctypes.data, value.size
    else:
        raise KernelArgumentError(f"{where} must be a tensor or numpy array, got {type(value).__name__}")
    if _dtype_name(value) not in p.dtypes:
        raise KernelArgumentError(f"{where} must be {' or '.join(p.dtypes)}, got {_dtype_name(value)}")
    known, free = 1, False
    for dim in p.shape:
        if dim == "?":
            free = True
        else:
            known *= eval(_compiled(dim), {"__builtins__": {}}, scalars)  # noqa: S307 - the header's own, checked
    fits = (count % known == 0 if known else count == 0) if free else count == known
    if not fits:
        shape = "(" + ", ".join(p.shape) + ")"
        raise KernelArgumentError(f"{where} must have {shape} = {'a multiple of ' if free else ''}{known} "
                                  f"elements, got {count}")
    return address


def call(name: str, **kwargs):
    """Call entry `nbvh_<name>` with its parameters by keyword (see the module docstring); returns its result
    (None, an int handle, or the integer it returns)."""
    entry = _entries().get(f"nbvh_{name}")
    if entry is None:
        raise KernelArgumentError(f"no kernel entry nbvh_{name} in nbvh_kernels.h")
    names = [p.name for p in entry.params]
    if "threads" in names and "threads" not in kwargs:
        kwargs["threads"] = library.threads()
    missing, unknown = [n for n in names if n not in kwargs], [k for k in kwargs if k not in names]
    if missing or unknown:
        raise KernelArgumentError(f"{entry.name}: missing {missing}, unknown {unknown}")
    scalars = {}
    for p in entry.params:
        if not p.pointer:
            value = kwargs[p.name]
            kind = Integral if p.ctype in ("int", "int64_t", "uint64_t") else Real
            if isinstance(value, bool) or not isinstance(value, kind):
                raise KernelArgumentError(f"{entry.name}: {p.name} must be a number ({p.ctype}), "
                                          f"got {type(value).__name__}")
            scalars[p.name] = value
    args = [_address(entry, p, kwargs[p.name], scalars) if p.pointer else kwargs[p.name] for p in entry.params]
    return _function(entry.name)(*args)


def __getattr__(name: str):
    """`bindings.net_train(**kwargs)` is `call("net_train", **kwargs)` for every entry the header declares."""
    if f"nbvh_{name}" in _entries():
        return lambda **kwargs: call(name, **kwargs)
    raise AttributeError(name)
