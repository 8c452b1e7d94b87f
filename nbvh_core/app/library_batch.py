"""Compress an asset library on Ray: decide first, train second, resumable, robust to bad assets and dead workers.

    nbvh batch LIBRARY -o OUT [--quality Q | --target-mse X | --budget-kb N] [--address auto|HOST:PORT]

* **Assets** (`discover`): LIBRARY is a folder (searched recursively for every mesh format the CLI reads, .npz
  arrays, and .blend files - each mesh object one asset, exported by a `blender` binary, `blend_export.py`) or a
  list file (one path per line, relative to the list). A file that cannot be read becomes a failed row, not a stop.
* **Decide first** (`measure_asset`, one Ray task per asset): triangles, resident bytes as a ray tracer holds the
  mesh, its Draco size, the run's own verdict (`weighing.weigh`) and a thumbnail, before any training; the first report is
  written as soon as every asset is measured.
* **Train second** (`compress_asset`): only assets worth compressing, largest predicted savings first, each one task
  sized by its need (CPUs and memory from the triangle count, a GPU when the cluster has one). A task returns its
  results as bytes; the driver writes them (`outputs.OutputSet`: all files of an asset appear together), so a
  worker that dies leaves nothing behind, and Ray retries it (`max_retries`). An asset's failure (bad mesh,
  divergence) is its row's error; the run goes on.
* **Resume**: each trained asset lives in OUT/assets/KEY/, KEY = hash of the mesh's content and the settings; a
  rerun finds KEY/result.json and trains nothing again. Ctrl-C / SIGTERM cancels the tasks and keeps what finished.
* **Cluster**: without `address` an embedded Ray starts with this machine's cores (`ray.init()`); `address`
  ('auto' or HOST:PORT) joins a cluster started with `ray start --head` / `ray start --address HOST:PORT`.

Events (JSON lines with `--events`, for the add-on): `progress` (phase measure|train, done, total, fraction, eta_s),
`asset` (one per finished row), `warning`, and a final `result` with the report's paths.
"""
from __future__ import annotations

import hashlib
import json
import os
import socket
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from ..protocol.events import EventSink, null_sink
from ..protocol import events as wire
from .library_assets import Asset, discover, load_asset
from .ray_tasks import cluster_info, require_ray, run_tasks, start_ray, task_resources
from ..planning.settings import settings_from_request

THUMBNAIL_PX = 96


@dataclass
class Row:
    """A library report row: what was measured, decided and (for worth assets) trained. status: measured |
    not_worth | done | cached | failed | cancelled."""

    name: str
    source: str
    status: str = "measured"
    error: str | None = None
    triangles: int | None = None
    mesh_resident_bytes: int | None = None
    draco_bytes: int | None = None
    compact_bytes: int | None = None  # the mesh as a compact ray-traceable mesh (compact_mesh)
    texture_bytes: int | None = None  # the asset's images as held (width x height x channels), kept either way
    decimation_triangles: int | None = None  # the verdict's winning decimation (written beside the results)
    decimation_compact_bytes: int | None = None  # what the verdict counted for it as a compact mesh
    decimation_written_bytes: int | None = None  # the NAME.compact.cmsh written: equal to the count
    predicted_model_bytes: int | None = None
    #: After training, the compact decimation's bytes at the model's own held-out MSE (decision.final_verdict)
    alternative_bytes: int | None = None
    verdict: str | None = None
    recommendation: str | None = None
    key: str | None = None
    model_bytes: int | None = None  # the .nbvh file (stored and resident as traced)
    model_resident_bytes: int | None = None
    mse: float | None = None
    iou: float | None = None
    train_seconds: float | None = None
    measure_seconds: float | None = None
    worker: str | None = None  # host:pid of the worker that produced the result
    thumb_original: str | None = None  # PNG file name inside OUT/thumbs
    thumb_neural: str | None = None
    files: dict = field(default_factory=dict)

    @property
    def saved_vs_alternative_bytes(self) -> int:
        """Bytes saved by the model against the strongest alternative: the compact decimation at the same measured
        MSE (0 when not compressed or not measured; negative never ships: the batch keeps the mesh then)."""
        if self.status in ("done", "cached") and self.alternative_bytes and self.model_bytes:
            return self.alternative_bytes - self.model_bytes
        return 0

    @property
    def saved_bytes(self) -> int:
        """Resident bytes saved by using the model instead of the mesh (0 when not compressed)."""
        if self.status in ("done", "cached") and self.mesh_resident_bytes and self.model_resident_bytes:
            return self.mesh_resident_bytes - self.model_resident_bytes
        return 0

    @property
    def predicted_savings(self) -> int:
        if self.recommendation == "neural" and self.mesh_resident_bytes and self.predicted_model_bytes:
            return self.mesh_resident_bytes - self.predicted_model_bytes
        return 0

    def to_dict(self) -> dict:
        return {**asdict(self), "saved_bytes": self.saved_bytes, "predicted_savings": self.predicted_savings,
                "saved_vs_alternative_bytes": self.saved_vs_alternative_bytes}


