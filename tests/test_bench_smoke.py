"""Every benchmark still runs: each one declared in bench/registry.py, at its declared smoke arguments (and
$NBVH_BENCH_SMOKE=1 where options cannot make it tiny), writing into a temporary results folder; every CSV row it
writes carries the harness stamp, and it writes the files it declares.

The numbers are not checked here (a smoke run's are meaningless); that the script ends cleanly and stamps its
rows is."""
from __future__ import annotations

import csv
import fnmatch
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
sys.path.insert(0, str(ROOT))
from bench.registry import BENCHMARKS, DEVICE_CHECK, SUITES  # noqa: E402  (the repository root, as `python -m bench`)
from bench.__main__ import seed, smoke_command  # noqa: E402

#: Modules of the suites' folders that are libraries of their benchmarks, not benchmarks.
LIBRARIES = {"rd_runs", "failure_classes", "__init__"}
ALL = {b.name: b for b in (*BENCHMARKS, DEVICE_CHECK)}


def test_every_benchmark_is_declared_once_in_its_suite_s_folder():
    found = {p.stem: p.parent.name for p in BENCH.glob("*/*.py") if p.stem not in LIBRARIES}
    declared = {b.name: b.suite for b in BENCHMARKS}
    assert found == declared, f"undeclared {set(found) - set(declared)}; stale {set(declared) - set(found)}"
    assert len(BENCHMARKS) == len(declared) and {b.suite for b in BENCHMARKS} == set(SUITES)
    assert len([p for p in BENCH.glob("*.py")]) <= 12


def _written(scratch: Path, results: Path, seeded: set[str]) -> set[str]:
    """Files a smoke run wrote: under the results folder, or under the scratch folder its arguments name ({tmp}),
    each with a smoke run's _smoke / _quick suffix taken off."""
    out = set()
    for p in scratch.rglob("*"):
        if p.is_file() and p.name not in seeded:
            name = str(p.relative_to(results if results in p.parents else scratch))
            out.add(name.replace("_smoke", "").replace("_quick", ""))
    return out


@pytest.mark.parametrize("name", sorted(ALL))
def test_benchmark_runs_at_a_tiny_budget_and_stamps_its_rows(name, tmp_path):
    b = ALL[name]
    results = tmp_path / "results"
    results.mkdir()
    seed(b, results)
    seeded = set(b.seeds)
    env = dict(os.environ, NBVH_BENCH_RESULTS=str(results), NBVH_BENCH_SMOKE="1", PYTHONDONTWRITEBYTECODE="1")
    cmd = smoke_command(b, tmp_path)
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"{' '.join(cmd[1:])}:\n{proc.stdout[-1500:]}\n{proc.stderr[-3000:]}"
    written = _written(tmp_path, results, seeded)
    for path in results.rglob("*.csv"):
        if path.name in seeded:
            continue
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        for field in ("commit", "machine", "kernel_plan", "command"):
            assert rows and all(r.get(field) for r in rows), f"{path.name}: rows without {field}"
        assert all(r["command"].startswith(f"python -m {b.module}") for r in rows)
    # what it declares it writes, it writes (a smoke run may write a '_smoke' variant beside the real file)
    missing = [o for o in b.outputs if not fnmatch.filter(written, o)]
    assert not missing, f"{name} declares {missing} but wrote {sorted(written)}"
    shutil.rmtree(tmp_path, ignore_errors=True)


def test_the_stamp_says_dirty_for_changed_code_not_for_the_benchmarks_own_results(tmp_path):
    """`harness.commit_of`: a row appended to bench/results leaves the commit clean (a run's second row was stamped
    -dirty by its first); a changed source file, or a changed result beside it, still says -dirty."""
    sys.path.insert(0, str(BENCH))
    try:
        from bench.harness import commit_of
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
    os.environ["NBVH_COMMIT"] = "abc1234"  # a lent card's copy: the commit --prepare recorded, not its git folder's
    try:
        assert commit_of(tmp_path) == "abc1234"
    finally:
        del os.environ["NBVH_COMMIT"]


def test_the_card_s_host_syncs_are_counted_per_step_with_their_lines(monkeypatch, sample_meshes):
    """bench_speed's sync count (run on a card only): every 'synchronizing' warning torch's debug mode raises during
    the training is counted, with the line that asked; the mode is set back after. Here the mode and the training are
    stand-ins: the CPU build of torch has no sync debug mode."""
    import warnings
    from types import SimpleNamespace

    import torch

    import bench.speed.bench_speed as bench_speed
    from nbvh_core.app.pipeline import preset
    from nbvh_core.geometry.bvh import build_bvh

    modes = []
    monkeypatch.setattr(torch.cuda, "set_sync_debug_mode", modes.append)
    monkeypatch.setattr(bench_speed, "card_rays_per_step", lambda device: 8192)

    def train(model, bvh, tracer, cfg):
        for step in range(cfg.steps):
            if step % 16 == 0:
                warnings.warn_explicit("called a synchronizing CUDA operation", UserWarning, "loss_reads.py", 48)
            warnings.warn_explicit("something else", UserWarning, "train.py", 1)
        return SimpleNamespace(compute_path="fast on cuda", seconds=1.0)

    monkeypatch.setattr(bench_speed, "train", train)
    mesh = sample_meshes["blob"]
    s = preset("tiny")
    row = bench_speed.host_syncs(build_bvh(mesh, s.nodes), None, s, mesh, torch.device("cpu"), 64)
    assert modes == ["warn", "default"]
    assert (row["what"], row["per_s"], row["sync_sites"], row["rays_per_step"]) == ("syncs", 4 / 64, "loss_reads.py:48",
                                                                                    8192)


def test_bench_labels_measures_labels_made_on_the_card(sample_meshes):
    """bench_labels' card columns (measured on a card only) at a toy chunk, the CPU standing in for the card under
    Triton's interpreter: every rate positive, the tracer's bytes its tables'."""
    pytest.importorskip("triton")
    import torch

    import bench.speed.bench_labels as bench_labels
    from nbvh_core.geometry.bvh import build_bvh
    from nbvh_core.geometry.exact import ExactTracer
    from nbvh_core.training.config import TrainConfig

    mesh = sample_meshes["blob"]
    bvh = build_bvh(mesh, 31)
    cfg = TrainConfig(steps=4, rays_per_step=32, label_steps=2, seed=0)
    threads = torch.get_num_threads()
    try:
        row = bench_labels.card_costs(bvh, ExactTracer(mesh), cfg, 1, 1, device="cpu")
    finally:
        torch.set_num_threads(threads)  # the benchmark sets its own: the tests after this one keep theirs
    assert row["card_label_samples_per_s"] > 0 and row["card_first_hit_rays_per_s"] > 0
    assert row["card_streamed_samples_per_s"] > 0 and row["card_tracer_bytes"] > 36 * mesh.n_triangles
