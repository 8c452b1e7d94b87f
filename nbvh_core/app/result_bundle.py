"""One finished compression as every front end writes it (the CLI's `compress`, the add-on's job, a library batch):
the same files, the same report, made in one place.

Files, beside the model (STEM = the model's path without `.nbvh`):
  STEM.nbvh            the model
  STEM.report.json     the report (`report`): sizes by component, the mesh's resident bytes, quality, training,
                       settings, the verdict, the files
  STEM.preview.png     the model rendered (its look, when it has one) from the camera
  STEM.reference.png   the mesh from the same camera, for side-by-side comparison
  STEM.points.npy      (P, 6) or (P, 9) proxy points from the model's own hits (`make_proxy_points`), when
                       asked for

`make_bundle` returns the files as bytes (pure: a Ray worker makes them, the driver writes them); `write_bundle`
stages them and renames them into place together (`outputs.OutputSet`): all of a result or, on any failure, the
previous one as it was.
"""
from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROLES = ("model", "report", "preview", "reference", "points")
_SUFFIX = {"model": ".nbvh", "report": ".report.json", "preview": ".preview.png", "reference": ".reference.png",
           "points": ".points.npy"}


def bundle_paths(model_path: str | Path, roles: tuple[str, ...] = ROLES) -> dict[str, Path]:
    """{role: path} of a bundle whose model is `model_path` (the other files share its stem)."""
    model_path = Path(model_path)
    stem = model_path.with_suffix("") if model_path.suffix == ".nbvh" else model_path
    return {role: model_path if role == "model" else Path(f"{stem}{_SUFFIX[role]}") for role in roles}


@dataclass
class View:
    """Where the previews look from: a render.Camera in the unit box and the image size in pixels."""

    camera: object
    width: int = 256
    height: int = 256


@dataclass
class Bundle:
    """The files of one result as bytes, by role (`ROLES`), and its report as a dict (also in files['report'])."""

    files: dict[str, bytes]
    report: dict = field(default_factory=dict)


def report(result, mesh, extra: dict | None = None) -> dict:
    """The one report of a result (`pipeline.CompressResult` or a loaded model's stand-in with `summary()`):
    its summary, the mesh's resident bytes, the asset's texture bytes, plus `extra` (the front end's own fields)."""
    from ..planning.sizing import mesh_resident_bytes

    out = result.summary()
    out["mesh_resident_bytes"] = (result.assessment.resident if result.assessment is not None
                                  else mesh_resident_bytes(mesh))
    out["texture_bytes"] = mesh.look.texture_bytes() if mesh.look else 0
    out.update(extra or {})
    return out


def make_bundle(result, mesh, view: View, roles: tuple[str, ...] = ROLES, *, proxy_points: int = 0,
                seed: int = 0, extra: dict | None = None) -> Bundle:
    """The bundle's files for `roles` ('points' only with proxy_points > 0; 'model' from result.data). The reference
    image traces the result's own ExactTracer (one is made from `mesh` for a loaded model, which has none)."""
    from ..geometry.exact import ExactTracer
    from ..rendering.render import png_bytes, render_neural, render_reference

    files: dict[str, bytes] = {}
    if "model" in roles:
        files["model"] = result.data
    if "preview" in roles:
        files["preview"] = png_bytes(render_neural(result.model, view.camera, view.width, view.height).display)
    if "reference" in roles:
        tracer = result.tracer or ExactTracer(mesh)
        files["reference"] = png_bytes(render_reference(tracer, view.camera, view.width, view.height).display)
    if "points" in roles and proxy_points > 0:
        buf = io.BytesIO()
        np.save(buf, make_proxy_points(result.model, proxy_points, seed=seed))
        files["points"] = buf.getvalue()
    rep = report(result, mesh, extra)
    if "report" in roles:
        files["report"] = json.dumps(rep, indent=2, default=str).encode()
    return Bundle(files, rep)


def write_bundle(paths: dict[str, Path], bundle: Bundle, also: dict[Path, bytes] | None = None,
                 should_cancel=None) -> None:
    """Write the bundle's files to `paths` (by role; roles without a path are not written) and `also` (more files
    that belong to the same result) together. should_cancel() True before the rename: nothing is written and
    process.Cancelled is raised."""
    from ..protocol.outputs import OutputSet
    from ..protocol.process import Cancelled

    staged = OutputSet()
    for role, data in bundle.files.items():
        if role in paths:
            staged.stage(Path(paths[role]), data)
    for path, data in (also or {}).items():
        staged.stage(Path(path), data)
    if should_cancel is not None and should_cancel():
        staged.discard()
        raise Cancelled("cancelled before the results were written")
    staged.commit()


def make_proxy_points(model, n_points: int, seed: int = 0) -> np.ndarray:
    """(P, 6) float32 points + unit normals on the model's surface, in the mesh's original coordinates; (P, 9)
    with each point's linear RGB albedo (the model's look) when the model carries materials.

    Rays from a sphere around the asset toward random points of its box; every predicted hit is a point
    (P <= n_points). Computed from the neural model only (the mesh is not used), so the proxy shows what
    the model learned.
    """
    import torch

    from ..training.rays import RayConfig, sample_rays

    rng = np.random.default_rng(seed)
    lo, hi = model.nodes["lo"][0], model.nodes["hi"][0]
    pts = []
    have = 0
    for _ in range(8):
        o, d = sample_rays(lo, hi, max(2 * (n_points - have), 1024), rng, RayConfig(outside_fraction=1.0))
        q = model.query(torch.from_numpy(o), torch.from_numpy(d))
        hit = q.hit.cpu().numpy()
        p = o[hit] + q.t.cpu().numpy()[hit, None] * d[hit]
        n = q.normal.cpu().numpy()[hit]
        colour = model.albedo_at(np.clip(p, 0.0, 1.0))  # None for a bare shape
        pts.append(np.concatenate((model.transform.to_original(p), n) + (() if colour is None else (colour,)),
                                  axis=1))
        have += int(hit.sum())
        if have >= n_points:
            break
    out = np.concatenate(pts)[:n_points] if pts else np.zeros((0, 9 if model.materials else 6))
    return out.astype(np.float32)


class LoadedResult:
    """The parts of pipeline.CompressResult a loaded (not trained) model can offer."""

    def __init__(self, model, info, path: str):
        from ..training.train import TrainResult

        self.model = model
        self.tracer = None  # no mesh was traced for a loaded model
        self.assessment = None
        self.file_bytes = info.total_bytes
        self.components = info.components
        meta = info.metadata
        tr = meta.get("training") or {}
        self.training = TrainResult(steps=tr.get("steps", 0), seconds=tr.get("seconds", 0.0), samples=tr.get("samples", 0),
                                    samples_per_s=tr.get("samples_per_s", 0.0), final_loss=tr.get("final_loss", 0.0),
                                    device=tr.get("device", "?"))
        self._summary = {"path": path, "file_bytes": info.total_bytes, "components": info.components,
                         "quality": meta.get("quality"), "training": tr, "settings": meta.get("settings"),
                         "seconds": {}, "why": "loaded from file", "target_met": meta.get("target_met")}

    def summary(self) -> dict:
        return dict(self._summary)
