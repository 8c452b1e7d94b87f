"""What every benchmark shares: where results go, the stamp on every row, CSV rows that land as they are measured,
Markdown tables, and the smoke switch.

* `RESULTS`: bench/results, or $NBVH_BENCH_RESULTS (the smoke test writes into a temporary folder).
* `stamp()`: commit (+ "-dirty" when tracked code differs from it; the results themselves excepted), machine,
  kernel plan and command; every CSV row carries it (`append_rows` adds it to rows that lack it), every Markdown
  report starts with it.
* `append_rows`: rows appended as they land, so a long run is resumable and its partial CSV can be committed; a
  CSV learns new columns without shifting old rows.
* `SMOKE` ($NBVH_BENCH_SMOKE=1): tests/test_bench_smoke.py runs every benchmark at a tiny budget; a benchmark
  reads it where its options cannot make a run tiny enough.

Benchmarks run as modules from the repository root (`python -m bench run SUITE`, `python -m bench.SUITE.NAME ...`;
bench/registry.py declares each): nbvh_core is installed (editable) in the environment, and the repository root -
`python -m` puts it on the path - holds this package and the add-on's (not installed: Blender loads it).
"""
from __future__ import annotations

import csv
import datetime
import os
import platform
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(os.environ.get("NBVH_BENCH_RESULTS") or ROOT / "bench" / "results")
SMOKE = os.environ.get("NBVH_BENCH_SMOKE") == "1"
STAMP_FIELDS = ("commit", "machine", "kernel_plan", "command", "utc")


def stamp() -> dict:
    """commit (short hash, + '-dirty' with uncommitted changes), machine (host, architecture, CPUs, GPU), the kernel
    plan (which path ran: `kernels.describe()`), the command that made the row, and when (UTC)."""
    from nbvh_core import kernels

    return {"commit": commit_of(ROOT), "machine": machine(), "kernel_plan": kernels.describe(),
            "command": " ".join([command_of(sys.argv[0]), *sys.argv[1:]]),
            "utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M")}


def command_of(script: str) -> str:
    """How a benchmark is run again: `python -m bench.SUITE.NAME` for a module of this folder (what `python -m
    bench run` and `python -m bench.SUITE.NAME` put in sys.argv[0]), else the script's name."""
    path = Path(script).resolve()
    try:
        parts = path.with_suffix("").relative_to(ROOT).parts
    except ValueError:
        return path.name
    return "python -m " + ".".join(parts)


def commit_of(root: Path) -> str:
    """The checkout's short commit hash, + '-dirty' when a tracked file differs from it, the benchmarks' results
    (bench/results) excepted: a benchmark's own rows, appended as they land, are no change to the code they measure
    (else every row after a run's first would read -dirty)."""
    def git(*args: str) -> str:
        out = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True)
        return out.stdout.strip() if out.returncode == 0 else ""

    if os.environ.get("NBVH_COMMIT"):  # a copy whose git folder is not the tree's (a lent card's: device_check.sh)
        return os.environ["NBVH_COMMIT"]
    commit = git("rev-parse", "--short", "HEAD") or "unknown"
    if git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)bench/results"):
        commit += "-dirty"
    return commit


def machine() -> str:
    """host, architecture, CPU count and the CUDA device when there is one."""
    import torch

    gpu = f" gpu={torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""
    return f"{platform.node()} {platform.machine()} cpus={os.cpu_count()}{gpu}"


def result_path(name: str) -> Path:
    """RESULTS / name, its folder made."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    return RESULTS / name


def append_rows(path: str | os.PathLike, rows: list[dict], run_stamp: dict | None = None) -> None:
    """Append `rows` to the CSV at `path`, each stamped (`run_stamp` or a fresh `stamp()`) where it has no stamp of
    its own; columns new to the file are added (older rows get them empty)."""
    if not rows:
        return
    st = run_stamp or stamp()
    rows = [{**{k: st[k] for k in STAMP_FIELDS if k not in r}, **r} for r in rows]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    old = read_rows(path)
    fields = list(dict.fromkeys([*(old[0].keys() if old else []), *(k for r in rows for k in r)]))
    if old and list(old[0].keys()) == fields:
        with open(path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=fields).writerows(rows)
        return
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows([*old, *rows])


def append_row(path: str | os.PathLike, row: dict) -> None:
    append_rows(path, [row])


def write_rows(path: str | os.PathLike, rows: list[dict], run_stamp: dict | None = None) -> None:
    """Replace the CSV at `path` with `rows` (stamped like `append_rows`), in one step: a run killed while writing
    leaves the previous file."""
    path = Path(path)
    if not rows:
        path.unlink(missing_ok=True)
        return
    staged = path.with_name(path.name + ".partial")
    staged.unlink(missing_ok=True)
    append_rows(staged, rows, run_stamp)
    os.replace(staged, path)


def read_rows(path: str | os.PathLike) -> list[dict]:
    """The CSV's rows as dicts (strings); [] when there is no file."""
    path = Path(path)
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def measure_missing(path: str | os.PathLike, cases: list[tuple[tuple, tuple]], key_of, measure, report=None) -> None:
    """Resume a benchmark: measure each case whose key no row of `path` has yet and append its row as it lands.
    cases: [(key, measure's arguments)]; key_of(row) -> the key a row was measured for; report(rows): rewrites the
    benchmark's tables and charts after each row (None: nothing)."""
    done = {key_of(r) for r in read_rows(path)}
    for key, args in cases:
        if key in done:
            continue
        row = measure(*args)
        append_rows(path, [row])
        print(row, flush=True)
        if report is not None:
            report(read_rows(path))


