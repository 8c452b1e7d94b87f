"""What holding textures at the views' needs costs and saves (`geometry.texture_hold`), on a real textured scan.

For each on-screen size: the side the rule holds each image at, the bytes a file stores for the images, and the
held look against the source's on the held-out views (16; the metric's 256 px and a closer 1024 px): colour MSE
(linear albedo) and FLIP of the displayed images. The geometry is the source's: only the texture differs.

    NBVH_GIT_MIRRORS=... .venv/bin/python -m bench.look.bench_texture_hold [--asset fuze] [--px 0 2048 1024 512 256]
        [--upscale 1 4]

Writes bench/results/texture_hold.{csv,md}.
"""
from __future__ import annotations

import argparse

from bench.harness import SMOKE, markdown_table, result_path, stamp, write_markdown, write_rows


def held_row(source, px: int, resolutions: tuple[int, ...]) -> dict:
    """One on-screen size's row: held sides, stored image bytes, colour MSE and FLIP at each view resolution."""
    from nbvh_core.geometry.exact import ExactTracer
    from nbvh_core.geometry.texture_hold import hold_textures
    from nbvh_core.rendering.metrics import ViewScorer
    from nbvh_core.rendering.render import render_reference

    held, said = hold_textures(source, px)
    images = [m for m in held.look.materials if m.image is not None]
    row = {"on_screen_px": px or "as stored", "held": said.split(": ", 1)[1] if said else "none",
           "sides": " ".join(f"{m.image.shape[1]}x{m.image.shape[0]}" for m in images),
           "image_bytes": sum(len(m.stored_image()) for m in images)}
    shaded = ExactTracer(held)
    for res in resolutions:
        scorer = ViewScorer(ExactTracer(source), source.transform, 16, res, held_out=True)
        q, _ = scorer.score(lambda cam, w, h: render_reference(shaded, cam, w, h), flip=True)
        row[f"colour_mse_{res}px"], row[f"flip_{res}px"] = q.colour_mse, q.flip
    return row


def upscaled(mesh, factor: int):
    """`mesh` with each image `factor` times larger (Lanczos; no source bytes): the same detail in more texels."""
    import dataclasses

    import numpy as np
    from PIL import Image

    def larger(m):
        if m.image is None:
            return m
        h, w = m.image.shape[:2]
        big = np.asarray(Image.fromarray(m.image).resize((w * factor, h * factor), Image.LANCZOS))
        return dataclasses.replace(m, image=np.ascontiguousarray(big), source=None)

    look = dataclasses.replace(mesh.look, materials=[larger(m) for m in mesh.look.materials])
    return dataclasses.replace(mesh, look=look, name=f"{mesh.name} (images x{factor})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--asset", default="fuze", help="a real asset (bench/real_assets.py) or a demo asset's name")
    ap.add_argument("--px", type=int, nargs="+", default=[0, 2048, 1024, 512, 256],
                    help="on-screen sizes (0: the images as stored)")
    ap.add_argument("--resolutions", type=int, nargs="+", default=[256, 1024], help="held-out view resolutions")
    ap.add_argument("--upscale", type=int, nargs="+", default=[1, 4],
                    help="each factor: the asset with its images this many times larger (Lanczos), an over-resolved "
                         "export of the same atlas (a 4K export of a 1K scan); 1: as it is")
    args = ap.parse_args()
    from nbvh_core.geometry import demo_assets
    from nbvh_core.geometry.mesh import load_mesh

    if args.asset in demo_assets.ASSETS:
        source = demo_assets.ASSETS[args.asset]()
    else:
        from bench.real_assets import asset_path

        source = load_mesh(asset_path(args.asset))
    run_stamp = stamp()
    rows = []
    for factor in args.upscale:
        asset = upscaled(source, factor) if factor > 1 else source
        rows += [{"images": f"x{factor}", **held_row(asset, px, tuple(args.resolutions))} for px in args.px]
    for r in rows:
        print(r)
    name = "texture_hold_smoke" if SMOKE else "texture_hold"
    write_rows(result_path(f"{name}.csv"), rows, run_stamp)
    header = list(rows[0])
    cells = [[f"{v:.5f}" if isinstance(v, float) else (f"{v:,}" if isinstance(v, int) else v) for v in r.values()]
             for r in rows]
    write_markdown(result_path(f"{name}.md"),
                   [f"# Textures held at the views' needs: {source.name} ({source.n_triangles:,} triangles)", "",
                    "Held by `geometry.texture_hold` (a texel per pixel on the sparsest-textured tenth of the surface "
                    "when the asset spans the on-screen size; held only where it stores fewer bytes). Colour MSE "
                    "(linear albedo) and FLIP: the held look against the source's, 16 held-out views; the geometry "
                    "is the source's.", "", *markdown_table(header, cells)], run_stamp)


if __name__ == "__main__":
    main()
