"""What a user could ship instead of a model, measured, and the verdict before training.

* **The alternative** (`alternatives`): decimations of the mesh (`geometry.decimation.Decimator`: meshoptimizer,
  the look kept, one chain per mesh) up to the smallest that meets the quality target, each held as the compact
  ray-traceable mesh (`geometry.compact_mesh`: exact bytes) and scored by the run's metric on the check and the
  held-out views; the whole mesh as a compact mesh; Draco's size of the mesh (storage alone). The plan's progress,
  Cancel points and time share come in through `tick` (`weighing.PlanProgress`).
* **The verdict before training** (`assess`): when the mesh as it is, or the smallest decimation of it that meets
  the target, is no larger than the model held as a compact ray-traceable mesh (or, with mesh_layout "plain", as a
  plain ray tracer holds it), compressing is not worth it; the result says so with all sizes (a user can still
  force the model).
"""
from __future__ import annotations

import math
import time

from ..decision.config import DecisionConfig
from ..decision.records import Alternatives, Assessment, MeshMeasure
from ..decision.verdict import verdict_before_training
from ..geometry.bvh import FullTree, SharedTree, build_full_tree, tree_of
from ..geometry.decimation import CHAIN_LEVELS, Decimator, decimate, simplifier_missing
from ..geometry.mesh import Mesh
from ..protocol.memory import return_free_memory
from ..planning.sizing import mesh_resident_bytes


#: Decimation sizes tried first (triangles, x4 apart; those >= DECIMATE_MAX_SHARE of the mesh are not tried), then
#: DECIMATE_REFINE bisections (in log space) between the last that missed and the first that met: the decimation
#: reported is within 2^(2 / 2^DECIMATE_REFINE) = 1.19x of the smallest that meets the target. One size x4 above the
#: first that met is measured too, so the alternative's curve (`decision.alternative_curve`) reaches models that
#: beat the target by measurement, not by extrapolation. The ladder is the decimation chain's levels up to ~1M: each
#: count measured is a level the smaller ones are simplified from.
DECIMATE_COUNTS = CHAIN_LEVELS[:7]
DECIMATE_MAX_SHARE = 0.7
DECIMATE_REFINE = 3


def look_carried_bytes(mesh: Mesh, n_vertices: int, n_triangles: int) -> int:
    """The bytes a mesh of `n_vertices` / `n_triangles` (the asset or a decimation of it) needs to carry the asset's
    look, as a compact mesh would hold it: the same slot images the model stores (`Material.stored_image`),
    16-bit texture coordinates per vertex when images are sampled, and a slot id per triangle (ceil(log2 slots)
    bits) when there are several slots. The compact mesh written is geometry only; the .glb written beside it
    carries the look (`kept_mesh.kept_mesh_files`). 0 for a bare shape."""
    look = mesh.look
    if look is None:
        return 0
    from ..neural.quantize import StorageConfig
    from ..storage.layout import look_stored_bytes

    textures = look_stored_bytes(None, look.materials, StorageConfig())["textures"]  # each image encoded once
    uv = 4 * n_vertices if look.textured else 0
    slots = math.ceil(n_triangles * math.ceil(math.log2(look.n_slots)) / 8) if look.n_slots > 1 else 0
    return int(textures + uv + slots)


def decimation_entry(mesh: Mesh, count: int, checks, held_out, draco,
                     decimator: Decimator | None = None) -> MeshMeasure:
    """One point of the alternative: the decimation to ~`count` triangles (`decimator`, the mesh's
    `geometry.decimation.Decimator`: one chain for every point; else one is made), plainly and as a compact mesh
    (exact bytes; the decoded compact mesh scored on the check views and, when given, the held-out views)."""
    from ..geometry.compact_mesh import compact_mesh

    dec = (decimator or Decimator(mesh))(count)
    if dec.n_triangles == 0:
        return MeshMeasure(0, count, mse=math.inf, compact_mse=math.inf)
    tree = build_full_tree(dec)  # one tree for the resident count and the compact layout's clusters
    nbytes, decoded = compact_mesh(dec, tree)
    as_shipped = checks.score_mesh(dec)  # with its look, when it has one: the checks weigh its colour too
    entry = MeshMeasure(dec.n_triangles, count, mse=as_shipped.mse,
                        resident_bytes=mesh_resident_bytes(dec, tree)["total"], compact_bytes=nbytes,
                        look_bytes=look_carried_bytes(mesh, dec.n_vertices, dec.n_triangles),
                        compact_mse=checks.score_mesh(decoded).mse,
                        colour_mse=as_shipped.colour_mse)  # None for a bare shape
    if held_out is not None:
        entry.compact_mse_held_out = held_out.score_mesh(decoded).mse
        entry.colour_mse_held_out = _colour_mse(dec, held_out)
    if draco is not None:
        entry.draco11_bytes = _draco_bytes(dec, draco)
    return entry