def num(row: dict, key: str) -> float:
    """A CSV cell as a float (nan when empty or missing)."""
    try:
        return float(row.get(key) or "nan")
    except ValueError:
        return float("nan")


def markdown_table(header: list[str], rows: list[list]) -> list[str]:
    """A Markdown table's lines."""
    cells = [[str(c) for c in r] for r in rows]
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(r) + " |" for r in cells)]


def write_markdown(path: str | os.PathLike, lines: list[str], run_stamp: dict | None = None) -> Path:
    """Write a Markdown report: `lines`, with the stamp (the command that made it, commit, machine, kernel plan,
    time) after its title (a first line '# ...') or first."""
    st = run_stamp or stamp()
    note = [f"Made by `{st['command']}` at commit {st['commit']} on {st['machine']}; kernels: {st['kernel_plan']}; "
            f"{st['utc']} UTC.", ""]
    lines = list(lines)
    split = 2 if lines and lines[0].startswith("# ") and len(lines) > 1 and not lines[1].strip() else \
        1 if lines and lines[0].startswith("# ") else 0
    text = lines[:split] + ([""] if split == 1 else []) + note + lines[split:]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(text).rstrip() + "\n")
    return path


#: The PNG text key that carries a figure's stamp (`stamp_text`); `tests/test_provenance.py` reads it.
PNG_STAMP_KEY = "nbvh-provenance"


def stamp_text(run_stamp: dict | None = None) -> str:
    """One line: the command that made a result, commit, machine, kernel plan and UTC time."""
    st = run_stamp or stamp()
    return (f"made by `{st['command']}` at commit {st['commit']} on {st['machine']}; kernels: {st['kernel_plan']}; "
            f"{st['utc']} UTC")


def save_figure(fig, path: str | os.PathLike, dpi: int = 110, run_stamp: dict | None = None) -> Path:
    """Save a matplotlib figure as PNG with its stamp both drawn small along the bottom edge (a reader of the image
    sees where it comes from) and kept as the PNG text chunk PNG_STAMP_KEY (a test can read it)."""
    text = stamp_text(run_stamp)
    fig.text(0.005, 0.003, text, fontsize=5, color="0.4", ha="left", va="bottom")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, metadata={PNG_STAMP_KEY: text})
    return path


def save_bytes_mse_chart(fig, ax, title: str, path: str | os.PathLike) -> Path:
    """Finish a chart of file bytes (x) against image MSE (y), both log, with the one metric's label, and save it."""
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("file bytes")
    ax.set_ylabel("image MSE (16 held-out views, 256 px)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def save_image(image, path: str | os.PathLike, run_stamp: dict | None = None) -> Path:
    """Save a PIL image as PNG with the stamp as the text chunk PNG_STAMP_KEY."""
    from PIL import PngImagePlugin

    info = PngImagePlugin.PngInfo()
    info.add_text(PNG_STAMP_KEY, stamp_text(run_stamp))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path, pnginfo=info)
    return path


def product_scorer(mesh, tracer=None, n_views: int | None = None, resolution: int | None = None):
    """The product's one metric for a benchmark's contenders (`rendering.metrics.ViewScorer`): the held-out orbit
    views, as many and as large as a run's final evaluation (`Settings.eval_views`, `eval_resolution`) unless a
    smoke run asks for fewer. tracer: an ExactTracer of `mesh` already built."""
    from nbvh_core.geometry.exact import ExactTracer
    from nbvh_core.planning.settings import Settings
    from nbvh_core.rendering.metrics import ViewScorer

    s = Settings()
    return ViewScorer(tracer or ExactTracer(mesh), mesh.transform, n_views or s.eval_views,
                      resolution or s.eval_resolution, held_out=True)
