"""The README's figures are the stamped results' figures: its results table row for row from
bench/results/shipped.csv, the heavy assets' wall times, ratios and peaks from bench/results/heavy.csv, and every
bench/results file it names exists (tests/test_provenance.py checks that each is stamped). A figure edited by hand,
or a result rerun without the README following, fails here."""
import csv
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
RESULTS = ROOT / "bench" / "results"


def _rows(name: str) -> list[dict]:
    with open(RESULTS / name, newline="") as f:
        return list(csv.DictReader(f))


def _table_after(heading: str) -> list[list[str]]:
    """The first Markdown table after the line `heading`: its body rows as cells."""
    lines = README[README.index(heading):].splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    body = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        body.append([c.strip() for c in line.strip("|").split("|")])
    return body


def _int(text: str) -> int:
    return int(re.sub(r"[^\d]", "", text))


def test_the_results_table_is_shipped_csv_row_for_row():
    table = _table_after("## Results")
    rows = _rows("shipped.csv")
    assert len(table) == len(rows)
    for cells, row in zip(table, rows):
        what = cells[2].replace("*", "")
        assert what.startswith("the model" if row["shipped"] == "model" else "decimation"), (cells, row["asset"])
        assert _int(cells[3]) == int(row["shipped_bytes"]), (cells, row["asset"])
        assert cells[4] == f"{float(row['mse']):.5f}", (cells, row["asset"])
        assert cells[5] == f"{float(row['flip']):.4f}", (cells, row["asset"])
        assert _int(cells[6]) == round(float(row["alternative_bytes"])), (cells, row["asset"])
        assert cells[7] == f"{float(row['wall_s']):.1f} s", (cells, row["asset"])
        assert cells[8] == f"{float(row['mse_turned']):.5f}", (cells, row["asset"])  # the second held-out set
        assert cells[9] == f"{float(row['ratio_turned']):.2f}", (cells, row["asset"])


def test_the_heavy_assets_figures_are_heavy_csv():
    rows = _rows("heavy.csv")
    text = " ".join(README[README.index("Heavy assets, the model's home ground"):].split("\n\n")[0].split())
    walls = ", ".join(f"{float(r['wall_s']):.0f}" for r in rows[:-1]) + f" and {float(rows[-1]['wall_s']):.0f} s wall"
    assert walls in text
    for r in rows:
        if r["ratio"].replace(".", "").isdigit():
            assert f"{float(r['ratio']):.2f}x" in text, r["asset"]
    peaks = ", ".join(f"{int(r['peak_bytes']) / 2**30:.1f}" for r in rows[:-1])
    assert f"peak memory {peaks} and {int(rows[-1]['peak_bytes']) / 2**30:.1f} GiB" in text
    assert f"{float(rows[-1]['peak_per_triangle']):.0f} B per" in text


def test_every_result_the_readme_names_exists():
    named = set(re.findall(r"bench/results/[\w./-]+\.(?:md|csv|png)", README))
    assert named
    missing = sorted(n for n in named if not (ROOT / n).exists())
    assert not missing, missing


def test_the_speed_against_accuracy_figures_are_preset_curves_csv():
    rows = {(r["mesh"], float(r["time_limit_s"])): r for r in _rows("preset_curves.csv")}
    text = " ".join(README[README.index("Speed against accuracy (`bench"):].split("\n\n")[0].split())
    for mesh in ("bunny", "spiky"):
        first, last = rows[(mesh, 25.0)], rows[(mesh, 200.0)]
        assert f"{float(first['mse']):.5f} -> {float(last['mse']):.5f}" in text, mesh
    assert f"{float(rows[('bunny', 25.0)]['decimation_to_model']):.2f}x -> " \
           f"{float(rows[('bunny', 200.0)]['decimation_to_model']):.2f}x" in text
    assert f"{float(rows[('spiky', 200.0)]['decimation_to_model']):.2f}x smaller at 200 s" in text
