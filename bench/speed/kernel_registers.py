"""What the card's Triton kernels cost in registers, without a card: each kernel compiled for an NVIDIA target
(sm_90a, the H100/H200's) by Triton on this machine and assembled by the ptxas Triton ships, `ptxas -v` read back.
A kernel that spills registers to local memory on the card is slow however correct the interpreter finds it; this
is the one measure of that available where no card is lent (the speed itself needs one: bench/device_check.py).

    .venv/bin/python -m bench.speed.kernel_registers            # bench/results/kernel_registers.{csv,md}

Rows: kernel (ray query mlp | kmlp, table f32 | u8 codes, a HashVQAD's index or none; the MLP's training forward and
backward; the training labels' mesh trace and leaf lists), the default preset's shape (10 levels x 4 features, k = 4, 2 hidden layers of 64), registers per thread,
spill store bytes, local stack bytes, compile seconds.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

os.environ.pop("TRITON_INTERPRET", None)  # the kernels are compiled, not interpreted: read when Triton is imported

from bench.harness import append_rows, markdown_table, result_path, stamp, write_markdown

TARGET_ARCH, TARGET_SM = 90, "sm_90a"  # Hopper: what the lent cards are


@dataclass(frozen=True)
class CardBuild:
    """A kernel as ptxas assembled it: registers per thread, bytes spilled (stores) and the local stack."""

    registers: int
    spill_store_bytes: int
    stack_bytes: int
    compile_s: float


def _ray_query_signature(kind: str, codes: bool, levels: int, features: int, k: int, width: int,
                         hidden: int, index_bits: int) -> tuple[dict, dict]:
    from nbvh_core.kernels.triton import ray_query

    pointers = dict(o_ptr="*fp32", d_ptr="*fp32", inv_ptr="*fp32", n="i32", rec_f_ptr="*fp32", rec_i_ptr="*i32",
                    frac_ptr="*fp32", table_ptr="*u8" if codes else "*fp32", offset_ptr="*fp32", scale_ptr="*fp32",
                    scales_ptr="*fp32", res_ptr="*i32", dense_ptr="*i32", base_ptr="*i32", start_ptr="*i32",
                    index_ptr="*u8" if index_bits else "*i32", w_in_ptr="*fp32", b_in_ptr="*fp32",
                    w_hid_ptr="*fp32", b_hid_ptr="*fp32", w_out_ptr="*fp32", b_out_ptr="*fp32", hit_ptr="*i8",
                    t_ptr="*fp32", normal_ptr="*fp32", segments_ptr="*i32")
    n_in = (2 if kind == "kmlp" else k) * levels * features
    table_rows = 2048 // 16 if index_bits else 2048  # HashVQAD: H = 16 T, the index reaching T / 16 rows
    constants = dict(L=levels, H=2048, T=table_rows, LISTED=False, F=features, BITS=index_bits, CODES=codes, K=k, K_PAD=-(-n_in // 32) * 32, W=width,
                     HIDDEN=hidden - 1, OUT_PAD=16, KMLP=kind == "kmlp", DEPTH=32, BR=ray_query.BLOCK_R,
                     PRECISION="tf32")
    return pointers, constants


def build_ray_query(kind: str = "mlp", codes: bool = True, levels: int = 10, features: int = 4, k: int = 4,
                    width: int = 64, hidden: int = 2, index_bits: int = 0) -> CardBuild:
    """Compile the ray-query kernel for `TARGET_SM` as `first_hits` launches it (BLOCK_R rays, WARPS warps, TF32)
    and read ptxas's report. Raises RuntimeError when ptxas fails."""
    from nbvh_core.kernels.triton import ray_query

    pointers, constants = _ray_query_signature(kind, codes, levels, features, k, width, hidden, index_bits)
    return _compile(ray_query._ray_query, pointers, constants, ray_query.WARPS)


