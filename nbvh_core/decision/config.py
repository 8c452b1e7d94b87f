"""What a run's decisions are asked to weigh: the quality level, the mesh layout the model is weighed against, how
the size is searched, how often training is checked, and whether the user forces the model whatever the verdict."""
from __future__ import annotations

from dataclasses import dataclass

#: The mesh layouts the model can be weighed against: "compact", the strongest ray-traceable mesh
#: (`geometry.compact_mesh`), or "plain", as Embree or Cycles hold it (~44 B per triangle).
MESH_LAYOUTS = ("compact", "plain")
#: "grow": one training whose table doubles in place while the checks say growing pays; "retrain": predict T,
#: train, measure, correct.
SIZE_SEARCHES = ("grow", "retrain")


@dataclass(frozen=True)
class DecisionConfig:
    """target_mse: the image-MSE level the model must meet (None: a fixed size, no alternative measured);
    mesh_layout: one of MESH_LAYOUTS; size_search: one of SIZE_SEARCHES; check_every_s: seconds between training
    checks (the check views; growth and early stop); force: write the model even where a measured alternative is
    smaller."""

    target_mse: float | None = None
    mesh_layout: str = "compact"
    size_search: str = "grow"
    check_every_s: float = 20.0
    force: bool = False

    def __post_init__(self):
        if self.mesh_layout not in MESH_LAYOUTS:
            raise ValueError(f"mesh_layout must be one of {', '.join(MESH_LAYOUTS)}, got {self.mesh_layout!r}")
        if self.size_search not in SIZE_SEARCHES:
            raise ValueError(f"size_search must be one of {', '.join(SIZE_SEARCHES)}, got {self.size_search!r}")
        if self.target_mse is not None and not self.target_mse > 0:
            raise ValueError(f"target MSE must be > 0, got {self.target_mse:g}")
