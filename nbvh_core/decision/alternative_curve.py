"""The alternative a model must beat, as a curve: compact-mesh bytes against image MSE, measured once per run on
the decimations `app.alternatives.alternatives` tried and the whole mesh, each scored by the run's own metric.

Between two measured points the curve is the straight line in log bytes / log MSE (decimation sizes 4x apart; a
prediction that flatters the alternative next to the whole mesh, whose MSE is only the grid's: a verdict that
rests on it measures the decimation it predicts first, `final_verdict`);
below the best measured MSE (the whole mesh's grid error) no alternative exists; above the loosest, the smallest
measured decimation stands for it (a smaller one may exist: this flatters the model only where models are
tiny)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from .records import Alternatives, MeshMeasure


@dataclass(frozen=True)
class CurvePoint:
    """bytes: the compact mesh's exact bytes; mse: its measured MSE on this curve's views; triangles; requested:
    the decimation count asked for (None: the whole mesh); colour_mse: for an asset with a look, the colour MSE of
    the mesh as it ships with its look on this curve's views (None: no look, or not measured)."""

    bytes: int
    mse: float
    triangles: int
    requested: int | None
    colour_mse: float | None = None

    def meets(self, mse: float, colour_mse: float | None = None) -> bool:
        """Whether this mesh stands in for a model of geometry `mse` and, for an asset with a look, `colour_mse`: at
        least as good on every measure the model has (a point whose colour was not measured cannot stand in for a
        model whose colour was)."""
        if self.mse > mse:
            return False
        return colour_mse is None or (self.colour_mse is not None and self.colour_mse <= colour_mse)

    @classmethod
    def from_entry(cls, entry: MeshMeasure, held_out: bool = False) -> "CurvePoint":
        """A measured decimation or the whole mesh (`app.alternatives.decimation_entry`, `whole_mesh_entry`) as a
        point: its bytes are the compact mesh and what it needs to carry the asset's look
        (`app.alternatives.look_carried_bytes`), its MSE on the check views or (held_out) the held-out views."""
        mse = entry.compact_mse_held_out if held_out else entry.compact_mse
        colour = entry.colour_mse_held_out if held_out else entry.colour_mse
        return cls(int(entry.compact_bytes) + int(entry.look_bytes or 0), float(mse), int(entry.triangles),
                   entry.requested_triangles, None if colour is None else float(colour))


def _envelope(points: list[CurvePoint]) -> list[CurvePoint]:
    """By bytes ascending, each point that is better than every smaller one (measured, finite)."""
    out: list[CurvePoint] = []
    for p in sorted((p for p in points if math.isfinite(p.mse) and p.bytes > 0), key=lambda p: (p.bytes, p.mse)):
        if not out or p.mse < out[-1].mse:
            out.append(p)
    return out


class AlternativeCurve:
    """The lower envelope of measured (bytes, MSE) points: no point kept is beaten in both by another."""

    def __init__(self, points: list[CurvePoint]):
        self.points = _envelope(points)

    @classmethod
    def from_alternatives(cls, alt: Alternatives, held_out: bool = False) -> "AlternativeCurve | None":
        """The curve of `app.alternatives.alternatives`'s result on its check views, or (held_out) on the held-out
        views; None when no decimation was measured."""
        def measured(e: MeshMeasure | None) -> bool:
            mse = None if e is None else e.compact_mse_held_out if held_out else e.compact_mse
            return mse is not None and e.compact_bytes is not None

        entries = [*alt.decimations_tried, alt.mesh_compact]
        curve = cls([CurvePoint.from_entry(e, held_out) for e in entries if measured(e)])
        return curve if curve.points else None

    def bytes_at(self, mse: float) -> float:
        """The alternative's bytes to reach `mse` (inf: nothing measured reaches it)."""
        pts = self.points
        if mse >= pts[0].mse:
            return float(pts[0].bytes)
        for lo, hi in zip(pts, pts[1:]):  # lo: fewer bytes, higher MSE
            if hi.mse <= mse <= lo.mse:
                w = math.log(lo.mse / mse) / math.log(lo.mse / hi.mse) if lo.mse > hi.mse else 1.0
                return math.exp(math.log(lo.bytes) + w * math.log(hi.bytes / lo.bytes))
        return math.inf

    def triangles_at(self, mse: float) -> int | None:
        """The decimation count the curve expects to reach `mse` (log-log between the measured points), or None
        outside the decimations measured."""
        pts = self.points  # the whole mesh (requested None) bounds the last gap by its triangle count
        for lo, hi in zip(pts, pts[1:]):
            if hi.mse <= mse <= lo.mse and lo.mse > hi.mse:
                w = math.log(lo.mse / mse) / math.log(lo.mse / hi.mse)
                a, b = lo.requested or lo.triangles, hi.requested or hi.triangles
                count = int(round(math.exp(math.log(a) + w * math.log(b / a))))
                return count if count < (hi.triangles if hi.requested is None else math.inf) else None
        return None

    def add(self, point: CurvePoint) -> None:
        """One more measured point (a decimation measured to settle a verdict)."""
        self.points = _envelope(self.points + [point])

    def cheapest_meeting(self, mse: float, colour_mse: float | None = None) -> CurvePoint | None:
        """The smallest measured point that stands in for a model of `mse` (and, with a look, `colour_mse`:
        `CurvePoint.meets`): what can be shipped instead, or None."""
        return next((p for p in self.points if p.meets(mse, colour_mse)), None)

    def to_dict(self) -> list[dict]:
        return [{"bytes": p.bytes, "mse": p.mse, "triangles": p.triangles, "requested": p.requested,
                 "colour_mse": p.colour_mse} for p in self.points]
