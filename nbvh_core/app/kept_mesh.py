"""The files a user gets when the verdict keeps a mesh, the same in every path (CLI, library batch, the add-on's
job): the winning decimation as NAME.glb (its materials, slots, texture coordinates and textures, in the asset's
units: what Blender and engines open), and the winner (the decimation or the whole mesh) as NAME.compact.cmsh, the
compact ray-traceable mesh whose bytes the verdict counted, byte for byte."""
from __future__ import annotations

from ..decision.records import Assessment
from ..geometry.mesh import Mesh

#: suffix of each kept file, after the asset's name
GLB, COMPACT = ".glb", ".compact.cmsh"


def kept_mesh_files(mesh: Mesh, assessment: Assessment, dec: Mesh | None) -> dict[str, bytes]:
    """suffix -> bytes of each file the kept mesh is written as ({} when the verdict ships a model). dec: the
    decimation the verdict keeps, rebuilt exactly as measured (`alternatives.winning_decimation`: deterministic; None
    when it keeps none), built once by the caller for every use."""
    from ..geometry.compact_mesh import encode_compact, in_original_units
    from ..geometry.glb import encode_glb

    files: dict[str, bytes] = {}
    if dec is not None:
        files[GLB] = encode_glb(dec)
    if assessment.layout == "compact" and assessment.recommendation in ("mesh", "decimate"):
        winner = dec if dec is not None else mesh  # encoded as the verdict counted it, placed in original units
        files[COMPACT] = in_original_units(encode_compact(winner), winner.transform.scale, winner.transform.offset)
    return files


def counted_compact_bytes(assessment: Assessment) -> int | None:
    """The compact mesh's bytes the verdict counted for what it keeps (without the look's bytes, which the .glb
    carries), or None when it keeps no mesh."""
    kept = {"decimate": assessment.alternatives.decimation,
            "mesh": assessment.alternatives.mesh_compact}.get(assessment.recommendation)
    return None if kept is None else int(kept.compact_bytes)


def kept_quality(mesh: Mesh, dec: Mesh | None) -> dict | None:
    """The kept decimation `dec` with its look, scored against `mesh` on the held-out views (the run's metric: 16 at
    256 px): image MSE, colour MSE (linear albedo, where the asset has a look) and FLIP of the displayed images
    (what people see). None when no decimation is kept."""
    from ..geometry.exact import ExactTracer
    from ..rendering.metrics import MetricConfig, ViewScorer
    from ..rendering.render import render_reference

    if dec is None:
        return None
    metric = MetricConfig()
    scorer = ViewScorer(ExactTracer(mesh), mesh.transform, metric.views, metric.resolution, held_out=True)
    kept = ExactTracer(dec)
    q, _ = scorer.score(lambda cam, w, h: render_reference(kept, cam, w, h), flip=True)
    return {"mse": q.mse, "colour_mse": q.colour_mse, "flip": q.flip, "views": scorer.name}
