"""Headless compression inside Blender (the same code path as the panel):

    blender -b scene.blend -P compress.py -- (--objects NAME [NAME ...] | --all) --out DIR
            [--preset preview|default|high | --budget-kb N | --target-mse X | --quality preview|standard|high]
            [--time-limit S] [--device auto|cpu|cuda]
            [--python PATH] [--load MODEL.nbvh] [--save-blend FILE.blend] [--force] [--resume]

Under `blender -b`, timers never fire while this script runs, so it waits on the jobs itself and prints
their events as progress. Exit code 0 only when every object was compressed (or loaded); otherwise the
error is printed and the exit code is 1 (Blender needs --python-exit-code 1 to pass it on, or the script
exits itself, as it does here). The user's objects are never modified; the .blend is saved only with
--save-blend, to a new file. --budget-kb with several objects is one budget for all of them, shared by need
(detail and size on the scene camera's screen); the report shows the split. --target-mse / --quality size each
object for that image MSE, measure it and retrain at the size the measurement calls for (at most 3 trainings).
An object that is not worth compressing gets its verdict in seconds and no training unless --force; --resume
continues the checkpoint a killed run left in --out. A failed or cancelled re-run keeps the previous results.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))


def engine_quality_levels() -> dict:
    from nbvh_core.protocol.quality_levels import QUALITY_LEVELS  # plain Python: no torch in Blender's process

    return QUALITY_LEVELS


def describe_levels() -> str:
    from nbvh_core.protocol.quality_levels import describe

    return describe()


def parse(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="blender -b FILE.blend -P compress.py --",
                                 description="Compress Blender objects into neural geometry (.nbvh)")
    which = ap.add_mutually_exclusive_group(required=True)
    which.add_argument("--objects", nargs="+", help="object names")
    which.add_argument("--all", action="store_true", help="every mesh object of the file")
    ap.add_argument("--out", required=True, help="output folder for .nbvh files, previews and the report")
    size = ap.add_mutually_exclusive_group()
    size.add_argument("--preset", help="named fixed sizes (nbvh_core's presets: preview, default, high, the paper's "
                                       "base, I, II, III; default: each object sized to the quality level standard)")
    size.add_argument("--budget-kb", type=float)
    size.add_argument("--target-mse", type=float)
    size.add_argument("--quality", choices=list(engine_quality_levels()),
                      help=f"named target: {describe_levels()}")
    ap.add_argument("--time-limit", type=float, help="training seconds per object")
    ap.add_argument("--steps", type=int, help="training steps per object (tests)")
    ap.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    ap.add_argument("--python", help="Python with PyTorch for the jobs (default: found automatically)")
    ap.add_argument("--load", help="load an existing .nbvh for the (single) object instead of training")
    ap.add_argument("--save-blend", help="save the scene with the previews to this new .blend")
    ap.add_argument("--force", action="store_true", help="train even objects that are not worth compressing")
    ap.add_argument("--resume", action="store_true", help="continue the training a killed run left in --out")
    return ap.parse_args(argv)


def run(argv: list[str]) -> int:
    import bpy

    from addon import compress_session, previews, render_engine
    from addon.job import default_python

    args = parse(argv)
    if not hasattr(bpy.types.Object, "nbvh_model"):  # the add-on is not enabled here: its object link still saves
        bpy.types.Object.nbvh_model = render_engine._model_property()
    if args.all:
        objects = [o for o in bpy.context.scene.objects if o.type == "MESH"]
        if not objects:
            print("error: --all: this file has no mesh objects", file=sys.stderr)
            return 1
    else:
        missing = [n for n in args.objects if bpy.data.objects.get(n) is None]
        if missing:
            print(f"error: no object named {', '.join(repr(n) for n in missing)} in this file", file=sys.stderr)
            return 1
        objects = [bpy.data.objects[n] for n in args.objects]
    overrides = {"device": args.device, "time_limit_s": args.time_limit, "steps": args.steps,
                 "budget_kb": args.budget_kb, "force": True if args.force else None,
                 "target_mse": compress_session.QUALITY_LEVELS[args.quality] if args.quality else args.target_mse}
    if args.steps is not None and args.time_limit is None:
        overrides["time_limit_s"] = 0  # steps only (0 = no wall-clock limit, see job)
    overrides = {k: v for k, v in overrides.items() if v is not None}
    req = compress_session.Request(preset=args.preset, overrides=overrides, out_dir=str(Path(args.out).resolve()),
                         load_model=args.load, resume=args.resume)
    python = args.python or default_python()
    try:
        session, refusals = compress_session.start(bpy.context, objects, req, python)
    except RuntimeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    for msg in refusals:
        print(f"error: {msg}", file=sys.stderr)
    if refusals:
        session.queue.cancel_all()
        for job in session.queue.jobs:
            job.cleanup()
        return 1

    def show(job, ev):
        kind = ev.get("event")
        if kind == "progress":
            print(f"[{job.name}] {ev.get('phase')} {100 * ev.get('fraction', 0):5.1f}% step {ev.get('step')} "
                  f"loss {ev.get('loss')} {ev.get('samples_per_s')} samples/s ETA {ev.get('eta_s')} s", flush=True)
        elif kind in ("phase", "warning", "error"):
            print(f"[{job.name}] {kind}: {ev.get('phase', '')} {ev.get('message', '')}", flush=True)
        elif kind == "result":
            print(f"[{job.name}] wrote {ev.get('path')} ({ev.get('bytes')} B)", flush=True)

    session.queue.wait(on_event=show)
    compress_session.end_session(session)
    compress_session.finish_done(session, bpy.context.scene)
    paths = compress_session.write_scene_report(session)
    if paths:
        print(f"report: {paths[0]} {paths[1]}")
    if args.save_blend:
        target = Path(args.save_blend).resolve()
        if bpy.data.filepath and Path(bpy.data.filepath).resolve() == target:
            print("error: --save-blend must name a new file, not the open .blend", file=sys.stderr)
            return 1
        links = previews.relink_models(target)  # "//" in the saved file means its own folder
        bpy.ops.wm.save_as_mainfile(filepath=str(target), copy=True)
        print(f"saved {target} with {links} model link(s) relative to it (the NBVH render engine draws them)")
    for name, msg in session.kept_as_mesh.items():
        print(f"{name}: kept as a mesh (nothing trained; --force trains anyway): {msg}")
    for name, msg in session.failures.items():
        print(f"error: {name}: {msg}", file=sys.stderr)
    return 1 if session.failures else 0


def main() -> int:
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    try:
        code = run(argv)
    except SystemExit as exc:  # argparse (--help, bad options)
        code = int(exc.code or 0)
    return code


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    if code:
        sys.exit(code)