def alternatives(mesh: Mesh, target_mse: float | None, checks=None, held_out=None, tree=None,
                 decimator: Decimator | None = None, tick=None) -> Alternatives:
    """What a user could ship instead, measured: decimations (`geometry.decimation.decimate`: meshoptimizer, the look
    kept) up to the smallest whose image MSE meets `target_mse` (see DECIMATE_COUNTS), each with its resident and
    compact-mesh bytes and the compact mesh's MSE, scored by the run's own metric: `checks` (a
    rendering.metrics.ViewScorer: the training checks' views) and `held_out` (the final evaluation's); the whole
    mesh as a compact mesh ('mesh_compact'; `tree`: its `bvh.shared_tree` when the caller has one), scored when
    the plan's share allows; Draco (11-bit, storage bytes) of the mesh, last.
    Missing optional packages give a note instead of numbers. With a target, `checks` is required. decimator:
    the mesh's `Decimator` (its chain serves later points too), else one is made. tick(message, planned): called
    before each measurement (`planned`: the most it may take in all; progress, and a Cancel point: it may raise)."""
    out = Alternatives()
    try:
        import DracoPy
    except ImportError:
        DracoPy = None
        out.add_note("DracoPy not installed: no Draco sizes")
    if target_mse is None:
        if DracoPy is not None:
            out.draco11_bytes = _draco_bytes(mesh, DracoPy)
        return out
    missing = simplifier_missing()
    if missing:  # said, not silent: the verdict then weighs no decimation, and the report says why
        out.add_note(missing)
        out.no_alternative = missing
        return out
    out.metric = checks.name
    tried: dict[int, MeshMeasure] = {}
    decimator = decimator or Decimator(mesh)

    counts = [c for c in DECIMATE_COUNTS if c < mesh.n_triangles * DECIMATE_MAX_SHARE]
    planned = len(counts) + DECIMATE_REFINE + 4  # the ladder, the top, the refinements, one above, the whole mesh,
    # Draco

    over = getattr(tick, "over_budget", lambda seconds=0.0: False)
    rate: list[float] = []  # the last measurement's seconds per triangle read (simplified, encoded, scored)

    def work(count: int) -> int:
        return decimator.pending_triangles(count) + count

    def measure(count: int) -> MeshMeasure:
        if tick is not None:
            tick(f"decimation to {count:,} triangles", planned)
        triangles, t = work(count), time.perf_counter()
        tried[count] = decimation_entry(mesh, count, checks, held_out, DracoPy, decimator)
        return_free_memory()  # what the measurement freed: the next one (or the tree) is not built on top of it
        rate[:] = [(time.perf_counter() - t) / triangles]
        if len(tried) == 1:
            _tree_after_top_pass(decimator, tree)
        return tried[count]

    def would_overrun(count: int) -> bool:
        """Past the share, or past it by the end of this measurement, predicted at the last one's rate: one pass
        over a heavy mesh can take longer than the whole share (the 10M lattice's 7M-triangle point: 53 s)."""
        return over(rate[0] * work(count) if rate else 0.0)

    met, skipped = _smallest_meeting(counts, int(mesh.n_triangles * DECIMATE_MAX_SHARE), measure,
                                     lambda entry: entry.meets(target_mse), would_overrun)
    if met is not None:
        out.decimation = tried[met]
    out.decimations_tried = [tried[c] for c in sorted(tried)]
    decimator.drop_mesh_corners()  # rebuilt if a later point needs them; not resident with the whole mesh's tree
    if tick is not None:
        tick(f"the whole mesh ({mesh.n_triangles:,} triangles) as a compact mesh", planned)
    whole_s = rate[0] * mesh.n_triangles if rate else 0.0  # a measurement of the whole mesh, predicted
    scored = not over(whole_s)  # encoded, decoded, traced and scored twice
    if not scored:
        skipped.append("the whole mesh's image error (its bytes are exact)")
    out.mesh_compact = whole_mesh_entry(mesh, checks if scored else None, held_out if scored else None, tree)
    # Draco's size is said beside the verdict (storage alone), never weighed: measured last, and only in the plan's
    # share (the 10M-triangle lattice's took 9.2 s and 1 GiB at its peak on 2 cores).
    if DracoPy is not None and over(whole_s):
        skipped.append("Draco's size of the whole mesh (storage alone)")
    elif DracoPy is not None:
        if tick is not None:
            tick("Draco's size of the whole mesh", planned)
        out.draco11_bytes = _draco_bytes(mesh, DracoPy)
    if skipped:
        out.skipped = "past the plan's time budget (spent, or predicted to be), not measured: " + "; ".join(skipped)
    return out


