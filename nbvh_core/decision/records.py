"""The typed records of a run's decisions (what was decided, on which measurements), serialised into reports."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from enum import Enum

#: The kinds of step a run's account (`RunNote`) tells.
NOTE_KINDS = ("plan", "resumed", "restart", "recovered", "growth", "search", "early stop")


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


@dataclass
class CheckDecision:
    """One training check. seconds since training began; log2_table: the table's size then; mse: measured on the
    check views, the model at its stored precision; projected_mse: at the end of the budget at this size (None
    before a projection is possible); model_bytes: the file as it would ship at this size (geometry, look,
    header); alternative_bytes: the alternative's bytes at the projected MSE (None: no alternative measured);
    action: a CheckAction; reason: one line."""

    seconds: float
    log2_table: int
    mse: float
    projected_mse: float | None
    model_bytes: int
    alternative_bytes: float | None
    action: CheckAction
    reason: str

    # At __init__ and whenever a rule changes it, the action stays a CheckAction: its value is accepted, anything
    # else is a ValueError.
    def __setattr__(self, name, value):
        super().__setattr__(name, CheckAction(value) if name == "action" else value)

    def to_dict(self) -> dict:
        return {**asdict(self), "action": self.action.value}


@dataclass
class FinalVerdict:
    """The model as shipped against the alternative at the same measured quality (held-out views).
    model_bytes: the .nbvh file; model_mse: its held-out MSE; alternative_bytes: the compact decimation's bytes
    that reach the model's MSE (interpolated on the measured curve; None: not measured); shipped: 'model' or
    'decimation' or 'mesh'; decimation: the measured decimation shipped instead (its triangles, requested count,
    compact bytes and held-out MSE) or None; level_met: the model met the target on the held-out views;
    forced: the user asked for the model whatever the verdict; message: one line for people; at_level: the mesh
    shipped was chosen at the target (the model missed it), not at the model's MSE; alternative_above: see below."""

    model_bytes: int
    model_mse: float
    alternative_bytes: float | None
    shipped: str
    decimation: dict | None
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


@dataclass
class Assessment:
    """model_bytes: the .nbvh size (exact payload + typical header); resident: `planning.sizing.mesh_resident_bytes(mesh)`;
    compact_bytes: the mesh in the compact ray-traceable layout; layout: the one the model was weighed against
    (decision.config.MESH_LAYOUTS); alternatives: `app.alternatives.alternatives(...)` when measured; recommendation: what to use (decision.verdict.RECOMMENDATIONS: 'neural',
    'mesh': the mesh as it is, 'decimate': the decimation in alternatives['decimation'])."""

    model_bytes: int
    resident: dict
    worth_compressing: bool
    message: str
    alternatives: dict = field(default_factory=dict)
    recommendation: str = "neural"
    #: The whole mesh as a compact ray-traceable mesh (`compact_mesh.encode_compact`), exact bytes.
    compact_bytes: int | None = None
    layout: str = "compact"
    #: The decision that kept the mesh after training began (`decision.records.FinalVerdict` as a dict), or None.
    final: dict | None = None
    #: When a decision after training began kept the mesh: the training's checks until then (`CheckDecision` as dicts).
    checks: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)
