"""Command line: `python -m nbvh_core COMMAND ...` (also installed as `nbvh`).

Commands:
  compress MESH -o OUT.nbvh     train a neural model (presets + every knob), write the file, preview and numbers
  render OUT.nbvh -o IMG.png    render a model (orbit view or explicit camera)
  info OUT.nbvh [--json]        bytes per component, settings, training and quality recorded in the file
  eval MESH OUT.nbvh [--json]   the paper's metric against the mesh: MSE, silhouette IoU, depth error
  inspect MESH --out DIR        BVH + labelled training rays of a mesh: report and images (no training)
  plan MESH... --budget-kb N    share one byte budget among several meshes by need
  batch LIBRARY -o OUT          a library on Ray: measure and decide every asset, train the worth ones, report
  samples                       list the bundled sample meshes

MESH is a mesh file (OBJ/PLY/STL/OFF/GLB/glTF, optionally .gz) or a bundled sample name.
Exit codes: 0 ok, 2 bad input (mesh, file, option, output location), 3 training diverged, 4 not worth compressing
(nothing trained; --force trains anyway), 130 cancelled (Ctrl-C / SIGTERM).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .cli_common import fmt_bytes, load_mesh_reporting, resolve_mesh
from .cli_compress import add_compress_parser


#: The settings a library batch takes for every asset (as `compress` offers them).
BATCH_SETTINGS = ("budget_kb", "target_mse", "time_limit_s", "steps", "force")


def cmd_inspect(args: argparse.Namespace) -> int:
    import torch

    from ..geometry.bvh import build_full_tree, cut_tree
    from ..geometry.exact import ExactTracer
    from ..rendering.render import Camera, render_reference, save_png
    from ..training.rays import generate_training_samples
    from ..planning.sizing import mesh_resident_bytes

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    mesh = load_mesh_reporting(args.mesh)
    t_load = time.perf_counter() - t0
    print(f"{mesh.name}: {mesh.n_vertices} vertices, {mesh.n_triangles} triangles (loaded in {t_load:.2f} s)")

    t0 = time.perf_counter()
    tree = build_full_tree(mesh)
    bvh = cut_tree(tree, args.nodes)
    t_bvh = time.perf_counter() - t0
    print(f"BVH: {bvh.n_nodes} nodes ({bvh.nbytes} B), {bvh.n_leaves} leaves, depth {bvh.max_depth}, "
          f"built in {t_bvh:.2f} s")

    tracer = ExactTracer(mesh)
    sample_stats = {}
    for mode in ("ownership", "consistent"):
        t0 = time.perf_counter()
        s = generate_training_samples(bvh, tracer, args.rays, mode, seed=args.seed)
        dt = time.perf_counter() - t0
        sample_stats[mode] = dict(s.stats, seconds=round(dt, 3), samples_per_s=round(len(s) / dt),
                                  mean_leaves_per_ray=round(len(s) / args.rays, 2))
        print(f"training rays ({mode}): {args.rays} rays -> {len(s)} samples, {int(s.hit.sum())} hits, "
              f"{len(s) / dt:,.0f} samples/s")

    cam = Camera(position=np.array([0.5 + 1.25, 0.5 + 0.8, 0.5 + 1.25]), target=np.full(3, 0.5),
                 up=np.array([0.0, 1.0, 0.0]))
    ref = render_reference(tracer, cam, args.size, args.size)
    save_png(out / "reference.png", ref.display)
    # Leaf colouring: owner leaf of the visible triangle, random colour per leaf, modulated by the shading.
    o, d = cam.rays(args.size, args.size)
    fh = tracer.first_hit(o, d)
    palette = np.random.default_rng(1).uniform(0.25, 1.0, size=(bvh.n_leaves, 3))
    colour = np.zeros((len(o), 3))
    colour[fh.hit] = palette[bvh.tri_leaf[fh.tri[fh.hit]]] * (0.3 + 0.7 * ref.image.reshape(-1)[fh.hit, None])
    save_png(out / "leaves.png", colour.reshape(args.size, args.size, 3))

    report = {
        "mesh": {"name": mesh.name, "vertices": mesh.n_vertices, "triangles": mesh.n_triangles,
                 "repairs": list(mesh.repairs), "transform": mesh.transform.to_dict(),
                 "surface_area_normalised": round(mesh.surface_area(), 4), "load_seconds": round(t_load, 3)},
        "bvh": {"budget": args.nodes, "nodes": bvh.n_nodes, "leaves": bvh.n_leaves, "bytes": bvh.nbytes,
                "max_depth": bvh.max_depth, "build_seconds": round(t_bvh, 3),
                "triangles_per_leaf": {"min": int(bvh.leaf_tri_count.min()), "max": int(bvh.leaf_tri_count.max()),
                                       "mean": round(float(bvh.leaf_tri_count.mean()), 2)}},
        "resident_mesh_bytes": mesh_resident_bytes(mesh, tree),
        "training_samples": sample_stats,
        "exact_backend": tracer.backend,
        "torch": torch.__version__,
    }
    (out / "report.json").write_text(json.dumps(report, indent=2))
    print(f"wrote {out / 'report.json'}, {out / 'reference.png'}, {out / 'leaves.png'}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from .. import kernels
    from ..storage.fileformat import load_nbvh
    from ..rendering.render import Camera, orbit_cameras, render_neural, save_png
    from ..training.train import pick_device

    model = load_nbvh(args.model, pick_device(args.device))
    model.half_tables = args.half
    if args.position is not None:
        cam = Camera(position=np.asarray(args.position, float), target=np.asarray(args.target, float),
                     up=np.array([0.0, 1.0, 0.0]), fov_deg=args.fov)
    else:
        cam = orbit_cameras(max(args.views, args.view + 1), fov_deg=args.fov)[args.view]
    t = time.perf_counter()
    res = render_neural(model, cam, args.width, args.height or args.width)
    dt = time.perf_counter() - t
    save_png(args.output, res.display)
    n = res.image.size
    plan = kernels.plan(model)
    print(f"wrote {args.output} ({args.width}x{args.height or args.width}, {dt:.2f} s, {n / dt:,.0f} rays/s on "
          f"{plan.device}: query {plan.query}{'; ' + plan.note if plan.note else ''})")
    return 0


def cmd_pack(args: argparse.Namespace) -> int:
    """Write the storage variant of a model (xz, decoded at load by every reader) beside it, or to -o."""
    from ..storage.fileformat import decode_nbvh, read_model_bytes, write_atomic
    from ..storage.packed import pack

    src = Path(args.model)
    data = read_model_bytes(src)
    decode_nbvh(data, str(src))  # only a valid model is packed
    out = Path(args.output) if args.output else src.with_suffix(".nbvhz")
    if out.exists() and not args.overwrite:
        raise FileExistsError(f"{out} exists (add --overwrite to replace it)")
    if out.resolve() == src.resolve():
        raise ValueError(f"{out}: the packed file would replace the model it is made from")
    packed = pack(data)
    write_atomic(out, packed)
    print(f"wrote {out}: {len(packed):,} B on disk for the {len(data):,} B traceable file "
          f"({len(packed) / len(data):.2f}x; `render`, `info` and the add-on read it as it is)")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from ..storage.fileformat import read_info
    from ..planning.sizing import mesh_resident_bytes

    info = read_info(args.model)
    meta = info.metadata
    out = {"path": info.path, "bytes": info.total_bytes, "stored_bytes": info.stored_bytes,
           "components": info.components,
           "config": info.header.fields["config"], "storage": info.storage.to_dict(),
           "source": meta.get("source"), "training": meta.get("training"), "quality": meta.get("quality"),
           "appearance": info.header.fields.get("appearance"), "textures": info.textures}
    if args.mesh:
        mesh = load_mesh_reporting(args.mesh)
        res = mesh_resident_bytes(mesh)
        out["mesh_resident_bytes"] = res
        out["ratio_resident_mesh_to_nbvh"] = res["total"] / info.total_bytes
        out["source_file_bytes"] = resolve_mesh(args.mesh).stat().st_size
        out["ratio_source_file_to_nbvh"] = out["source_file_bytes"] / info.total_bytes
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{info.path}: {fmt_bytes(info.total_bytes)} ({info.total_bytes:,} B)"
          + (f"; on disk {info.stored_bytes:,} B packed (xz, decoded at load)" if info.stored_bytes != info.total_bytes
             else ""))
    for k, v in info.components.items():
        print(f"  {k:10s} {v:>10,} B  {100 * v / info.total_bytes:5.1f}%")
    c = info.header.fields["config"]
    st = info.storage
    print(f"  model: {c['encoding']['kind']} T=2^{c['encoding']['log2_table']}, {c['network']['kind']} k={c['network']['k']}; "
          f"stored with {st.table_bits}-bit features, {st.network_bits}-bit weights, {st.node_bits}-bit boxes")
    look = info.header.fields.get("appearance")
    if look:
        def image(i: int, m: dict) -> str:
            t = info.textures.get(i, {})
            return f" ({m['image'][1]}x{m['image'][0]} {t.get('format', '').upper()}, {t.get('bytes', 0):,} B)"

        mats = ", ".join(m["name"] + (image(i, m) if m["image"] else "") for i, m in enumerate(look["materials"]))
        head = look["config"]
        print(f"  look: {len(look['materials'])} slot(s): {mats}; "
              + (f"head: {head.get('target', 'coordinates')}, {head.get('patches', 1)} patch(es)" if head else "no head (one plain slot)"))
    if meta.get("source"):
        s = meta["source"]
        print(f"  source: {s['name']}, {s['triangles']:,} triangles")
    if meta.get("quality"):
        q = meta["quality"]
        print(f"  quality: MSE {q['mse']:.5f}, IoU {q['silhouette_iou']:.4f}")
    if "mesh_resident_bytes" in out:
        print(f"  vs the mesh as a ray tracer holds it ({out['mesh_resident_bytes']['total']:,} B): "
              f"{out['ratio_resident_mesh_to_nbvh']:.1f}x; vs its file ({out['source_file_bytes']:,} B): "
              f"{out['ratio_source_file_to_nbvh']:.1f}x")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from ..geometry.exact import ExactTracer
    from ..storage.fileformat import load_nbvh
    from ..rendering.metrics import evaluate

    model = load_nbvh(args.model)
    mesh = load_mesh_reporting(args.mesh)
    src = model.metadata.get("source", {})
    if src and src.get("triangles") not in (None, mesh.n_triangles):
        print(f"warning: the model was trained on a mesh of {src['triangles']} triangles, this one has "
              f"{mesh.n_triangles}", file=sys.stderr)
    q, _ = evaluate(model, ExactTracer(mesh), args.views, args.resolution)
    d = q.to_dict()
    if args.json:
        print(json.dumps(d, indent=2))
    else:
        print(f"MSE {q.mse:.6f}  silhouette IoU {q.silhouette_iou:.4f}  depth error {q.depth_error:.6f} (unit box), "
              f"{q.depth_error_original_units:.6g} (mesh units)  over {q.views} views at {q.resolution}px; "
              f"neural {q.neural_rays_per_s:,.0f} rays/s, Embree {q.reference_rays_per_s:,.0f} rays/s")
    return 0


def cmd_samples(args: argparse.Namespace) -> int:
    from ..geometry.bundled_samples import SAMPLE_NAMES, sample_path

    for name, what in SAMPLE_NAMES.items():
        p = sample_path(name)
        print(f"{name:8s} {what:45s} {p}")
    return 0


def cmd_plan(args: argparse.Namespace) -> int:
    """Share one byte budget among several meshes by need (sizing.plan_scene) and print the split."""
    from ..planning.settings import preset
    from ..planning.sizing import plan_scene

    meshes = [load_mesh_reporting(m) for m in args.meshes]
    plan = plan_scene(meshes, args.budget_kb * 1024, preset(args.preset).with_overrides(mesh_layout=args.mesh_layout),
                      args.weights)
    rows = [{"mesh": r["name"], **{k: v for k, v in r.items() if k != "name"}} for r in plan["objects"]]
    for r in rows:
        r["predicted_mse"] = None if r["predicted_mse"] is None else round(r["predicted_mse"], 6)
    if args.json:
        skip = ("features", "objects", "base")
        print(json.dumps({**{k: v for k, v in plan.items() if k not in skip}, "objects": rows}, indent=2))
        return 0
    level = "-" if plan["level"] is None else f"{plan['level']:.4g}"
    print(f"budget {args.budget_kb:g} KB shared by need: common quality level MSE {level} "
          f"(each mesh aims at level / weight), total {plan['total'] / 1024:.0f} KB")
    for r in rows:
        if r["excluded"]:
            print(f"  {r['mesh']}: {r['triangles']:,} triangles -> nothing: its mesh is no larger than its model "
                  f"(keep the mesh)")
            continue
        print(f"  {r['mesh']}: {r['triangles']:,} triangles, weight {r['weight']:g} -> T=2^{r['log2_table']}, "
              f"{r['bytes'] / 1024:.0f} KB, predicted MSE {r['predicted_mse']:.4g}")
    return 0


def cmd_batch(args: argparse.Namespace) -> int:
    """Compress a library on Ray (batch.run_batch): measure and decide every asset, train the worth ones."""
    from .cli_options import request_from_args
    from .library_batch import run_batch
    from ..protocol.events import json_lines, progress_bar
    from ..protocol.process import install_cancel_handlers
    from ..protocol.quality_levels import QUALITY_LEVELS

    spec = {k: v for k, v in request_from_args(args, BATCH_SETTINGS).items() if v is not None}
    spec["preset"] = args.preset
    if args.quality:
        spec["target_mse"] = QUALITY_LEVELS[args.quality]
    sink = json_lines(sys.stdout) if args.events else progress_bar(sys.stderr)
    summary = run_batch(args.library, args.output, spec, sink, install_cancel_handlers(), address=args.address,
                        num_cpus=args.num_cpus, measure_only=args.measure_only, blender=args.blender)
    if not args.events:
        t = summary["totals"]
        print(f"\n{t['assets']} assets: " + ", ".join(f"{k} {v}" for k, v in sorted(t["by_status"].items())))
        print(f"resident memory {fmt_bytes(t['resident_before_bytes'])} -> {fmt_bytes(t['resident_after_bytes'])} "
              f"(saved {fmt_bytes(t['saved_bytes'])}); model files {fmt_bytes(t['model_storage_bytes'])}")
        print(f"report: {summary['html']} (+ report.csv, report.json)")
    return 0


def _add_inspect_parser(sub) -> None:
    q = sub.add_parser("inspect", help="BVH + training rays of a mesh: report and images")
    q.add_argument("mesh", help="mesh file (OBJ/PLY/STL/OFF/GLB/glTF, optionally .gz) or a bundled sample name")
    q.add_argument("--out", required=True, help="output folder")
    q.add_argument("--nodes", type=int, default=4096, help="BVH node budget (1..65535, default 4096)")
    q.add_argument("--rays", type=int, default=50_000, help="training rays to generate per label mode")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--size", type=int, default=384, help="image size in pixels")
    q.set_defaults(func=cmd_inspect)


def _add_render_parser(sub) -> None:
    from ..training.config import DEVICES

    r = sub.add_parser("render", help="render a .nbvh model to PNG")
    r.add_argument("model")
    r.add_argument("-o", "--output", required=True)
    r.add_argument("--width", type=int, default=512)
    r.add_argument("--height", type=int)
    r.add_argument("--view", type=int, default=0, help="orbit view index")
    r.add_argument("--views", type=int, default=16, help="orbit views the index counts in")
    r.add_argument("--position", type=float, nargs=3, help="camera position (unit-box coordinates)")
    r.add_argument("--target", type=float, nargs=3, default=[0.5, 0.5, 0.5])
    r.add_argument("--fov", type=float, default=40.0)
    r.add_argument("--half", action="store_true", help="float16 feature rows while rendering (faster on the CPU)")
    r.add_argument("--device", choices=DEVICES, default="auto",
                   help="where the model answers rays (auto: the card when there is one; its ray query is one Triton "
                        "kernel, the line printed says which path ran)")
    r.set_defaults(func=cmd_render)


def _add_info_parser(sub) -> None:
    pk = sub.add_parser("pack", help="the storage variant of a .nbvh model: xz on disk, decoded at load")
    pk.add_argument("model")
    pk.add_argument("-o", "--output", help="the packed file (default: MODEL with the suffix .nbvhz)")
    pk.add_argument("--overwrite", action="store_true")
    pk.set_defaults(func=cmd_pack)

    i = sub.add_parser("info", help="bytes per component and recorded numbers of a .nbvh file")
    i.add_argument("model")
    i.add_argument("--mesh", help="source mesh: also report the ratio to it")
    i.add_argument("--json", action="store_true")
    i.set_defaults(func=cmd_info)


def _add_eval_parser(sub) -> None:
    e = sub.add_parser("eval", help="the paper's metric of a .nbvh model against its mesh")
    e.add_argument("mesh")
    e.add_argument("model")
    e.add_argument("--views", type=int, default=16)
    e.add_argument("--resolution", type=int, default=256)
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_eval)


def _add_plan_parser(sub) -> None:
    from ..decision.config import MESH_LAYOUTS
    from ..planning.settings import PRESETS

    pl = sub.add_parser("plan", help="share one byte budget among several meshes by need")
    pl.add_argument("meshes", nargs="+")
    pl.add_argument("--budget-kb", type=float, required=True)
    pl.add_argument("--weights", type=float, nargs="+", help="per mesh, e.g. its share of the screen (default 1)")
    pl.add_argument("--preset", default="default", choices=list(PRESETS),
                    help="the settings each object's model is sized with (its T comes from the split)")
    pl.add_argument("--mesh-layout", choices=MESH_LAYOUTS, default="compact",
                    help="how a mesh kept as a mesh is held: an object whose mesh is no larger than its share's "
                         "model gets nothing")
    pl.add_argument("--json", action="store_true")
    pl.set_defaults(func=cmd_plan)


def _add_samples_parser(sub) -> None:
    s = sub.add_parser("samples", help="list the bundled sample meshes")
    s.set_defaults(func=cmd_samples)


def _add_batch_parser(sub) -> None:
    from .cli_options import add_setting_options
    from ..protocol.quality_levels import QUALITY_LEVELS
    from ..planning.settings import PRESETS

    b = sub.add_parser("batch", help="compress a library of assets on Ray (one machine or a cluster)")
    b.add_argument("library", help="a folder (searched recursively: mesh files, .npz arrays, .blend files) or a "
                                   "list file with one path per line")
    b.add_argument("-o", "--output", required=True, help="output folder: report.html/.csv/.json, assets/, thumbs/")
    b.add_argument("--preset", choices=list(PRESETS),
                   help="named fixed settings for every asset (default: each asset sized to the quality level standard)")
    add_setting_options(b, BATCH_SETTINGS, group_extras={"size": lambda g: g.add_argument(  # as `compress` has them
        "--quality", choices=list(QUALITY_LEVELS), help="a named target for every asset")})
    b.add_argument("--address", help="join a Ray cluster ('auto' or HOST:PORT, started with `ray start`); "
                                     "default: an embedded Ray on this machine")
    b.add_argument("--num-cpus", type=int, help="CPUs of the embedded Ray (default: all of this machine's)")
    b.add_argument("--measure-only", action="store_true", help="measure and decide every asset; train nothing")
    b.add_argument("--blender", help="Blender binary for .blend files (default: $NBVH_BLENDER or `blender`)")
    b.add_argument("--events", action="store_true", help="JSON-line events on stdout instead of a progress bar")
    b.set_defaults(func=cmd_batch)


def build_parser() -> argparse.ArgumentParser:
    from ..kernels import PATHS

    p = argparse.ArgumentParser(prog="nbvh", description="Neural BVH geometry compression")
    p.add_argument("--path", choices=PATHS,
                   help="compute path: fused C++ kernels (fast, default) or pure torch (reference); "
                        "also env NBVH_PATH")
    sub = p.add_subparsers(dest="command", required=True)
    _add_inspect_parser(sub)
    add_compress_parser(sub)
    _add_render_parser(sub)
    _add_info_parser(sub)
    _add_eval_parser(sub)
    _add_plan_parser(sub)
    _add_batch_parser(sub)
    _add_samples_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    started_at = time.perf_counter()  # a run's wall counts from here: the kernels' and torch's imports included
    from .. import kernels
    from ..protocol.process import Cancelled, NotWorthCompressing, outcome

    argv = sys.argv[1:] if argv is None else argv
    kernels.keep_freed_memory()  # this process trains or renders: keep its freed blocks (see the function)
    if argv[:1] == ["job"]:  # the background job protocol (see job.py): JSON events on stdout
        from .job import main as job_main

        return job_main(argv[1:])
    if argv[:1] == ["render-worker"]:  # the render engine's worker (see render_worker.py): JSON lines both ways
        from .render_worker import main as worker_main

        return worker_main(argv[1:])
    args = build_parser().parse_args(argv)
    args.started_at = started_at
    if args.path:
        kernels.set_path(args.path)
    try:
        return args.func(args)
    except Exception as exc:  # the exit code says how it ended (process.outcome); a crash keeps its traceback
        end = outcome(exc)
        if end.code == 1:
            raise
        if isinstance(exc, Cancelled):
            print(f"\ncancelled: {exc}; nothing was written", file=sys.stderr)
        elif isinstance(exc, NotWorthCompressing):
            print(f"{exc}\nno model was written; --force ships a model anyway", file=sys.stderr)
        elif end.kind == "diverged":
            print(f"\nerror: {end.message}; nothing was written", file=sys.stderr)
        else:
            print(f"error: {end.message}", file=sys.stderr)
        return end.code
    except KeyboardInterrupt:
        print("\ncancelled; nothing was written", file=sys.stderr)
        return 130