def _tree_after_top_pass(decimator: Decimator, tree) -> None:
    """A `bvh.SharedTree` not built yet is built now, right after the decimation chain's top pass: that pass's memory
    is freed (they are never resident together), and inside the plan's share, so that the points after it are
    predicted with its time spent (~11 s at 10M triangles on 2 cores). The whole mesh's compact bytes always need
    it; the whole mesh's wedge corners go first (12 B per triangle, rebuilt if a later point needs them)."""
    if isinstance(tree, SharedTree):
        decimator.drop_mesh_corners()
        tree.get()


def _draco_bytes(mesh: Mesh, DracoPy) -> int:
    """Draco's bytes of the mesh at 11-bit positions (compression level 7): what storage alone would take."""
    return len(DracoPy.encode(mesh.vertices, mesh.faces, quantization_bits=11, compression_level=7))


def _smallest_meeting(counts: list[int], top: int, measure, meets, over) -> tuple[int | None, list[str]]:
    """The search over decimation counts: the ladder `counts` up to the first whose measurement meets the level (and
    the one above it), the gap up to `top` when none did, then DECIMATE_REFINE bisections. Past the plan's time
    budget (`over(count)`: spent, or would be by the end of that count's measurement) the optional points go first:
    the one above the level, the refinements, then the rest of the ladder; the run says what it skipped and decides
    on what it measured (the final verdict measures the decimation at the model's quality either way). Returns (the
    smallest count measured to meet, or None; what was skipped)."""
    skipped: list[str] = []
    missed, met = None, None
    for i, count in enumerate(counts):
        if over(count):
            skipped.append(f"the decimations from {count:,} triangles up")
            break
        if meets(measure(count)):
            met = count
            if i + 1 < len(counts):
                if over(counts[i + 1]):
                    skipped.append(f"the decimation to {counts[i + 1]:,} (one above the level)")
                else:
                    measure(counts[i + 1])
            break
        missed = count
    if met is None and not skipped and counts and counts[-1] < top:  # the gap up to the whole mesh
        if over(top):
            skipped.append(f"the decimation to {top:,} triangles")
        elif meets(measure(top)):
            missed, met = counts[-1], top
    if met is not None:
        lo = missed if missed is not None else max(met // 4, 4)
        for _ in range(DECIMATE_REFINE):
            mid = int(round(math.sqrt(lo * met)))
            if mid in (lo, met):
                break
            if over(mid):
                skipped.append(f"the refinement between {lo:,} and {met:,} triangles")
                break
            if meets(measure(mid)):
                met = mid
            else:
                lo = mid
    return met, skipped


def whole_mesh_entry(mesh: Mesh, checks, held_out, tree: "FullTree | SharedTree | None" = None) -> MeshMeasure:
    """The whole mesh as a compact mesh: its exact bytes and the grid's own error on both view sets (without
    `checks`: the bytes alone). tree: the mesh's tree when the caller has one (a `bvh.SharedTree` not built yet is
    built after the scoring: the decoded copy and its tracer are gone by then)."""
    from ..geometry.compact_mesh import compact_bytes, decoded_mesh

    entry = MeshMeasure(mesh.n_triangles, look_bytes=look_carried_bytes(mesh, mesh.n_vertices, mesh.n_triangles))
    if checks is not None:
        decoded = decoded_mesh(mesh)
        entry.compact_mse = checks.score_mesh(decoded).mse
        entry.colour_mse = _colour_mse(mesh, checks)
        if held_out is not None:
            entry.compact_mse_held_out = held_out.score_mesh(decoded).mse
            entry.colour_mse_held_out = _colour_mse(mesh, held_out)
        del decoded
        return_free_memory()
    entry.compact_bytes = compact_bytes(mesh, tree_of(mesh, tree))
    return entry


def _colour_mse(shipped: Mesh, views) -> float | None:
    """For an asset with a look: the colour MSE of the mesh as it ships with its look (the .glb: the decimation,
    its coordinates, slots and images) on `views` (the held-out views: what the final verdict weighs beside geometry;
    the check views: what the checks weigh); else None (nothing rendered)."""
    return views.score_mesh(shipped).colour_mse if shipped.look is not None else None


def winning_decimation(mesh: Mesh, assessment: "Assessment", decimator: Decimator | None = None) -> Mesh | None:
    """The decimation the verdict recommends instead of a model (rebuilt exactly: the simplifier is deterministic
    and moves no vertex; from the run's `decimator` when given, whose chain already holds the levels above it), or
    None when the verdict is not 'decimate'."""
    dec = assessment.alternatives.decimation
    if assessment.recommendation != "decimate" or dec is None:
        return None
    count = int(dec.requested_triangles)
    return decimator(count) if decimator is not None else decimate(mesh, count)


def assess(mesh: Mesh, model_bytes: int, decision: DecisionConfig, checks=None, held_out=None,
           look_bytes: int = 0, decimator: Decimator | None = None, tree=None, tick=None) -> Assessment:
    """Weigh a model of `model_bytes` (its file, `RunConfig.file_bytes`) against the mesh and, with a target MSE
    (`decision.target_mse`) and the run's view sets (`checks`, `held_out`: `rendering.metrics.view_sets`), against
    the smallest decimation that meets it, each held in `decision.mesh_layout` (see MESH_LAYOUTS; both layouts are
    reported): 'mesh' when the whole mesh is no larger than the model, 'decimate' when the decimation is not, else
    'neural'. Draco's size (storage only) is reported beside. look_bytes: what the model's file adds for the
    asset's look (appearance head and textures, `storage.layout.look_stored_bytes`), so the model is weighed as it will
    ship. decimator: the mesh's `Decimator` (the caller's, to measure more points later); tree: the mesh's
    `bvh.build_full_tree` when the caller has one; tick: `alternatives`'."""
    from ..geometry.compact_mesh import compact_bytes

    layout = decision.mesh_layout
    model = model_bytes + look_bytes
    tree = tree if tree is not None else SharedTree(mesh)  # built after the decimations (their memory peak)
    # The Draco size always (cheap: shows which tool wins for storage alone); decimations only with a target.
    alt = alternatives(mesh, decision.target_mse if checks is not None else None, checks, held_out, tree,
                       decimator, tick)
    resident_bytes = mesh_resident_bytes(mesh, tree_of(mesh, tree))
    resident = resident_bytes["total"]
    compact = (alt.mesh_compact.compact_bytes if alt.mesh_compact is not None
               else compact_bytes(mesh, tree_of(mesh, tree)))
    # A mesh weighed against the model carries the asset's look too (the model's head and images are in `model`).
    whole_look = look_carried_bytes(mesh, mesh.n_vertices, mesh.n_triangles)
    resident, compact = resident + whole_look, compact + whole_look
    dec = alt.decimation.with_look() if alt.decimation is not None else None
    rec, msg = verdict_before_training(model, mesh.n_triangles, resident, compact, dec, alt.draco11_bytes, layout)
    return Assessment(model_bytes=model, resident=resident_bytes, worth_compressing=rec == "neural", message=msg,
                      alternatives=alt, recommendation=rec, compact_bytes=compact, layout=layout)