# ------------------------------------------------------------------------------------------------ discovery


# -------------------------------------------------------------------------------------------- the two tasks
def settings_key(mesh_sha256: str, spec: dict) -> str:
    """An asset's result folder name: the mesh's content and the settings asked for (a rerun with either changed
    trains again; a renamed or moved file does not)."""
    blob = json.dumps({"mesh": mesh_sha256, "settings": spec}, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def _worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def measure_asset(asset: dict, spec: dict) -> dict:
    """Ray task: measure one asset and decide (see the module docstring). Never raises: a failure is a row."""
    from ..geometry.exact import ExactTracer
    from ..geometry.texture_hold import hold_textures
    from ..neural.appearance import make_head
    from .trainings import mesh_identity
    from .weighing import weigh
    from ..planning.run_config import plan_run
    from ..rendering.render import orbit_cameras, png_bytes, render_reference

    t0 = time.perf_counter()
    out = {"name": asset["name"], "worker": _worker_id()}
    try:
        if asset.get("error"):
            raise ValueError(asset["error"])
        mesh = load_asset(asset["path"], asset["name"])
        run = plan_run(settings_from_request(spec), mesh)
        tracer = ExactTracer(mesh)  # the source's look is the reference; both sides store the held one
        mesh, _ = hold_textures(mesh, run.look.on_screen_px)
        a, weighing = weigh(mesh, run, tracer, make_head(mesh, run.look.head))  # the run's verdict, its look weighed
        thumb = render_reference(tracer, orbit_cameras(1)[0], THUMBNAIL_PX, THUMBNAIL_PX).display
        out.update(status="measured" if a.worth_compressing or run.decision.force else "not_worth",
                   triangles=mesh.n_triangles,
                   mesh_resident_bytes=a.resident["total"], draco_bytes=a.alternatives.draco11_bytes,
                   predicted_model_bytes=a.model_bytes, verdict=a.message, recommendation=a.recommendation,
                   key=settings_key(mesh_identity(mesh)["sha256"], spec), thumb=png_bytes(thumb),
                   compact_bytes=a.compact_bytes, texture_bytes=mesh.look.texture_bytes() if mesh.look else 0)
        out.update(_decimation_fields(mesh, a, weighing.decimator))
    except Exception as exc:  # a bad asset is a row with its error, never the end of the run
        out.update(status="failed", error=f"{type(exc).__name__}: {exc}")
    out["measure_seconds"] = round(time.perf_counter() - t0, 3)
    return out


def compress_asset(asset: dict, spec: dict) -> dict:
    """Ray task: train one asset's model, render its thumbnail; returns the file's bytes and the numbers. The
    training's decisions are the CLI's: a check or the final verdict that finds a measured decimation smaller at
    the model's own MSE keeps the mesh (status not_worth, with that decimation). Never raises for the asset's own
    failures."""
    from .. import kernels
    from .pipeline import compress_mesh
    from ..protocol.process import NotWorthCompressing
    from ..rendering.render import orbit_cameras
    from .result_bundle import View, make_bundle

    t0 = time.perf_counter()
    out = {"name": asset["name"], "worker": _worker_id()}
    try:
        import torch

        torch.set_num_threads(max(1, int(os.environ.get("OMP_NUM_THREADS", torch.get_num_threads()))))
        kernels.keep_freed_memory()
        mesh = load_asset(asset["path"], asset["name"])
        res = compress_mesh(mesh, settings_from_request(spec), started_at=t0)  # the wall counts its loading
        final = res.decisions.final
        bundle = make_bundle(res, mesh, View(orbit_cameras(1)[0], THUMBNAIL_PX, THUMBNAIL_PX),
                             ("model", "report", "preview"))
        out.update(status="done", bundle_files=bundle.files, summary=bundle.report, thumb=bundle.files["preview"],
                   model_bytes=res.file_bytes, model_resident_bytes=sum(res.model.resident_bytes().values()),
                   mse=res.quality.mse if res.quality else None, iou=res.quality.silhouette_iou if res.quality else None,
                   train_seconds=round(res.training.seconds, 2),
                   alternative_bytes=_rounded(final.alternative_bytes) if final else None,
                   verdict=final.message if final else None)
    except NotWorthCompressing as exc:  # a measurement during or after training kept the mesh
        a = exc.assessment
        out.update(status="not_worth", verdict=a.message, recommendation=a.recommendation,
                   **_decimation_fields(mesh, a, exc.decimator))
    except Exception as exc:
        out.update(status="failed", error=f"{type(exc).__name__}: {exc}")
    out["task_seconds"] = round(time.perf_counter() - t0, 2)
    return out


def _rounded(x) -> int | None:
    return None if x is None else int(round(x))


def _decimation_fields(mesh, assessment, decimator=None) -> dict:
    """The row's fields for the decimation a verdict keeps instead of a model (none when it keeps no decimation):
    the mesh that wins as a file the head writes (workers may not share its disk)."""
    from .alternatives import winning_decimation
    from .kept_mesh import counted_compact_bytes, kept_mesh_files

    if assessment.recommendation != "decimate":
        return {}
    files = kept_mesh_files(mesh, assessment, winning_decimation(mesh, assessment, decimator))
    return {"decimation_triangles": assessment.alternatives.decimation.triangles, "decimation_files": files,
            "decimation_compact_bytes": counted_compact_bytes(assessment)}


# ------------------------------------------------------------------------------------------------ the driver
def _safe(name: str) -> str:
    import re

    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)[:120]


