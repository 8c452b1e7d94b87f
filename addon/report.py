"""Asset memory report: per object, the mesh's bytes (as Blender stores it and as a ray tracer holds it)
against the .nbvh bytes by component, quality, training time and device; scene totals. JSON + HTML.

Pure Python (no bpy): `build_report` takes plain dicts so the same code serves the panel and compress.py.
"""
from __future__ import annotations

import base64
import html
import json
import os
from pathlib import Path


def _kb(n: float) -> str:
    return f"{n / 1024:,.1f} KB"


def texture_bytes(width: int, height: int, channels: int, is_float: bool) -> dict:
    """One image's memory: as Blender holds it (width x height x channels x 1 or 4 bytes) and as a GPU would in BC7
    (16 bytes per 4x4 block, the full mip chain)."""
    bc7, w, h = 0, max(width, 1), max(height, 1)
    while True:
        bc7 += ((w + 3) // 4) * ((h + 3) // 4) * 16
        if w == 1 and h == 1:
            break
        w, h = max(w // 2, 1), max(h // 2, 1)
    return {"width": width, "height": height, "channels": channels, "float": is_float,
            "blender_bytes": width * height * channels * (4 if is_float else 1), "bc7_bytes": bc7}


def asset_memory(mesh_total: int, textures: dict, after_geometry: int) -> dict:
    """The whole asset before and after: the mesh plus its textures, against the model plus the same textures
    (a model carries geometry only, so the textures stay). textures: {image name: texture_bytes(...)}."""
    tex = sum(t["blender_bytes"] for t in textures.values())
    before, after = mesh_total + tex, after_geometry + tex
    return {"texture_bytes": tex, "texture_bc7_bytes": sum(t["bc7_bytes"] for t in textures.values()),
            "asset_bytes_before": before, "asset_bytes_after": after,
            "ratio_asset": before / after if after else None}


def object_entry(name: str, blender_bytes: dict, job_report: dict, textures: dict | None = None,
                 materials: int = 0) -> dict:
    """One object's row: `blender_bytes` from export.mesh_data_bytes, `job_report` = NAME.report.json, `textures`
    {image name: texture_bytes} and the material slot count from export.asset_textures."""
    nbvh = job_report["file_bytes"]
    resident = job_report["mesh_resident_bytes"]
    q = job_report.get("quality") or {}
    t = job_report.get("training") or {}
    assessment = job_report.get("assessment") or {}
    return {
        "name": name,
        "blender_mesh_bytes": blender_bytes,
        "ray_tracing_resident_bytes": resident,
        "nbvh_bytes": nbvh,
        "nbvh_components": job_report["components"],
        "ratio_blender_mesh_to_nbvh": blender_bytes["total"] / nbvh,
        "materials": materials, "textures": textures or {},
        **asset_memory(blender_bytes["total"], textures or {}, nbvh),
        "ratio_resident_to_nbvh": resident["total"] / nbvh,
        "mse": q.get("mse"), "silhouette_iou": q.get("silhouette_iou"), "depth_error": q.get("depth_error"),
        "eval_views": q.get("views"), "train_seconds": t.get("seconds"), "device": t.get("device"),
        # The same file on a second held-out set, the lattice turned at random for this run (its seed recorded)
        "turned_views": job_report.get("quality_turned_views"),
        "settings": job_report.get("settings"), "files": job_report.get("files", {}),
        # Before training: was the model going to be smaller than the mesh a ray tracer holds? (decision.verdict)
        "worth_compressing": assessment.get("worth_compressing", resident["total"] > nbvh),
        "assessment": assessment.get("message", ""),
        "recommendation": assessment.get("recommendation", ""),
        "alternatives": assessment.get("alternatives", {}),
        "why": job_report.get("why", ""),
        "target_met": job_report.get("target_met"),
        # After the held-out evaluation: the model as shipped against the compact decimation at the same MSE
        "final_verdict": ((job_report.get("decisions") or {}).get("final") or {}).get("message", ""),
        "scene_split": job_report.get("scene_split"),
    }


def _turned_text(turned: dict | None) -> str:
    """'; on N views turned at random (seed S): MSE m, IoU i' for the report's quality row, or ''."""
    if not turned or turned.get("mse") is None:
        return ""
    return (f"; on {turned.get('views')} views turned at random (seed {turned.get('turn_seed')}): MSE "
            f"{turned['mse']:.5f}, IoU {turned.get('silhouette_iou', 0.0):.4f}")


def build_report(entries: list[dict], kept_as_mesh: list[dict] | None = None,
                 scene_split: dict | None = None) -> dict:
    """The scene report: trained `entries` (object_entry), and the objects whose verdict kept them as meshes
    ({name, blender_mesh_bytes, verdict, decimation}: no model ships for them; decimation: the one that wins,
    compress_session.decimation_offer, or None); scene_split: a scene budget's split when no trained entry carries
    it (every object kept)."""
    totals = {"blender_mesh_bytes": sum(e["blender_mesh_bytes"]["total"] for e in entries),
              "ray_tracing_resident_bytes": sum(e["ray_tracing_resident_bytes"]["total"] for e in entries),
              "nbvh_bytes": sum(e["nbvh_bytes"] for e in entries)}
    # Textures once each, however many objects share them; kept objects keep their meshes and textures.
    images = {n: t for e in [*entries, *(kept_as_mesh or [])] for n, t in (e.get("textures") or {}).items()}
    kept_mesh = sum(k["blender_mesh_bytes"]["total"] for k in kept_as_mesh or [])
    totals.update(asset_memory(totals["blender_mesh_bytes"] + kept_mesh, images, totals["nbvh_bytes"] + kept_mesh))
    if totals["nbvh_bytes"]:
        totals["ratio_blender_mesh_to_nbvh"] = totals["blender_mesh_bytes"] / totals["nbvh_bytes"]
        totals["ratio_resident_to_nbvh"] = totals["ray_tracing_resident_bytes"] / totals["nbvh_bytes"]
    split = next((e["scene_split"] for e in entries if e.get("scene_split")), scene_split)
    return {"objects": entries, "totals": totals, "scene_split": split, "kept_as_mesh": kept_as_mesh or []}


def _img_tag(path: str | None, alt: str) -> str:
    if not path or not os.path.exists(path):
        return f"<em>no {html.escape(alt)}</em>"
    data = base64.b64encode(Path(path).read_bytes()).decode()
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _decimation_text(offer: dict | None) -> str:
    """The winning decimation of an object kept as a mesh (compress_session.decimation_offer), as the report states it."""
    if not offer:
        return ""
    return (f"use a decimation: {offer['triangles']:,} triangles (Decimate ratio {offer['ratio']:.4f}, MSE "
            f"{offer['mse']:.4g}): {_kb(offer['resident_bytes'])} resident, {_kb(offer['compact_bytes'])} as a "
            "compact mesh")


def _alternatives_text(alt: dict) -> str:
    parts = []
    if "draco11_bytes" in alt:
        parts.append(f"Draco 11-bit file of the mesh {_kb(alt['draco11_bytes'])} (storage only: decoded before tracing)")
    dec = alt.get("decimation")
    if dec:
        parts.append(f"decimation to {dec['triangles']:,} triangles meets the target (MSE {dec['mse']:.4g}): "
                     f"{_kb(dec['resident_bytes'])} resident" + (f", {_kb(dec['draco11_bytes'])} as Draco" if "draco11_bytes" in dec else ""))
    elif alt.get("decimations_tried"):
        parts.append(f"no decimation up to {alt['decimations_tried'][-1]['triangles']:,} triangles meets the target")
    if alt.get("note"):
        parts.append(alt["note"])
    return "; ".join(parts) or "not measured (no quality target)"


def write_report(report: dict, out_dir: str | Path, stem: str = "nbvh_report") -> tuple[Path, Path]:
    """Write STEM.json and STEM.html (images embedded, so the page is self-contained)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    js = out_dir / f"{stem}.json"
    js.write_text(json.dumps(report, indent=2))
    rows = []
    for e in report["objects"]:
        comps = ", ".join(f"{k} {_kb(v)}" for k, v in e["nbvh_components"].items() if v)
        mse = "n/a" if e["mse"] is None else f"{e['mse']:.5f}"
        iou = "n/a" if e["silhouette_iou"] is None else f"{e['silhouette_iou']:.4f}"
        rows.append(f"""
<section><h2>{html.escape(e['name'])}</h2>
<table>
<tr><th>final verdict (held-out views; the compact decimation at the model's own MSE)</th><td>{html.escape(e.get('final_verdict') or 'not measured (no quality target)')}</td></tr>
<tr><th>mesh as Blender stores it</th><td>{_kb(e['blender_mesh_bytes']['total'])}</td></tr>
<tr><th>mesh as a ray tracer holds it (vertices, indices, normals, BVH)</th><td>{_kb(e['ray_tracing_resident_bytes']['total'])}</td></tr>
<tr><th>.nbvh</th><td>{_kb(e['nbvh_bytes'])} ({html.escape(comps)})</td></tr>
<tr><th>textures ({len(e.get('textures') or {})} images, {e.get('materials', 0)} material slots)</th><td>{_kb(e.get('texture_bytes', 0))} as Blender holds them, {_kb(e.get('texture_bc7_bytes', 0))} in BC7 on a GPU (kept: the model carries geometry only)</td></tr>
<tr><th>whole asset (mesh + textures -> model + textures)</th><td>{_kb(e.get('asset_bytes_before', 0))} -> {_kb(e.get('asset_bytes_after', 0))} ({(e.get('ratio_asset') or 0):.2f}x)</td></tr>
<tr><th>ratio (Blender mesh / .nbvh, resident / .nbvh)</th><td>{e['ratio_blender_mesh_to_nbvh']:.1f}x, {e['ratio_resident_to_nbvh']:.1f}x</td></tr>
<tr><th>quality</th><td>image MSE {mse}, silhouette IoU {iou} over {e['eval_views']} views{_turned_text(e.get('turned_views'))}</td></tr>
<tr><th>training</th><td>{e['train_seconds']} s on {html.escape(str(e['device']))}</td></tr>
<tr><th>verdict</th><td>{'worth compressing' if e['worth_compressing'] else '<strong>' + html.escape(e['assessment'] or 'not worth compressing') + '</strong>'}</td></tr>
<tr><th>alternatives (measured)</th><td>{html.escape(_alternatives_text(e.get('alternatives') or {}))}</td></tr>
<tr><th>asked, chosen and why</th><td>{html.escape(e.get('why') or '')}{'' if e.get('target_met') is None else (' - target met' if e['target_met'] else ' - <strong>target missed</strong>')}</td></tr>
</table>
<div class="pair"><figure>{_img_tag(e['files'].get('reference'), 'mesh')}<figcaption>mesh (Embree)</figcaption></figure>
<figure>{_img_tag(e['files'].get('preview'), 'neural')}<figcaption>neural (.nbvh)</figcaption></figure></div>
</section>""")
    t = report["totals"]
    split = report.get("scene_split")
    split_html = ""
    if split:
        lines = "".join(f"<tr><td>{html.escape(o['name'])}</td><td>{o['triangles']:,}</td><td>{o['weight']:.2f}</td>"
                        + ("<td colspan=3>nothing: its mesh is no larger than its model</td></tr>" if o.get("excluded")
                           or o["log2_table"] is None else
                           f"<td>2^{o['log2_table']}</td><td>{_kb(o['bytes'])}</td><td>{o['predicted_mse']:.4g}</td></tr>")
                        for o in split["objects"])
        level = "-" if split["level_mse"] is None else f"{split['level_mse']:.4g}"
        split_html = (f"<h2>Scene budget split</h2><p>{split['budget_kb']:g} KB shared by need (detail from the size "
                      f"predictor, weight = size on screen): common quality level MSE {level}, planned "
                      f"total {_kb(split['total_bytes'])}.</p><table><tr><th>object</th><th>triangles</th><th>weight</th>"
                      f"<th>T</th><th>planned</th><th>predicted MSE</th></tr>{lines}</table>")
    kept = report.get("kept_as_mesh") or []
    if kept:
        split_html += ("<h2>Kept as meshes (not worth compressing; nothing trained)</h2><table>" + "".join(
            f"<tr><th>{html.escape(k['name'])}</th><td>{_kb(k['blender_mesh_bytes']['total'])} in Blender</td>"
            f"<td>{html.escape(k['verdict'] or '')}</td><td>{_decimation_text(k.get('decimation'))}</td></tr>"
            for k in kept) + "</table>")
    page = f"""<!doctype html><meta charset="utf-8"><title>NBVH asset memory report</title>
<style>body{{font-family:sans-serif;max-width:60em;margin:2em auto}}th{{text-align:left;padding-right:1em}}
img{{width:256px;image-rendering:pixelated;background:#000}}.pair{{display:flex;gap:1em}}</style>
<h1>NBVH asset memory report</h1>
<p>Scene totals: Blender meshes {_kb(t['blender_mesh_bytes'])}, ray-tracing resident {_kb(t['ray_tracing_resident_bytes'])},
.nbvh {_kb(t['nbvh_bytes'])}; textures {_kb(t['texture_bytes'])} as Blender holds them ({_kb(t['texture_bc7_bytes'])} in BC7).
The whole scene's assets: {_kb(t['asset_bytes_before'])} -> {_kb(t['asset_bytes_after'])} ({(t['ratio_asset'] or 0):.2f}x).</p>
{split_html}
{''.join(rows)}"""
    htm = out_dir / f"{stem}.html"
    htm.write_text(page)
    return js, htm
