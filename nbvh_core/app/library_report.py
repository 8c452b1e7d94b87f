"""The library memory report: OUT/report.json (everything), report.csv (one flat row per asset) and report.html
(sortable table with thumbnails of the original and the neural render, totals, a chart of savings by asset),
written atomically after every change so a reader never sees half a report. Plain Python, no torch.
"""
from __future__ import annotations

import csv
import html
import io
import json
from pathlib import Path

CSV_COLUMNS = ("name", "source", "status", "verdict", "triangles", "mesh_resident_bytes", "draco_bytes",
               "compact_bytes", "texture_bytes", "decimation_triangles", "decimation_compact_bytes", "decimation_written_bytes",
               "predicted_model_bytes", "model_bytes", "alternative_bytes", "saved_vs_alternative_bytes",
               "model_resident_bytes", "saved_bytes", "mse", "iou",
               "train_seconds", "measure_seconds", "worker", "error")


def totals(rows: list) -> dict:
    """Library totals: assets by status, resident bytes before (every mesh as a ray tracer holds it) and after
    (compressed assets as their models, the rest as their meshes), memory saved, model storage, compute spent."""
    by_status: dict[str, int] = {}
    for r in rows:
        by_status[r.status] = by_status.get(r.status, 0) + 1
    before = sum(r.mesh_resident_bytes or 0 for r in rows)
    saved = sum(r.saved_bytes for r in rows)
    saved_vs_alternative = sum(r.saved_vs_alternative_bytes for r in rows)
    textures = sum(r.texture_bytes or 0 for r in rows)
    return {"assets": len(rows), "by_status": by_status, "resident_before_bytes": before, "texture_bytes": textures,
            "resident_after_bytes": before - saved, "saved_bytes": saved,
            "saved_vs_alternative_bytes": saved_vs_alternative,
            "model_storage_bytes": sum(r.model_bytes or 0 for r in rows if r.status in ("done", "cached")),
            "predicted_savings_bytes": sum(r.predicted_savings for r in rows),
            "train_seconds": round(sum(r.train_seconds or 0 for r in rows if r.status == "done"), 1),
            "measure_seconds": round(sum(r.measure_seconds or 0 for r in rows), 1)}


def _fmt_bytes(n) -> str:
    if n is None:
        return ""
    return f"{n / 1024:,.1f} KB" if abs(n) < 1024 ** 2 else f"{n / 1024 ** 2:,.2f} MB"


def _csv_text(rows: list) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow(r.to_dict())
    return buf.getvalue()


def _chart_svg(rows: list, width: int = 640, bar: int = 14) -> str:
    """Horizontal bars: resident bytes saved per compressed asset (or predicted, before training), largest first."""
    items = sorted(((r.name, r.saved_bytes or r.predicted_savings, bool(r.saved_bytes)) for r in rows
                    if (r.saved_bytes or r.predicted_savings) > 0), key=lambda x: -x[1])[:40]
    if not items:
        return "<p>No asset saves memory (yet).</p>"
    top = max(v for _, v, _ in items)
    parts = [f'<svg width="{width}" height="{bar * len(items) + 10}" xmlns="http://www.w3.org/2000/svg">']
    for i, (name, value, measured) in enumerate(items):
        w = max(1, int((width - 260) * value / top))
        colour = "#3a7" if measured else "#9cd"
        parts.append(f'<text x="0" y="{i * bar + 11}" font-size="11">{html.escape(name[:34])}</text>'
                     f'<rect x="200" y="{i * bar + 2}" width="{w}" height="{bar - 3}" fill="{colour}"/>'
                     f'<text x="{204 + w}" y="{i * bar + 11}" font-size="11">{_fmt_bytes(value)}</text>')
    parts.append("</svg>")
    return "".join(parts)


_SORT_JS = """
document.querySelectorAll('th').forEach((th, col) => th.addEventListener('click', () => {
  const body = th.closest('table').querySelector('tbody');
  const rows = Array.from(body.rows), asc = th.dataset.asc !== '1';
  const key = r => { const c = r.cells[col]; const v = c.dataset.v ?? c.textContent; const n = parseFloat(v);
                     return isNaN(n) ? v.toLowerCase() : n; };
  rows.sort((a, b) => (key(a) > key(b) ? 1 : key(a) < key(b) ? -1 : 0) * (asc ? 1 : -1));
  th.dataset.asc = asc ? '1' : '0'; rows.forEach(r => body.appendChild(r));
}));
"""


def _cell(value, shown: str | None = None) -> str:
    v = "" if value is None else value
    return f'<td data-v="{html.escape(str(v))}">{html.escape(shown if shown is not None else str(v))}</td>'