def _cached(out: Path, key: str) -> dict | None:
    """The finished result in OUT/assets/KEY, or None (missing, damaged or incomplete: trained again)."""
    folder = out / "assets" / key
    try:
        result = json.loads((folder / "result.json").read_text())
        name = result["files"]["model"]
        if not isinstance(name, str) or Path(name).name != name or not name.endswith(".nbvh"):
            return None  # a result names its model inside its own folder; anything else is not ours
        model = folder / name
        return result if model.is_file() and model.stat().st_size == result["model_bytes"] else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


class _Library:
    """The driver's state: the rows, where results go, and the report written after every change."""

    def __init__(self, out: Path, assets: list[Asset], spec: dict, events: EventSink, info: dict):
        from ..protocol.outputs import write_atomic

        self.out, self.spec, self.events, self.info = out, spec, events, info
        self.assets = {a.name: a for a in assets}
        self.rows = {a.name: Row(name=a.name, source=a.source) for a in assets}
        self.copies: dict[str, list[str]] = {}  # row trained -> rows with the same mesh and settings
        self.write_atomic = write_atomic
        (out / "thumbs").mkdir(parents=True, exist_ok=True)

    def thumb(self, name: str, kind: str, png: bytes | None) -> str | None:
        if not png:
            return None
        file = f"{_safe(name)}.{kind}.png"
        self.write_atomic(self.out / "thumbs" / file, png)
        return file

    def measured(self, name: str, r: dict) -> None:
        row = self.rows[name]
        for k in ("status", "error", "triangles", "mesh_resident_bytes", "draco_bytes", "predicted_model_bytes",
                  "verdict", "recommendation", "key", "measure_seconds", "worker", "compact_bytes", "texture_bytes",
                  "decimation_triangles", "decimation_compact_bytes"):
            if k in r:
                setattr(row, k, r[k])
        if "thumb" in r:
            row.thumb_original = self.thumb(name, "original", r.get("thumb"))
        for suffix, data in (r.get("decimation_files") or {}).items():  # the CLI's files (kept_mesh), written here
            from ..protocol.outputs import write_atomic
            from .kept_mesh import COMPACT, GLB

            path = self.out / "assets" / row.key / f"{_safe(name)}{suffix}"
            path.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(path, data)
            row.files[{GLB: "decimation", COMPACT: "decimation_compact"}[suffix]] = str(path.relative_to(self.out))
            if suffix == COMPACT:
                row.decimation_written_bytes = len(data)
        self.events(wire.asset(phase="measure", **_event_fields(row)))

    def trained(self, name: str, r: dict) -> None:
        from .result_bundle import Bundle, bundle_paths, write_bundle

        row = self.rows[name]
        row.worker, row.status, row.error = r.get("worker"), r["status"], r.get("error")
        if r["status"] == "not_worth":  # kept as a mesh by a measurement during or after training
            self.measured(name, r)
        if r["status"] == "done":
            folder = self.out / "assets" / row.key
            folder.mkdir(parents=True, exist_ok=True)
            model = f"{_safe(name)}.nbvh"
            for k in ("model_bytes", "model_resident_bytes", "mse", "iou", "train_seconds", "alternative_bytes",
                      "verdict"):
                setattr(row, k, r.get(k))
            row.thumb_neural = self.thumb(name, "neural", r.get("thumb"))
            row.files = {"model": str(Path("assets") / row.key / model)}
            record = {**row.to_dict(), "files": {"model": model}, "summary": r.get("summary")}
            # The asset's result bundle and its library record appear together; result.json marks it finished.
            write_bundle(bundle_paths(folder / model, ("model", "report", "preview")),
                         Bundle(r["bundle_files"], r.get("summary") or {}),
                         also={folder / "result.json": json.dumps(record, indent=2, default=str).encode()})
        self.events(wire.asset(phase="train", **_event_fields(row)))
        for other in self.copies.get(name, []):
            if row.status == "done":
                self.from_cache(other, {**row.to_dict(), "files": {"model": Path(row.files["model"]).name}})
            else:
                self.rows[other].status, self.rows[other].error = row.status, row.error
            self.events(wire.asset(phase="train", **_event_fields(self.rows[other])))
        self.write_report()

    def from_cache(self, name: str, record: dict) -> None:
        row = self.rows[name]
        for k in ("model_bytes", "model_resident_bytes", "mse", "iou", "train_seconds", "worker", "thumb_neural",
                  "alternative_bytes", "verdict"):
            setattr(row, k, record.get(k))
        row.status = "cached"
        row.files = {"model": str(Path("assets") / row.key / record["files"]["model"])}

    def write_report(self, final: bool = False) -> dict:
        from .library_report import write_report

        return write_report(self.out, [self.rows[n] for n in self.rows], {**self.info, "final": final})


