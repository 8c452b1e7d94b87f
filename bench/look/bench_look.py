"""The look of textured, multi-material assets through their models: slots, coordinates, colour images, bytes.

For each asset (the generated ones of `nbvh_core.geometry.demo_assets`, plus any mesh .npz with a look given by --npz, e.g.
the Smart-UV Suzanne `bench/look/look_suzanne.py` exports) compress with a preset at its own time budget, then from
`--views` orbit views at `--size` px:

* slot accuracy and coordinate error of the head at the exact hit points (what the head learnt) and at the
  model's own hit points (what a render shows: the geometry's error included), on pixels both hit; coordinates
  are scored in texels of a 512 px texture, away from UV seams (> 1% of the asset's size from one), on slots
  that sample an image (a plain slot's hits use no coordinates);
* FLIP (NVIDIA, `flip-evaluator`) and MSE of the model's colour render against the mesh's colour render with the
  same materials and light (the paper's head-on shading x albedo);
* bytes: the whole file, its appearance head, its textures; seconds: geometry training and the head's.

    .venv/bin/python -m bench.look.bench_look [--preset preview] [--assets globe,crate,ring,patchwork] [--npz X.npz]
                                         [--real engine] [--target coordinates|colour]

--target colour: the head learns the textured colour itself and the file keeps no image (the alternative to
coordinates + images); rows then have no slot or coordinate scores, the bytes and FLIP compare the two.

Rows append to bench/results/look.csv (stamped); a rerun skips rows it already has for the same commit.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]

from bench.harness import RESULTS, append_rows, read_rows, stamp
from bench.real_assets import asset_path
from nbvh_core.geometry.mesh import load_mesh
from nbvh_core.geometry import demo_assets
from nbvh_core.geometry.mesh_arrays import mesh_from_npz
from nbvh_core.geometry.look import hit_labels
from nbvh_core.geometry.uv_patches import seam_distance, seam_edges
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.rendering.render import orbit_cameras, render_neural, render_reference

OUT = RESULTS / "look.csv"
TEXELS = 512


def score_views(mesh, model, tracer, views: int, size: int) -> dict:
    """Slot and coordinate scores at exact and model hit points, and colour-image FLIP/MSE, over `views` views."""
    import flip_evaluator

    seams = seam_edges(mesh.vertices, mesh.faces, mesh.look.corner_uvs) if mesh.look.corner_uvs is not None \
        else np.zeros((0, 2, 3), np.float32)
    acc = {k: [] for k in ("slot_exact", "slot_model", "uv_exact", "uv_model", "away", "sampled", "flip", "mse")}
    sampled = mesh.look.image_slots
    for cam in orbit_cameras(views):
        o, d = cam.rays(size, size)
        fh = tracer.first_hit(o, d)
        q = model.query(torch.from_numpy(o), torch.from_numpy(d))
        both = fh.hit & q.hit.numpy()
        p_exact = o[both] + fh.t[both, None] * d[both]
        p_model = np.clip(o[both] + q.t.numpy()[both, None] * d[both], 0, 1)
        slot, uv = hit_labels(mesh.look, mesh.vertices, mesh.faces, fh.tri[both], p_exact)
        for tag, pts in (("exact", p_exact), ("model", p_model)):
            if model.appearance.cfg.target == "colour":
                continue
            ps, puv = model.appearance.predict(torch.from_numpy(pts.astype(np.float32)))
            acc[f"slot_{tag}"].append(ps == slot)
            if uv is not None:
                acc[f"uv_{tag}"].append(np.abs(puv - uv).max(1) * TEXELS)
        # coordinates are scored where they are used: away from seams, on slots that sample an image
        acc["away"].append(seam_distance(p_exact, seams) > 0.01)
        acc["sampled"].append(sampled[slot])
        ref = render_reference(tracer, cam, size, size).colour
        neu = render_neural(model, cam, size, size).colour
        acc["flip"].append(float(flip_evaluator.evaluate(ref, neu, "LDR", applyMagma=False)[1]))
        acc["mse"].append(float(((ref - neu) ** 2).mean()))
    away = np.concatenate(acc["away"])
    out = {"away_fraction": away.mean(), "flip": np.mean(acc["flip"]), "colour_mse": np.mean(acc["mse"])}
    if acc["slot_exact"]:
        out.update(slot_exact=np.concatenate(acc["slot_exact"]).mean(),
                   slot_model=np.concatenate(acc["slot_model"]).mean())
    for tag in ("exact", "model"):
        if acc[f"uv_{tag}"]:
            e = np.concatenate(acc[f"uv_{tag}"])[away & np.concatenate(acc["sampled"])]
            out[f"uv_half_texel_{tag}"] = (e < 0.5).mean()
            out[f"uv_median_texels_{tag}"] = float(np.median(e))
    return {k: round(float(v), 4) for k, v in out.items()}


def run_asset(name: str, mesh, preset_name: str, views: int, size: int, target: str) -> dict:
    s = preset(preset_name).with_overrides(force=True, appearance_target=target)
    r = compress_mesh(mesh, s)
    head = r.model.appearance
    row = {"asset": name, "preset": preset_name, "target": target, "triangles": mesh.n_triangles,
           "slots": mesh.look.n_slots, "patches": head.cfg.patches if head else 0,
           "file_bytes": r.file_bytes, "appearance_bytes": r.components.get("appearance", 0),
           "texture_bytes": r.components.get("textures", 0),
           "geometry_bytes": r.file_bytes - r.components.get("appearance", 0) - r.components.get("textures", 0),
           "geometry_train_s": round(r.training.seconds, 1), "appearance_s": round(r.seconds.get("appearance", 0), 1),
           "geometry_mse": round(r.quality.mse, 6)}
    if head is not None:
        row.update(score_views(mesh, r.model, r.tracer, views, size))
    row["appearance_share_of_geometry"] = round(row["appearance_bytes"] / row["geometry_bytes"], 4)
    return row


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="preview")
    ap.add_argument("--assets", default="globe,crate,ring,patchwork")
    ap.add_argument("--npz", action="append", default=[], type=Path)
    ap.add_argument("--real", action="append", default=[], help="a real asset by name (bench/real_assets.py), e.g. "
                    "engine: 115 plain material slots")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--target", choices=["coordinates", "colour"], default="coordinates")
    args = ap.parse_args()
    done = {(r["asset"], r["preset"], r.get("target") or "coordinates") for r in read_rows(OUT)
            if r["commit"] == stamp()["commit"]}
    jobs = [(a, lambda a=a: demo_assets.ASSETS[a]()) for a in args.assets.split(",") if a]
    jobs += [(p.stem, lambda p=p: mesh_from_npz(p, p.stem)) for p in args.npz]
    jobs += [(n, lambda n=n: load_mesh(asset_path(n))) for n in args.real]
    for name, make in jobs:
        if (name, args.preset, args.target) in done:
            continue
        row = run_asset(name, make(), args.preset, args.views, args.size, args.target)
        append_rows(OUT, [row])
        print(row, flush=True)


if __name__ == "__main__":
    main()
