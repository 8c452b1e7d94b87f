"""The typed records of a run's decisions (what was decided, on which measurements), serialised into reports."""
from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass, field, fields
from enum import Enum

#: The kinds of step a run's account (`RunNote`) tells.
NOTE_KINDS = ("plan", "resumed", "restart", "recovered", "growth", "search", "early stop", "look", "warning",
              "wall")


class CheckAction(str, Enum):
    """What a training check decided (a str: the report and the wire carry its value)."""

    TRAIN_ON = "train on"
    GROW = "grow"
    ROLL_BACK = "roll back"
    FINISH = "finish"
    STOP_LEVEL_MET = "stop: level met"
    STOP_KEEP_MESH = "stop: keep the mesh"

    @property
    def stops(self) -> bool:
        """Whether the training ends here (the level met, or the mesh kept)."""
        return self in (CheckAction.STOP_LEVEL_MET, CheckAction.STOP_KEEP_MESH)


#: The values of CheckAction, in order.
CHECK_ACTIONS = tuple(a.value for a in CheckAction)


@dataclass(frozen=True)
class RunNote:
    """One step of a run's account, in order: kind (NOTE_KINDS) and one line for people. The run's `why` is its
    notes joined; the report keeps them typed."""

    kind: str
    text: str

    def __post_init__(self):
        if self.kind not in NOTE_KINDS:
            raise ValueError(f"unknown note kind {self.kind!r}; one of {', '.join(NOTE_KINDS)}")

    def to_dict(self) -> dict:
        return asdict(self)


def why_of(notes) -> str:
    """The notes as one line: 'plan; growth; ...'."""
    return "; ".join(n.text for n in notes)


def _measured(record) -> dict:
    """A record's fields that hold a measurement (None: not measured, left out of the report)."""
    return {f.name: getattr(record, f.name) for f in fields(record) if getattr(record, f.name) is not None}


def _known(cls, d: dict) -> dict:
    """The keys of `d` that are fields of `cls` (a report written by a later version may hold more)."""
    names = {f.name for f in fields(cls)}
    return {k: v for k, v in d.items() if k in names}


class _FromDict:
    """A record read back from its report form (`to_dict`): the fields it knows, as they are. A record holding
    other records overrides `from_dict` to read them too."""

    @classmethod
    def from_dict(cls, d: dict):
        return cls(**_known(cls, d))


@dataclass(frozen=True)
class TrainingPoint:
    """Where a training stands when it is checked, in work and in seconds (what the loop passes its check hook).
    step: optimizer steps so far; seconds: the budget's seconds spent (a check's own time off the clock as far as the
    run's wall allows); fraction: of the budget, in [0, 1] (steps or seconds, whichever runs out first);
    steps_at_end: the step the budget ends at (a step budget's own; for a time budget, this step plus the steady
    step rate times the seconds left: the rate of the steps since the last check, so a card's first seconds of
    kernel compilation do not count as its pace)."""

    step: int
    seconds: float
    fraction: float
    steps_at_end: float


@dataclass
class CheckDecision(_FromDict):
    """One training check. seconds since training began (the budget's clock); log2_table: the table's size then;
    mse: measured on the check views, the model at its stored precision; projected_mse: at the end of the budget at
    this size (None before a projection is possible); model_bytes: the file as it would ship at this size (geometry,
    look, header); alternative_bytes: the alternative's bytes at the projected MSE (None: no alternative measured);
    action: a CheckAction; reason: one line; colour_mse: for an asset whose head was trained before the geometry, the
    model's colour MSE on the check views (a mesh stands in for it only when it also reaches it); step: the
    training's step then; steps_at_end: the step the budget was expected to end at (the projection runs to it)."""

    seconds: float
    log2_table: int
    mse: float
    projected_mse: float | None
    model_bytes: int
    alternative_bytes: float | None
    action: CheckAction
    reason: str
    colour_mse: float | None = None
    step: int | None = None
    steps_at_end: float | None = None

    # At __init__ and whenever a rule changes it, the action stays a CheckAction: its value is accepted, anything
    # else is a ValueError.
    def __setattr__(self, name, value):
        super().__setattr__(name, CheckAction(value) if name == "action" else value)

    def to_dict(self) -> dict:
        return {**asdict(self), "action": self.action.value}