def _event_fields(row: Row) -> dict:
    return {k: v for k, v in row.to_dict().items() if k in ("name", "status", "error", "triangles",
                                                             "mesh_resident_bytes", "model_bytes", "mse",
                                                             "saved_bytes", "predicted_savings")}


def run_batch(library: str | os.PathLike, out: str | os.PathLike, spec: dict, events: EventSink = null_sink,
              should_cancel: Callable[[], bool] = lambda: False, address: str | None = None,
              num_cpus: int | None = None, measure_only: bool = False, blender: str | None = None) -> dict:
    """Run the whole library (see the module docstring). spec: preset name + Settings overrides, as the job
    request's "settings". Returns the report's summary (paths, totals, rows). Raises process.Cancelled (the
    report then holds what finished), ValueError for a LIBRARY that lists nothing."""
    from ..protocol.outputs import OutputLock

    require_ray()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with OutputLock(out / "report.html"):  # one batch per output folder at a time
        return _run_locked(Path(library), out, spec, events, should_cancel, address, num_cpus, measure_only, blender)


def _run_locked(library: Path, out: Path, spec: dict, events: EventSink, should_cancel, address, num_cpus,
                measure_only: bool, blender: str | None) -> dict:
    import ray

    t0 = time.time()
    assets = discover(library, out / ".work", blender)
    started = start_ray(address, num_cpus)
    try:
        cluster = cluster_info()
        lib = _Library(out, assets, spec, events, {"library": str(library), "settings": spec, "cluster": cluster,
                                                   "started": time.strftime("%Y-%m-%dT%H:%M:%S")})
        events(wire.phase(phase="measure", message=f"{len(assets)} assets on {cluster['nodes']} node(s),"
                                                   f" {cluster['CPU']:g} CPUs: measuring"))
        run_tasks(ray.remote(measure_asset), [(a.name, (asdict(a), spec), {"num_cpus": 1}) for a in assets],
                   "measure", lib.measured, events, should_cancel)
        lib.info["measured_s"] = round(time.time() - t0, 1)
        lib.write_report()  # the first version: every verdict, before any training
        if not measure_only:
            _train_worth(lib, cluster, spec, events, should_cancel)
        lib.info["wall_s"] = round(time.time() - t0, 1)
        summary = lib.write_report(final=True)
    except BaseException:
        if "lib" in locals():
            for row in lib.rows.values():
                if row.status == "measured" and not measure_only:  # measured = worth it, or forced
                    row.status = "cancelled"
            lib.info["wall_s"] = round(time.time() - t0, 1)
            lib.write_report(final=True)
        raise
    finally:
        if started:
            ray.shutdown()
    events(wire.result(report=summary["html"], json=summary["json"], csv=summary["csv"], totals=summary["totals"]))
    return summary