def _row_html(r) -> str:
    img = (lambda f: f'<img src="thumbs/{html.escape(f)}" width="64" height="64">' if f else "")
    mse = "" if r.mse is None else f"{r.mse:.5f}"
    return ("<tr>" + f"<td>{img(r.thumb_original)}</td><td>{img(r.thumb_neural)}</td>" + _cell(r.name)
            + _cell(r.status) + _cell(r.triangles, f"{r.triangles:,}" if r.triangles else "")
            + _cell(r.mesh_resident_bytes, _fmt_bytes(r.mesh_resident_bytes))
            + _cell(r.model_resident_bytes, _fmt_bytes(r.model_resident_bytes))
            + _cell(r.model_bytes, _fmt_bytes(r.model_bytes))
            + _cell(r.alternative_bytes, _fmt_bytes(r.alternative_bytes))
            + _cell(r.draco_bytes, _fmt_bytes(r.draco_bytes))
            + _cell(r.compact_bytes, _fmt_bytes(r.compact_bytes))
            + _cell(r.texture_bytes, _fmt_bytes(r.texture_bytes))
            + _cell(r.saved_bytes, _fmt_bytes(r.saved_bytes)) + _cell(r.mse, mse)
            + _cell(r.iou, "" if r.iou is None else f"{r.iou:.4f}")
            + _cell(r.train_seconds, "" if r.train_seconds is None else f"{r.train_seconds:.0f} s")
            + _cell(r.error or r.verdict or "", (r.error or r.verdict or "") + (
                f" Written: {r.files['decimation']}" if r.files.get("decimation") else "")) + "</tr>")


def html_report(rows: list, info: dict, t: dict | None = None) -> str:
    """The report page (self-contained but for the thumbnails in thumbs/); t: `totals(rows)` when computed."""
    t = t if t is not None else totals(rows)
    head = ("<tr><th>original</th><th>neural</th><th>asset</th><th>status</th><th>triangles</th>"
            "<th>resident (mesh)</th><th>resident (model)</th><th>.nbvh file</th>"
            "<th>compact decimation at the model's MSE</th><th>Draco 11-bit</th><th>compact mesh</th>"
            "<th>textures</th><th>saved</th><th>MSE</th><th>IoU</th><th>train</th><th>verdict / error</th></tr>")
    status = ", ".join(f"{k} {v}" for k, v in sorted(t["by_status"].items()))
    state = "final" if info.get("final") else "in progress"
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>NBVH library report</title>
<style>body{{font-family:sans-serif;margin:1.5em}} table{{border-collapse:collapse;font-size:13px}}
td,th{{border:1px solid #ccc;padding:3px 6px}} th{{cursor:pointer;background:#eee}} td:nth-child(n+5){{text-align:right}}
</style></head><body>
<h1>Library memory report <small>({state})</small></h1>
<p>{html.escape(str(info.get("library", "")))} - {t["assets"]} assets ({html.escape(status)}).
Against the strongest alternative (each model against the compact decimation at its own measured MSE, held-out
views): the models save <b>{_fmt_bytes(t["saved_vs_alternative_bytes"])}</b>; an asset where a decimation is
smaller is kept as a mesh.
Resident memory as a ray tracer holds it: <b>{_fmt_bytes(t["resident_before_bytes"])}</b> before,
<b>{_fmt_bytes(t["resident_after_bytes"])}</b> after (saved {_fmt_bytes(t["saved_bytes"])}; predicted for the
assets worth compressing {_fmt_bytes(t["predicted_savings_bytes"])}). Model files {_fmt_bytes(t["model_storage_bytes"])}.
Textures, kept either way: {_fmt_bytes(t["texture_bytes"])}; whole assets (geometry + textures)
{_fmt_bytes(t["resident_before_bytes"] + t["texture_bytes"])} before, {_fmt_bytes(t["resident_after_bytes"] + t["texture_bytes"])} after.
Compute: {t["train_seconds"]:.0f} s training, {t["measure_seconds"]:.0f} s measuring; wall {info.get("wall_s", "?")} s
on {info.get("cluster", {}).get("nodes", "?")} node(s), {info.get("cluster", {}).get("CPU", "?")} CPUs.
Click a column to sort.</p>
<h2>Savings by asset</h2>{_chart_svg(rows)}
<h2>Assets</h2><table><thead>{head}</thead><tbody>{"".join(_row_html(r) for r in rows)}</tbody></table>
<script>{_SORT_JS}</script></body></html>"""


def write_report(out: Path, rows: list, info: dict) -> dict:
    """Write OUT/report.{json,csv,html} atomically; returns {'json', 'csv', 'html' (paths), 'totals', 'rows'}."""
    from ..protocol.outputs import write_atomic

    out = Path(out)
    data = {"info": info, "totals": totals(rows), "rows": [r.to_dict() for r in rows]}
    write_atomic(out / "report.json", json.dumps(data, indent=2, default=str).encode())
    write_atomic(out / "report.csv", _csv_text(rows).encode())
    write_atomic(out / "report.html", html_report(rows, info, data["totals"]).encode())
    return {"json": str(out / "report.json"), "csv": str(out / "report.csv"), "html": str(out / "report.html"),
            "totals": data["totals"], "rows": data["rows"]}