@dataclass
class MeshMeasure(_FromDict):
    """One mesh measured as the alternative to a model (`app.alternatives`): a decimation of the asset
    (`requested_triangles`: the count asked for) or the whole mesh (`requested_triangles` None). Bytes are exact:
    `compact_bytes` the compact ray-traceable mesh (geometry), `look_bytes` what it needs beside to carry the asset's
    look, `resident_bytes` as a plain ray tracer holds it, `draco11_bytes` Draco's storage size. MSEs are the run's
    metric: `mse` the decimation itself, `colour_mse` it as it ships with its look and `compact_mse` its compact mesh
    decoded, on the check views; `compact_mse_held_out` and `colour_mse_held_out` on the held-out views.
    None: not measured (a decimation that came out empty has only its counts and infinite MSEs)."""

    triangles: int
    requested_triangles: int | None = None
    mse: float | None = None
    resident_bytes: int | None = None
    compact_bytes: int | None = None
    look_bytes: int | None = None
    compact_mse: float | None = None
    colour_mse: float | None = None
    compact_mse_held_out: float | None = None
    colour_mse_held_out: float | None = None
    draco11_bytes: int | None = None

    def meets(self, target_mse: float) -> bool:
        """Whether its compact mesh meets `target_mse` on the check views and, where measured, the held-out views."""
        return max(self.compact_mse, self.compact_mse_held_out or 0.0) <= target_mse

    def with_look(self) -> "MeshMeasure":
        """The same measure with the look's bytes counted in its resident and compact bytes (how it is weighed
        against a model, whose file carries the look)."""
        def plus_look(nbytes: int | None) -> int | None:
            return None if nbytes is None else nbytes + (self.look_bytes or 0)

        return dataclasses.replace(self, resident_bytes=plus_look(self.resident_bytes),
                                   compact_bytes=plus_look(self.compact_bytes))

    def to_dict(self) -> dict:
        return _measured(self)


@dataclass
class Alternatives:
    """What a user could ship instead of a model, as measured (`app.alternatives.alternatives`): Draco's size of
    the mesh (storage only), the decimations tried in triangle order and the smallest that met the target
    (`decimation`), the whole mesh as a compact mesh, the metric's name, what was skipped past the plan's time share,
    and why nothing could be measured (`no_alternative`: the simplifier missing) or a note."""

    draco11_bytes: int | None = None
    note: str | None = None
    no_alternative: str | None = None
    metric: str | None = None
    decimation: MeshMeasure | None = None
    decimations_tried: list[MeshMeasure] = field(default_factory=list)
    mesh_compact: MeshMeasure | None = None
    skipped: str | None = None

    def add_note(self, text: str) -> None:
        self.note = f"{self.note}; {text}" if self.note else text

    def tried(self, requested_triangles: int) -> MeshMeasure | None:
        """The decimation measured for `requested_triangles`, or None."""
        return next((e for e in self.decimations_tried if e.requested_triangles == requested_triangles), None)

    def to_dict(self) -> dict:
        out = _measured(self)
        for name in ("decimation", "mesh_compact"):
            if name in out:
                out[name] = out[name].to_dict()
        out["decimations_tried"] = [e.to_dict() for e in self.decimations_tried]
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "Alternatives":
        known = _known(cls, d)
        for name in ("decimation", "mesh_compact"):
            if known.get(name) is not None:
                known[name] = MeshMeasure.from_dict(known[name])
        known["decimations_tried"] = [MeshMeasure.from_dict(e) for e in known.get("decimations_tried", [])]
        return cls(**known)