def _train_worth(lib: _Library, cluster: dict, spec: dict, events: EventSink, should_cancel) -> None:
    """The training phase: worth assets, largest predicted savings first; finished ones (by KEY) are reused."""
    import ray

    worth = sorted((r for r in lib.rows.values() if r.status == "measured"),
                   key=lambda r: -r.predicted_savings)
    jobs, first_of_key = [], {}
    for row in worth:
        record = _cached(lib.out, row.key)
        if record is not None:
            lib.from_cache(row.name, record)
        elif row.key in first_of_key:  # the same mesh twice in the library: trained once, shared
            lib.copies.setdefault(first_of_key[row.key], []).append(row.name)
        else:
            first_of_key[row.key] = row.name
            jobs.append((row.name, (asdict(lib.assets[row.name]), spec), task_resources(row.triangles, cluster)))
    if len(jobs) < len(worth) - sum(len(v) for v in lib.copies.values()):
        events(wire.phase(phase="train", message=f"{len(worth) - len(jobs)} assets already finished "
                                                 "in an earlier run (same mesh and settings): kept"))
    events(wire.phase(phase="train", message=f"training {len(jobs)} of {len(lib.rows)} assets "
                                             "(the ones worth compressing), largest savings first"))
    run_tasks(ray.remote(compress_asset), jobs, "train", lib.trained, events, should_cancel)
