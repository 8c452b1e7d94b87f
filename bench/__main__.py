"""The benchmarks' one entry point (run from the repository root):

    python -m bench list                      # suites, their benchmarks, meshes, budgets, outputs
    python -m bench run SUITE [--smoke]       # every benchmark of a suite at its defaults (--smoke: at its tiny size)
    python -m bench run NAME [--smoke] [-- ARGS...]   # one benchmark (ARGS: its own options)

Each benchmark runs as its own process (`python -m bench.SUITE.NAME`), so one that fails does not stop the rest;
the exit status is the number that failed. --smoke writes into a temporary folder ($NBVH_BENCH_RESULTS) with
$NBVH_BENCH_SMOKE=1, as tests/test_bench_smoke.py does, and leaves bench/results alone.
"""
from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.registry import BENCHMARKS, DEVICE_CHECK, SUITES, Benchmark, by_name

ROOT = Path(__file__).resolve().parents[1]


def list_benchmarks() -> str:
    """The registry as text, suite by suite."""
    lines = []
    for suite in SUITES:
        members = [b for b in BENCHMARKS if b.suite == suite]
        lines.append(f"{suite} ({len(members)})")
        for b in members:
            feeds = f" -> {b.doc}" if b.doc else ""
            lines.append(f"  {b.name:22s} {b.meshes}; {b.budget}; writes {', '.join(b.outputs) or '-'}{feeds}")
    lines.append(f"device check: {DEVICE_CHECK.module} ({DEVICE_CHECK.budget})")
    return "\n".join(lines)


def seed(b: Benchmark, results: Path) -> None:
    """The result files a smoke run of `b` reads, one row each (`Benchmark.seeds`)."""
    for file, row in b.seeds.items():
        with open(results / file, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(row))
            w.writeheader()
            w.writerow(row)


def smoke_command(b: Benchmark, scratch: Path) -> list[str]:
    """The process that runs `b` at its smoke size ({tmp} in its arguments: `scratch`)."""
    return [sys.executable, "-m", b.module, *(a.replace("{tmp}", str(scratch)) for a in b.smoke)]


def run(benchmarks: list[Benchmark], smoke: bool, extra: list[str]) -> int:
    """Run each benchmark as its own process; returns how many failed."""
    failed = 0
    for b in benchmarks:
        env = dict(os.environ)
        with tempfile.TemporaryDirectory(prefix=f"nbvh-{b.name}-") as tmp:
            if smoke:
                results = Path(tmp) / "results"
                results.mkdir()
                seed(b, results)
                env.update(NBVH_BENCH_RESULTS=str(results), NBVH_BENCH_SMOKE="1")
                cmd = smoke_command(b, Path(tmp)) + extra
            else:
                cmd = [sys.executable, "-m", b.module, *extra]
            print(f"== {b.suite or 'device'}/{b.name}: {' '.join(cmd[1:])}", flush=True)
            code = subprocess.run(cmd, cwd=ROOT, env=env).returncode
        if code:
            failed += 1
            print(f"!! {b.name} exited {code}", flush=True)
    return failed


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench", description="the benchmarks, by suite")
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="suites and their benchmarks")
    r = sub.add_parser("run", help="run a suite or one benchmark")
    r.add_argument("target", help=f"a suite ({', '.join(SUITES)}) or a benchmark's name")
    r.add_argument("--smoke", action="store_true", help="at the tiny size the tests use, into a temporary folder")
    r.add_argument("extra", nargs=argparse.REMAINDER, help="after --: the benchmark's own options (one benchmark)")
    args = p.parse_args(argv)
    if args.command == "list":
        print(list_benchmarks())
        return 0
    extra = args.extra[1:] if args.extra[:1] == ["--"] else args.extra
    if args.target in SUITES:
        if extra:
            p.error("a suite runs at its declared arguments; pass options to one benchmark")
        chosen = [b for b in BENCHMARKS if b.suite == args.target]
    else:
        try:
            chosen = [by_name(args.target)]
        except KeyError:
            p.error(f"no suite or benchmark {args.target!r} (python -m bench list)")
    return min(run(chosen, args.smoke, extra), 125)


if __name__ == "__main__":
    raise SystemExit(main())
