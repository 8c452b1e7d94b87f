"""The verdict before training: is a model of this size worth training at all, against the whole mesh and the
smallest measured decimation that meets the target, each held in the layout the run weighs against? A rule on
measured and exact byte counts (`app.alternatives.assess` measures them); the smaller of the alternatives wins."""
from __future__ import annotations

import dataclasses

from .records import Assessment, FinalVerdict, MeshMeasure

#: What the verdict recommends: train the model, keep the mesh as it is, or ship the measured decimation.
RECOMMENDATIONS = ("neural", "mesh", "decimate")


def held_text(layout: str, plain: int, compact: int) -> str:
    """'31,322 B as a compact mesh (135,392 B as a plain ray tracer holds it)', the verdict's layout first."""
    a, b = f"{compact:,} B as a compact mesh", f"{plain:,} B as a plain ray tracer holds it"
    return f"{a} ({b})" if layout == "compact" else f"{b} ({a})"


def verdict_before_training(model: int, triangles: int, resident: int, compact: int,
                            decimation: MeshMeasure | None, draco: int | None, layout: str) -> tuple[str, str]:
    """(recommendation, one line for people) for a model file of `model` bytes against the whole mesh of
    `triangles` (`resident`: as a plain ray tracer holds it; `compact`: the compact ray-traceable mesh; both with
    the asset's look) and `decimation` (None, or the smallest measured one meeting the target, its bytes with the
    look: `MeshMeasure.with_look`), held in `layout` ('compact' or 'plain'). draco: the
    whole mesh's Draco 11-bit bytes (storage only; said beside). 'mesh' when the whole mesh is no larger than the
    model and no larger than the decimation; 'decimate' when the decimation is no larger than the model; else
    'neural' (a decimation is offered even when the whole mesh is also smaller: it is the least a user ships)."""
    def held(plain: int, comp: int) -> int:
        return comp if layout == "compact" else plain

    draco_text = f"; Draco 11-bit of the mesh: {draco:,} B for storage" if draco is not None else ""
    whole = held(resident, compact)
    whole_text = held_text(layout, resident, compact)
    dec_held = held(decimation.resident_bytes, decimation.compact_bytes) if decimation is not None else None
    if whole <= model and (dec_held is None or whole <= dec_held):
        return "mesh", (f"not worth compressing: the mesh ({triangles:,} triangles) is already no larger than this "
                        f"model (~{model:,} B): {whole_text}; keep the mesh, or ask for a smaller model "
                        f"(--budget-kb){draco_text}")
    if dec_held is not None and dec_held <= model:
        return "decimate", (f"not worth compressing: a decimation to {decimation.triangles:,} triangles meets the "
                            f"target (MSE {decimation.mse:.4g}) in "
                            f"{held_text(layout, decimation.resident_bytes, decimation.compact_bytes)}, no more "
                            f"than this model (~{model:,} B; the full mesh: {whole_text}){draco_text}")
    msg = f"model ~{model:,} B vs the mesh {whole_text}: {whole / model:.1f}x smaller"
    if decimation is not None:
        msg += (f"; the smallest decimation meeting the target ({decimation.triangles:,} triangles) holds "
                f"{held_text(layout, decimation.resident_bytes, decimation.compact_bytes)}: "
                f"{dec_held / model:.2f}x the model")
    return "neural", msg + draco_text


def mesh_kept(assessment: Assessment, verdict: FinalVerdict | None, checks: list | tuple = ()) -> Assessment:
    """The assessment after a decision taken on measurements kept the mesh (a training check's, or the final
    verdict's, `verdict`; None: the check kept the whole mesh): it recommends the measured decimation that verdict
    names (or the whole mesh) and carries the verdict's message and record, and the training's `checks`
    (`CheckDecision`s) that led there."""
    alt = dataclasses.replace(assessment.alternatives)
    rec = "mesh"
    if verdict is not None and verdict.decimation is not None and verdict.decimation.requested_triangles:
        rec = "decimate"
        alt.decimation = alt.tried(verdict.decimation.requested_triangles) or alt.decimation
    return dataclasses.replace(assessment, worth_compressing=False, recommendation=rec,
                               message=verdict.message if verdict is not None else assessment.message,
                               alternatives=alt, final=verdict, checks=list(checks))
