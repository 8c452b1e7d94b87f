"""`nbvh compress`: its options (the settings' own, `cli_options`, and the run's), the run checked before it trains
and locked to its output, the verdict's alternative written when the mesh wins, and the result's summary."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from ..protocol import events as wire
from .cli_common import fmt_bytes, load_mesh_reporting, resolve_mesh

def add_compress_parser(sub) -> None:
    from .cli_options import add_setting_options
    from ..protocol.quality_levels import QUALITY_LEVELS
    from ..protocol.quality_levels import describe as describe_levels
    from ..planning.settings import PRESETS

    c = sub.add_parser("compress", help="train a neural model of a mesh and write OUT.nbvh")
    c.add_argument("mesh")
    c.add_argument("-o", "--output", required=True,
                   help="output .nbvh file (+ .report.json, .preview.png, .reference.png beside it)")
    c.add_argument("--preset", choices=list(PRESETS),
                   help="named fixed settings (preview, default, high; the options below override single fields); "
                        "without a preset or a size the run is sized to the quality level standard: the verdict "
                        "first, then one training that grows its table until the level is met")
    add_setting_options(c, group_extras={"size": lambda g: g.add_argument(  # every Settings field declared with help
        "--quality", choices=list(QUALITY_LEVELS), help=f"a named target: {describe_levels()}")})
    c.add_argument("--float16", action="store_true", help="store tables and weights as float16 (= --table-bits 16)")
    c.add_argument("--view", type=int, help="orbit view index of the preview image")
    c.add_argument("--size", type=int, default=256, help="preview image size")
    c.add_argument("--checkpoint", help="checkpoint file written during training (default: .OUT.nbvh.checkpoint "
                                        "beside the output, removed when the run finishes)")
    c.add_argument("--resume", metavar="CHECKPOINT", help="continue the training a checkpoint holds (same mesh; its "
                                                         "settings are used)")
    c.add_argument("--overwrite", action="store_true", help="replace an existing result at -o")
    c.add_argument("--events", action="store_true", help="print JSON-line events on stdout instead of a bar")
    c.set_defaults(func=cmd_compress)


def cmd_compress(args: argparse.Namespace) -> int:
    """Train, then write the result bundle (result_bundle: the model, its report, its preview and the mesh's from the
    same view) as one unit: checked before training (never over the input, never over a finished result without
    --overwrite, writable), one run per output (outputs.OutputLock), checkpoints every --checkpoint-every seconds
    (resume with --resume)."""
    from ..protocol.events import json_lines, progress_bar
    from ..protocol.outputs import OutputLock, check_outputs, resolve_output
    from ..protocol.process import outcome
    from .result_bundle import bundle_paths

    started_at = getattr(args, "started_at", None) or time.perf_counter()  # the run's wall counts its loading
    sink = json_lines(sys.stdout) if args.events else progress_bar(sys.stderr)
    try:
        mesh_path = resolve_mesh(args.mesh)
        mesh = load_mesh_reporting(args.mesh)
        out = resolve_output(args.output, mesh.name)
        paths = bundle_paths(out, ("model", "report", "preview", "reference"))
        inputs = [mesh_path] + ([Path(args.resume)] if args.resume else [])
        check_outputs(list(paths.values()), inputs, overwrite=args.overwrite)
        with OutputLock(out):
            return _compress_locked(args, mesh, mesh_path, paths, sink, started_at)
    except BaseException as exc:  # the event stream says how the run ended, whatever ended it
        if args.events:
            sink(wire.error(kind=outcome(exc).kind, message=str(exc)))
        raise


def _write_alternative(mesh, assessment, stem: Path, mesh_path: Path, args, sink, decimator=None) -> None:
    """When the verdict keeps a mesh, the user gets the mesh that wins, beside where the model would have gone
    (`kept_mesh.kept_mesh_files`: NAME.glb with its look, NAME.compact.cmsh of exactly the bytes the verdict counted;
    written atomically; an existing file only with --overwrite), and why, as NAME.verdict.json: the assessment with
    the measured alternatives, the final verdict, the training's checks when training had begun, each file's
    bytes and the kept decimation's quality with its look (`kept_mesh.kept_quality`: FLIP, colour and image MSE on
    the held-out views; no model report: no model was written)."""
    from ..protocol.outputs import check_outputs, write_atomic
    from .alternatives import winning_decimation
    from .kept_mesh import counted_compact_bytes, kept_mesh_files, kept_quality
    from .pipeline import memory_record

    dec = winning_decimation(mesh, assessment, decimator)  # once: the files and the quality read the same mesh
    files = {Path(f"{stem}{suffix}"): data for suffix, data in kept_mesh_files(mesh, assessment, dec).items()}
    why = {**assessment.to_dict(), "files": {p.name: len(d) for p, d in files.items()},
           "counted_compact_bytes": counted_compact_bytes(assessment), "kept_quality": kept_quality(mesh, dec),
           "memory": memory_record(mesh)}
    files[Path(f"{stem}.verdict.json")] = json.dumps(why, indent=1, default=str).encode()
    for path, data in files.items():
        try:
            check_outputs([path], [mesh_path], overwrite=args.overwrite)
        except ValueError as exc:  # an earlier result there: kept unless --overwrite
            print(f"the winning mesh was not written: {exc}", file=sys.stderr)
            continue
        write_atomic(path, data)
        if path.suffix == ".json":
            print(f"why: {path}", file=sys.stderr)
            continue
        if args.events:
            sink(wire.written(files=[str(path)], kind="decimation" if dec is not None else "mesh",
                              triangles=(dec or mesh).n_triangles))
        final = assessment.final
        reached = ("reaches the model's measured quality" if final and not final.at_level
                   else "meets the target")
        what = (f"the decimation that {reached} ({dec.n_triangles:,} triangles, MSE "
                f"{assessment.alternatives.decimation.compact_mse:.4g})" if dec is not None else "the mesh")
        print(f"kept as a mesh: wrote {what} to {path} ({len(data):,} B)", file=sys.stderr)


def _compress_locked(args, mesh, mesh_path, paths, sink, started_at: float) -> int:
    from .cli_options import request_from_args
    from ..protocol.outputs import checkpoint_for
    from .pipeline import compress_mesh, resume_settings
    from ..protocol.process import NotWorthCompressing, install_cancel_handlers
    from ..planning.settings import settings_from_request
    from ..rendering.render import orbit_cameras
    from ..protocol.quality_levels import QUALITY_LEVELS
    from .result_bundle import View, make_bundle, write_bundle

    out = paths["model"]
    stem = out.with_suffix("")

    if args.resume:
        settings = resume_settings(args.resume, mesh)
        print(f"resuming {args.resume}: T=2^{settings.log2_table}, {settings.nodes} nodes, "
              f"{settings.encoding}+{settings.network}", file=sys.stderr)
    else:
        spec = {**request_from_args(args), "preset": args.preset}
        if args.float16:
            spec.update(table_bits=16, network_bits=16)
        if args.quality:
            spec["target_mse"] = QUALITY_LEVELS[args.quality]
        settings = settings_from_request(spec)
    settings = settings.with_overrides(force=args.force, checkpoint_every_s=args.checkpoint_every_s)
    default_ck = checkpoint_for(out)
    checkpoint = Path(args.checkpoint) if args.checkpoint else default_ck
    try:
        result = compress_mesh(mesh, settings, None, events=sink, should_cancel=install_cancel_handlers(),
                               checkpoint_path=checkpoint, resume_from=args.resume, started_at=started_at)
    except NotWorthCompressing as exc:
        _write_alternative(mesh, exc.assessment, stem, mesh_path, args, sink, exc.decimator)
        raise
    except BaseException:
        if checkpoint.exists():
            print(f"\ntraining state kept in {checkpoint}: continue with "
                  f"`nbvh compress {args.mesh} -o {out} --resume {checkpoint}`", file=sys.stderr)
        raise
    cam = orbit_cameras(1)[0] if args.view is None else orbit_cameras(args.eval_views or 16)[args.view]
    bundle = make_bundle(result, mesh, View(cam, args.size, args.size), tuple(paths),
                         extra={"source_file_bytes": mesh_path.stat().st_size})
    write_bundle(paths, bundle)  # the model, its report and its previews appear together, or the previous ones stay
    summary = bundle.report
    if checkpoint == default_ck or args.resume == str(checkpoint):
        checkpoint.unlink(missing_ok=True)
    if args.events:
        sink(wire.written(files=[str(p) for p in paths.values()]))
    else:
        _print_result(result, summary, out, paths)
    return 0


def _print_result(result, summary: dict, out: Path, paths: dict) -> None:
    """What `compress` prints when it wrote its files: the verdict against the strongest alternative first, the
    bytes, the whole mesh held compactly and plainly, the quality (geometry, and the file as shipped with its
    look), the training and why."""
    q = result.quality
    print(f"\nwrote {out} ({fmt_bytes(result.file_bytes)}) and, beside it, "
          f"{', '.join(p.name for role, p in paths.items() if role != 'model')}")
    final, assessment = result.decisions.final, result.assessment
    if final:  # the strongest alternative first: the compact decimation at the model's own measured MSE
        print(f"verdict: {final.message}")
    print("bytes: " + ", ".join(f"{k} {v:,}" for k, v in result.components.items()))
    resident = summary['mesh_resident_bytes']['total']
    compact = assessment.compact_bytes if assessment else None
    held = [f"as a compact mesh {compact:,} B ({compact / result.file_bytes:.2f}x the model)"] if compact else []
    held.append(f"as a ray tracer holds it {resident:,} B ({resident / result.file_bytes:.1f}x the model)")
    print("the whole mesh: " + "; ".join(held))
    draco = assessment.alternatives.draco11_bytes if assessment else None
    if draco:
        print(f"the mesh as a Draco 11-bit file (storage and transfer only; decoded before tracing): {draco:,} B")
    if q:
        print(f"quality ({q.views} {'held-out ' if q.held_out else ''}views, {q.resolution}px): MSE {q.mse:.5f}, "
              f"silhouette IoU {q.silhouette_iou:.4f}, depth error {q.depth_error:.5f} (unit box)")
    turned = result.quality_turned
    if turned is not None:
        print(f"a second held-out set ({turned.views} views turned at random, seed {turned.turn_seed}): MSE "
              f"{turned.mse:.5f}, silhouette IoU {turned.silhouette_iou:.4f}")
    s = result.quality_as_shipped
    if s is not None and s.colour_mse is not None:
        print(f"the file as shipped, its look included ({s.views} held-out views, {s.resolution}px): colour MSE "
              f"{s.colour_mse:.5f}, FLIP {s.flip:.4f}")
    t = result.training
    reused = f"; {t.reused_batches:,} batches served again while the host labelled" if t.reused_batches else ""
    batch = f" of {t.rays_per_step:,} rays" if t.rays_per_step else ""
    print(f"training: {t.steps} steps{batch}, {t.seconds:.1f} s, {t.samples_per_s:,.0f} samples/s on {t.device}{reused}")
    print(f"why: {result.why}")
    if result.target_met is not None:
        print(f"target {'met' if result.target_met else 'MISSED'}: MSE {q.mse:.5f} vs {result.settings.target_mse:g}")
    if assessment and not assessment.worth_compressing:
        print(f"note: {assessment.message}")
