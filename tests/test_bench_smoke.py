"""Every benchmark still runs: each script at a tiny budget (its own options, and $NBVH_BENCH_SMOKE=1 where options
cannot make it tiny), writing into a temporary results folder; every CSV row it writes carries the harness stamp.

The numbers are not checked here (a smoke run's are meaningless); that the script ends cleanly and stamps its
rows is."""
from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
#: The shared modules of bench/ (not benchmarks themselves).
LIBRARIES = {"harness.py", "rd_runs.py", "bench_meshes.py", "real_assets.py", "failure_classes.py"}
#: script -> its arguments at a tiny budget ({tmp}: the case's scratch folder).
SMOKE = {
    "bench_batch_cluster.py": ["--assets", "blob", "studs", "--preset", "tiny", "--time-limit", "1"],
    "bench_compact.py": ["--storage", "smoke"],
    "bench_compact_layout.py": ["--assets", "gear"],
    "bench_decimators.py": ["--assets", "blob", "--shares", "0.1", "--views", "1", "--size", "32"],
    "device_check.py": ["--smoke", "--out", "{tmp}/gpu"],
    "bench_engine.py": ["{tmp}/models", "--frames", "1"],
    "kernel_registers.py": ["--cases", "1"],
    "bench_foundation.py": ["--quick", "--rays", "2000", "--nodes", "64"],
    "bench_grow.py": ["--meshes", "blob", "--preset", "tiny", "--sizes", "7", "--time-limit", "2"],
    "bench_need.py": ["--meshes", "gear", "--time-limit", "2"],
    "fit_budget.py": [],
    "bench_frontier.py": ["--meshes", "blob", "--seconds", "1", "--variants", "f4=features:4,log2_table:6"],
    "bench_freeze.py": ["--assets", "blob", "--time", "3", "--views", "1"],
    "bench_kill_resume.py": ["--mesh", "blob", "--preset", "preview", "--time-limit", "8", "--checkpoint-every", "1",
                             "--straight", "1"],
    "bench_leaf_sampling.py": ["--quick", "--train-s", "1"],
    "bench_look.py": ["--preset", "tiny", "--assets", "crate", "--views", "1", "--size", "64"],
    "bench_look_head.py": ["--assets", "crate", "--seconds", "1", "--device", "cpu"],
    "bench_method_speed.py": ["--steps", "3", "--repeats", "1", "--renders", "1"],
    "bench_pays.py": ["--meshes", "blob", "--presets", "tiny", "--time-limit", "1"],
    "bench_preset_curves.py": ["--meshes", "blob", "--budgets", "tiny=1"],
    "bench_quality.py": ["--quick", "--meshes", "knot"],
    "bench_rd_compact.py": ["--meshes", "blob"],
    "bench_rollback.py": ["--mesh", "gear", "--target", "0.01", "--time-limit", "2"],
    "bench_recovery.py": ["--mesh", "blob", "--preset", "tiny", "--time-limit", "1.5", "--fail-at", "0.6"],
    "bench_resolution.py": ["--meshes", "blob", "--n-max", "32", "--preset", "tiny", "--steps", "5"],
    "bench_shipped.py": ["--assets", "gear", "--time-limit", "2"],
    "bench_heavy.py": ["--lattices", "40", "--time-limit", "2"],
    "bench_failures.py": ["--time-limit", "1", "--methods", "default", "base", "--cases", "one triangle", "learning rate x100"],
    "bench_samples.py": ["--preset", "tiny", "--out", "{tmp}/samples"],
    "bench_storage.py": ["--meshes", "blob", "--preset", "tiny", "--seconds", "1"],
    "bench_speed.py": ["--quick", "--asset", "blob", "--train-s", "1", "--steps", "3"],
    "bench_trace_speed.py": ["{tmp}/a.nbvh", "{tmp}/b.nbvh", "--make-tiny", "--size", "16", "--repeats", "1",
                             "--views", "1"],
    "bench_textured_keep.py": ["--asset", "globe", "--levels", "1", "--time-limit", "2"],
    "bench_target_runs.py": ["--mesh", "gear", "--target", "0.01", "--seeds", "0", "--time-limit", "2"],
    "bench_table_bits.py": ["--meshes", "blob", "--seconds", "1", "--pairs", "8:6", "4:7"],
    "bench_table5.py": ["--steps", "5", "--meshes", "blob", "--methods", "base", "III"],
    "error_split.py": ["blob", "--preset", "tiny", "--steps", "5"],
    "fit_sizing.py": ["--quick"],
    "fuzz_files.py": ["--kind", "mesh", "--cases", "12"],
    "fuzz_reader.py": ["--cases", "12"],
    "look_suzanne.py": ["{tmp}/suzanne", "--seconds", "2", "--size", "48", "--cycles-samples", "1"],
    "profile_fixed_batch.py": ["2"],
    "profile_neural.py": ["--asset", "blob", "--rays", "256", "--size", "32", "--out", "{tmp}/profile.md"],
    "profile_soft_step.py": ["2"],
}
#: CSVs a case reads, seeded into its results folder: (file, the one row written). bench_compact reads a
#: bench_pays row (a model's bytes and MSE, and the decimation found to meet that MSE).
SEEDS = {"bench_compact.py": ("pays.csv", {"mesh": "blob", "preset": "tiny", "storage": "smoke", "file_bytes": 50000,
                                            "mse": 0.002, "equal_mse_decimation_triangles": 500})}


