"""Long fuzz run of the .nbvh reader: many truncated, bit-flipped and header-mutated files (tests/fuzzing.py), each
decoded and rendered in a worker process, so a crash (a signal) or a hang is counted instead of ending the run.

    .venv/bin/python -m bench.fuzzing.fuzz_reader --cases 5000      # -> bench/results/fuzz.csv (one row per run) + fuzz.md

Counts: models (loaded and rendered), refusals (one-line NBVHFileError), crashes (the worker died), hangs (a case
past its time limit), other exceptions (each is a reader bug), and the workers' peak resident memory.
"""
from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.harness import RESULTS, ROOT, append_rows, write_markdown

WORKER = r"""
import json, resource, sys
sys.path[:0] = [sys.argv[1] + "/tests"]  # the test suite's mutators (tests/fuzzing.py)
from fuzzing import check_case, fuzz_cases
data = open(sys.argv[2], "rb").read()
start, stop, seed = int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
for i, (kind, blob) in enumerate(fuzz_cases(data, stop, seed)):
    if i < start:
        continue
    try:
        out = check_case(blob, 20.0)
    except TimeoutError:
        out = "hang"
    except Exception as exc:
        out = "exception:" + type(exc).__name__ + ":" + str(exc)[:200]
    print(json.dumps({"i": i, "kind": kind, "out": out,
                      "peak_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}), flush=True)
"""


def make_model(folder: Path) -> Path:
    from nbvh_core.app.pipeline import compress_mesh, preset
    from nbvh_core.geometry.bundled_samples import sample_path
    from nbvh_core.geometry.mesh import load_mesh

    path = folder / "fuzz.nbvh"
    compress_mesh(load_mesh(sample_path("blob")), preset("tiny").with_overrides(encoding="hashgrid", network="mlp",
                                                                                force=True), path,
                  evaluate_quality=False)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    counts = {"model": 0, "refused": 0, "crash": 0, "hang": 0, "exception": 0}
    examples: dict[str, list] = {}
    peak = 0
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        model = make_model(Path(tmp))
        i = 0
        while i < args.cases:
            proc = subprocess.Popen([sys.executable, "-c", WORKER, str(ROOT), str(model), str(i), str(args.cases),
                                     str(args.seed)], stdout=subprocess.PIPE, text=True)
            last = i - 1
            for line in proc.stdout:
                row = json.loads(line)
                last = row["i"]
                peak = max(peak, row["peak_kb"])
                key = row["out"].split(":")[0]
                counts[key] += 1
                if key not in ("model", "refused"):
                    examples.setdefault(key, []).append(row)
            proc.wait()
            if proc.returncode != 0:  # the worker died on case last + 1
                counts["crash"] += 1
                examples.setdefault("crash", []).append({"i": last + 1, "returncode": proc.returncode})
                last += 1
            i = last + 1
    row = {"cases": args.cases, "seed": args.seed, **counts, "peak_rss_mb": round(peak / 1024, 1),
           "seconds": round(time.time() - t0, 1), "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / "fuzz.csv"
    append_rows(path, [row])
    lines = ["# Reader fuzz runs (bench/fuzzing/fuzz_reader.py)", "",
             "Truncations, bit flips (half with a recomputed checksum, so they reach the parser) and one-field header "
             "mutations of a real model; each case decoded and rendered (12x12) in a worker process.", "",
             "| cases | seed | models | refusals | crashes | hangs | other exceptions | peak RSS MB | seconds |",
             "|---|---|---|---|---|---|---|---|---|"]
    with open(path) as f:
        for r in csv.DictReader(f):
            lines.append(f"| {r['cases']} | {r['seed']} | {r['model']} | {r['refused']} | {r['crash']} | {r['hang']} "
                         f"| {r['exception']} | {r['peak_rss_mb']} | {r['seconds']} |")
    write_markdown(RESULTS / "fuzz.md", lines)
    print(json.dumps(row))
    for key, rows in examples.items():
        print(key, rows[:5])


if __name__ == "__main__":
    main()