@dataclass(frozen=True)
class ShippedMesh(_FromDict):
    """The mesh a final verdict ships instead of the model: its triangles, the decimation count asked for (None:
    the whole mesh), its compact bytes with the look's, and its held-out MSE and colour MSE (None: not measured)."""

    triangles: int
    requested_triangles: int | None
    compact_bytes: int
    mse: float
    colour_mse: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class FinalVerdict:
    """The model as shipped against the alternative at the same measured quality (held-out views).
    model_bytes: the .nbvh file; model_mse: its held-out MSE; alternative_bytes: the compact decimation's bytes
    that reach the model's MSE (interpolated on the measured curve; None: not measured); shipped: 'model' or
    'decimation' or 'mesh'; decimation: the measured mesh shipped instead (`ShippedMesh`) or None; level_met: the
    model met the target on the held-out views;
    forced: the user asked for the model whatever the verdict; message: one line for people; at_level: the mesh
    shipped was chosen at the target (the model missed it), not at the model's MSE; alternative_above: see below."""

    model_bytes: int
    model_mse: float
    alternative_bytes: float | None
    shipped: str
    decimation: ShippedMesh | None
    level_met: bool | None
    forced: bool
    message: str
    at_level: bool = False
    #: Where no measured point reaches the model's MSE: the bytes of the largest measured decimation that misses it
    #: (any decimation reaching it is larger: bytes grow with triangles), else None.
    alternative_above: int | None = None
    #: For an asset with a look: the file's colour MSE on the held-out views, which a mesh had to reach too to ship
    #: instead (`final_verdict`); None: geometry alone was weighed.
    model_colour_mse: float | None = None

    @property
    def ratio(self) -> float | None:
        """alternative bytes / model bytes at equal measured MSE (> 1: the model is smaller)."""
        return None if not self.alternative_bytes else self.alternative_bytes / self.model_bytes

    def to_dict(self) -> dict:
        return {**asdict(self), "ratio": self.ratio}

    @classmethod
    def from_dict(cls, d: dict) -> "FinalVerdict":
        """The record `to_dict` wrote (its derived `ratio` is computed again)."""
        known = _known(cls, d)
        if known.get("decimation") is not None:
            known["decimation"] = ShippedMesh.from_dict(known["decimation"])
        return cls(**known)


@dataclass
class Assessment:
    """model_bytes: the .nbvh size (exact payload + typical header); resident: `planning.sizing.mesh_resident_bytes(mesh)`;
    compact_bytes: the mesh in the compact ray-traceable layout; layout: the one the model was weighed against
    (decision.config.MESH_LAYOUTS); alternatives: what was measured (`app.alternatives.alternatives`); recommendation:
    what to use (decision.verdict.RECOMMENDATIONS: 'neural', 'mesh': the mesh as it is, 'decimate': the decimation
    in `alternatives.decimation`)."""

    model_bytes: int
    resident: dict
    worth_compressing: bool
    message: str
    alternatives: Alternatives = field(default_factory=Alternatives)
    recommendation: str = "neural"
    #: The whole mesh as a compact ray-traceable mesh (`compact_mesh.encode_compact`), exact bytes.
    compact_bytes: int | None = None
    layout: str = "compact"
    #: The final verdict that kept the mesh after training began, or None.
    final: FinalVerdict | None = None
    #: When a decision after training began kept the mesh: the training's checks until then.
    checks: list[CheckDecision] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {**asdict(self), "alternatives": self.alternatives.to_dict(),
                "final": self.final.to_dict() if self.final is not None else None,
                "checks": [c.to_dict() for c in self.checks]}

    @classmethod
    def from_dict(cls, d: dict) -> "Assessment":
        """The record a report holds (`to_dict`) read back: the same measurements, typed."""
        known = _known(cls, d)
        known["alternatives"] = Alternatives.from_dict(known.get("alternatives") or {})
        known["final"] = FinalVerdict.from_dict(known["final"]) if known.get("final") else None
        known["checks"] = [CheckDecision.from_dict(c) for c in known.get("checks") or []]
        return cls(**known)


@dataclass
class RunDecisions:
    """The decisions on measurements of a run that trained: every training check (in order), the model's MSE on the
    check views and on the held-out views, the final verdict (None: nothing was weighed after training) and the
    alternative's curve on the held-out views it was weighed against (`AlternativeCurve.to_dict`)."""

    checks: list[CheckDecision] = field(default_factory=list)
    mse_check_views: float | None = None
    mse_held_out_views: float | None = None
    final: FinalVerdict | None = None
    alternative: list[dict] | None = None

    def to_dict(self) -> dict:
        return {"checks": [c.to_dict() for c in self.checks], "mse_check_views": self.mse_check_views,
                "mse_held_out_views": self.mse_held_out_views,
                "final": self.final.to_dict() if self.final is not None else None, "alternative": self.alternative}