def test_every_benchmark_has_a_smoke_run():
    scripts = {p.name for p in BENCH.glob("*.py")} - LIBRARIES
    assert scripts == set(SMOKE), f"no smoke run for {scripts - set(SMOKE)}; stale: {set(SMOKE) - scripts}"


def _seed(name: str, results: Path) -> None:
    if name not in SEEDS:
        return
    file, row = SEEDS[name]
    with open(results / file, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        w.writeheader()
        w.writerow(row)


@pytest.mark.parametrize("name", sorted(SMOKE))
def test_benchmark_runs_at_a_tiny_budget_and_stamps_its_rows(name, tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    _seed(name, results)
    seeded = {p.name for p in results.iterdir()}
    args = [a.replace("{tmp}", str(tmp_path)) for a in SMOKE[name]]
    env = dict(os.environ, NBVH_BENCH_RESULTS=str(results), NBVH_BENCH_SMOKE="1", PYTHONDONTWRITEBYTECODE="1")
    proc = subprocess.run([sys.executable, str(BENCH / name), *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, f"{name} {' '.join(args)}:\n{proc.stdout[-1500:]}\n{proc.stderr[-3000:]}"
    for path in results.rglob("*.csv"):
        if path.name in seeded:
            continue
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        for field in ("commit", "machine", "kernel_plan", "command"):
            assert rows and all(r.get(field) for r in rows), f"{path.name}: rows without {field}"
        assert all(r["command"].startswith(f"bench/{name}") for r in rows)
    shutil.rmtree(tmp_path, ignore_errors=True)


def test_the_stamp_says_dirty_for_changed_code_not_for_the_benchmarks_own_results(tmp_path):
    """`harness.commit_of`: a row appended to bench/results leaves the commit clean (a run's second row was stamped
    -dirty by its first); a changed source file, or a changed result beside it, still says -dirty."""
    sys.path.insert(0, str(BENCH))
    try:
        from harness import commit_of
    finally:
        sys.path.remove(str(BENCH))

    def git(*args):
        subprocess.run(["git", "-c", "user.email=t@t", "-c", "user.name=t", *args], cwd=tmp_path, check=True,
                       capture_output=True)

    (tmp_path / "bench" / "results").mkdir(parents=True)
    (tmp_path / "code.py").write_text("x = 1\n")
    (tmp_path / "bench" / "results" / "rows.csv").write_text("commit\n")
    git("init", "-q")
    git("add", "-A")
    git("commit", "-qm", "x")
    clean = commit_of(tmp_path)
    assert clean and not clean.endswith("-dirty")
    (tmp_path / "bench" / "results" / "rows.csv").write_text("commit\nabc\n")
    assert commit_of(tmp_path) == clean
    (tmp_path / "code.py").write_text("x = 2\n")
    assert commit_of(tmp_path) == clean + "-dirty"