def build_mlp_training(backward: bool, kind: str = "mlp", levels: int = 10, features: int = 4, k: int = 4,
                       width: int = 64, hidden: int = 2) -> CardBuild:
    """Compile the MLP's training forward (storing activations) or its backward kernel for `TARGET_SM` at the
    default preset's shape, as `mlp_train_forward` launches them (Triton's default 4 warps)."""
    from nbvh_core.kernels.triton import mlp

    n_in = (2 if kind == "kmlp" else k) * levels * features
    shape = dict(K_PAD=-(-n_in // mlp.BLOCK_K) * mlp.BLOCK_K, W=width, HIDDEN=hidden - 1, OUT_PAD=16, BM=mlp.BLOCK_M,
                 BK=mlp.BLOCK_K)
    if backward:
        pointers = dict(dy_ptr="*fp32", acts_ptr="*fp32", w_in_ptr="*fp32", w_hid_ptr="*fp32", w_out_ptr="*fp32",
                        dz_ptr="*fp32", dx_ptr="*fp32", m="i32", n_in="i32", n_out="i32")
        return _compile(mlp._mlp_backward, pointers, shape, 4)
    pointers = dict(x_ptr="*fp32", w_in_ptr="*fp32", b_in_ptr="*fp32", w_hid_ptr="*fp32", b_hid_ptr="*fp32",
                    w_out_ptr="*fp32", b_out_ptr="*fp32", out_ptr="*fp32", acts_ptr="*fp32", m="i32", n_in="i32",
                    K_PAD=None, W=None, HIDDEN=None, OUT_PAD=None, n_out="i32", BM=None, BK=None, SAVE=None)
    return _compile(mlp._mlp_forward, pointers, dict(shape, SAVE=True), 4)


def build_label_kernel(kind: str, depth: int = 64) -> CardBuild:
    """Compile a training-label kernel for `TARGET_SM` as the card launches it: 'mesh trace' (the nearest triangle
    hit; a stack of `depth` slots: a mesh tree of up to depth - 2 levels) or 'leaf lists' (the write pass)."""
    from nbvh_core.kernels.triton import leaf_lists, mesh_trace

    if kind == "mesh trace":
        pointers = dict(o_ptr="*fp32", d_ptr="*fp32", inv_ptr="*fp32", tmin_ptr="*fp32", tmax_ptr="*fp32", n="i32",
                        rec_f_ptr="*fp32", rec_i_ptr="*i32", tri_ptr="*fp32", id_ptr="*i32", t_ptr="*fp32",
                        out_ptr="*i32")
        return _compile(mesh_trace._nearest_hits, pointers, dict(DEPTH=depth, BR=mesh_trace.BLOCK_R),
                        mesh_trace.WARPS)
    pointers = dict(o_ptr="*fp32", inv_ptr="*fp32", tmax_ptr="*fp32", n="i32", rec_f_ptr="*fp32", rec_i_ptr="*i32",
                    count_ptr="*i64", offset_ptr="*i64", node_ptr="*i64", te_ptr="*fp32", tx_ptr="*fp32")
    return _compile(leaf_lists._leaf_walk, pointers, dict(WRITE=True, DEPTH=depth, BR=leaf_lists.BLOCK_R),
                    leaf_lists.WARPS)


def _compile(fn, pointers: dict, constants: dict, warps: int) -> CardBuild:
    """`fn` compiled for TARGET_SM with `pointers` (argument types, in the kernel's order; None: a constant) and
    `constants`, assembled by ptxas -v: its report. Raises RuntimeError when ptxas fails."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    signature = {name: kind or "constexpr" for name, kind in pointers.items()}
    signature.update({name: "constexpr" for name in constants if name not in signature})
    names = list(signature)
    source = ASTSource(fn=fn, signature=signature,
                       constexprs={(names.index(name),): value for name, value in constants.items()})
    start = time.perf_counter()
    compiled = triton.compile(source, target=GPUTarget("cuda", TARGET_ARCH, 32), options={"num_warps": warps})
    seconds = time.perf_counter() - start
    ptxas = os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin", "ptxas")
    with tempfile.TemporaryDirectory() as tmp:
        ptx = os.path.join(tmp, "kernel.ptx")
        with open(ptx, "w") as f:
            f.write(compiled.asm["ptx"])
        out = subprocess.run([ptxas, f"-arch={TARGET_SM}", "-v", ptx, "-o", os.path.join(tmp, "kernel.cubin")],
                             capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"ptxas failed: {out.stderr.strip().splitlines()[-1:]}")
    return _parse(out.stderr, seconds)


def _parse(report: str, seconds: float) -> CardBuild:
    registers = re.search(r"Used (\d+) registers", report)
    spills = re.search(r"(\d+) bytes spill stores", report)
    stack = re.search(r"(\d+) bytes stack frame", report)
    if registers is None:
        raise RuntimeError("ptxas printed no register count")
    return CardBuild(int(registers.group(1)), int(spills.group(1)) if spills else 0,
                     int(stack.group(1)) if stack else 0, round(seconds, 1))


CASES = [("ray query mlp, u8 codes", lambda: build_ray_query("mlp", True)),
         ("ray query mlp, f32 table", lambda: build_ray_query("mlp", False)),
         ("ray query kmlp, u8 codes", lambda: build_ray_query("kmlp", True)),
         ("ray query kmlp, f32 table", lambda: build_ray_query("kmlp", False)),
         ("ray query mlp, u8 codes, HashVQAD 4-bit index", lambda: build_ray_query("mlp", True, index_bits=4)),
         ("mlp training forward (activations stored)", lambda: build_mlp_training(False, "mlp")),
         ("mlp training backward", lambda: build_mlp_training(True, "mlp")),
         ("kmlp training forward (activations stored)", lambda: build_mlp_training(False, "kmlp")),
         ("kmlp training backward", lambda: build_mlp_training(True, "kmlp")),
         ("labels: mesh trace, 64-slot stack", lambda: build_label_kernel("mesh trace", 64)),
         ("labels: leaf lists, 32-slot stack", lambda: build_label_kernel("leaf lists", 32))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=len(CASES), help="how many of the cases to build (smoke: 1)")
    args = ap.parse_args()
    run = stamp()
    rows = []
    for label, build_case in CASES[:args.cases]:
        build = build_case()
        row = {"kernel": label, "target": TARGET_SM, "registers": build.registers,
               "spill_store_bytes": build.spill_store_bytes, "stack_bytes": build.stack_bytes,
               "compile_s": build.compile_s}
        print(row, flush=True)
        rows.append(row)
    append_rows(result_path("kernel_registers.csv"), rows, run)
    table = markdown_table(["kernel", "target", "registers", "spill stores (B)", "stack (B)", "compile (s)"],
                           [[r["kernel"], r["target"], r["registers"], r["spill_store_bytes"], r["stack_bytes"],
                             r["compile_s"]] for r in rows])
    write_markdown(result_path("kernel_registers.md"),
                   ["# The card's Triton kernels as ptxas assembles them", "",
                    "The default preset's shape, compiled for the card without one (no timing: "
                    "bench/device_check.py on a card).", "", *table], run)


if __name__ == "__main__":
    sys.exit(main())
