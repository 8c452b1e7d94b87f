"""A run's configuration, nested by concern and frozen: `plan_run` turns one request (`Settings`: flat, the record
files and checkpoints keep) into the parts each stage of a run takes, and nothing below asks for more than its part:

    RunConfig.nodes     -> geometry.bvh.build_bvh
    RunConfig.model     -> neural.model.NeuralBVH          (encoding, network)
    RunConfig.training  -> training.train.train            (budget, schedule, labels, quantization-aware end)
    RunConfig.storage   -> storage.fileformat.encode_nbvh  (bits per value)
    RunConfig.decision  -> decision.*                      (level, layout, size search, checks, force)
    RunConfig.metric    -> rendering.metrics.view_sets     (views, resolution)
    RunConfig.look      -> training.appearance_training    (the appearance head and its share of the budget)
    RunConfig.sizes     -> RunConfig.at_table              (with a target: every table size the run may train)
    RunConfig.growth    -> decision.checks.CheckRule       (with a target: the growing training's plan)
    RunConfig.predicted_log_mse -> decision.size_search  (with a target: the retrain search's predictions)

The run is planned once: a size search or a growing table reads the sizes planned here, nothing derives them again.
Every default lives once, on the part that uses it (TrainConfig, StorageConfig, ...); `Settings` takes its defaults
from them and the presets set what the product uses."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from ..decision.config import DecisionConfig
from ..decision.growth import SMALLEST_START, GrowthPlan, growth_clock, plan_growth
from ..decision.records import RunNote
from ..geometry.mesh import Mesh
from ..neural.appearance import AppearanceConfig
from ..neural.model import ModelConfig
from ..neural.quantize import StorageConfig
from ..rendering.metrics import MetricConfig
from ..training.config import TrainConfig
from .card_batch import rays_per_step as card_rays_per_step
from .settings import Settings, estimate_file_bytes
from .mesh_measures import GridMeasures, grid_measures
from .sizing import LOG2_RANGE, forecast, size_request


@dataclass(frozen=True)
class LookConfig:
    """The appearance head (`neural.appearance`): its architecture template (`head`; the asset fills in its slots
    and patches) and its training budget: `budget_s` seconds, or None: `share` of the geometry's training time
    (a run in steps)."""

    head: AppearanceConfig
    share: float
    budget_s: float | None
    #: the largest size on screen (pixels) the textures are held at (`geometry.texture_hold`; 0: as they are)
    on_screen_px: int = 0


@dataclass(frozen=True)
class SizePlan:
    """The run at one table size: its model's configuration, the grid's finest resolution it records (`n_max`) and
    its file's bytes (exact payload + typical header, the look not included)."""

    model: ModelConfig
    n_max: int | None
    file_bytes: int


@dataclass(frozen=True)
class RunConfig:
    """What one run does, by part. request: the resolved flat Settings this configuration was made from (written
    into the file's header and checkpoints); file_bytes: the model's file at these sizes (exact payload + typical
    header, the look not included); grid: the mesh's measures when the grid's finest resolution follows the mesh
    (re-chosen at every table size a search tries), else None; notes: why these sizes (typed, for the report);
    expected_log2_table: with a target, the table the predictor expects to meet it (`sizing.expected_table`: what
    the verdict before training weighs), else None; sizes: every other table size a run with a target may train,
    planned with the run ({(log2 T, grid re-chosen): SizePlan}; `at_table` reads them); growth: with a target and
    size_search "grow", the growing training's plan (`decision.growth`: start and largest table, clock, check
    period), else None; predicted_log_mse: with a target, the size predictor's ln MSE at each table size in
    LOG2_RANGE (and the planned one) at the training's budget ({log2 T: ln MSE}; empty without a fit: the retrain
    search's guide)."""

    request: Settings
    nodes: int
    model: ModelConfig
    training: TrainConfig
    storage: StorageConfig
    decision: DecisionConfig
    metric: MetricConfig
    look: LookConfig
    file_bytes: int
    grid: GridMeasures | None = None
    notes: tuple[RunNote, ...] = ()
    expected_log2_table: int | None = None
    sizes: dict = field(default_factory=dict, compare=False)
    growth: GrowthPlan | None = None
    predicted_log_mse: dict = field(default_factory=dict, compare=False)

    @property
    def log2_table(self) -> int:
        return self.model.encoding.log2_table

    def at_table(self, log2_table: int, regrid: bool = True) -> "RunConfig":
        """The same run with a table of 2^log2_table rows, as planned (`sizes`); regrid: with the grid's finest
        resolution chosen for the mesh at that size, when it follows the mesh (a growing table keeps the resolution
        it was planned for). Raises ValueError for a size the run did not plan."""
        regrid = regrid and self.grid is not None
        if log2_table == self.log2_table and not regrid:
            return self
        plan = self.sizes.get((log2_table, regrid))
        if plan is None:
            raise ValueError(f"table size 2^{log2_table} was not planned for this run (a run with a target plans "
                             f"2^{SMALLEST_START}-2^{LOG2_RANGE[-1]})")
        request = dataclasses.replace(self.request, log2_table=log2_table, n_max=plan.n_max)
        return dataclasses.replace(self, request=request, model=plan.model, file_bytes=plan.file_bytes)

    def with_training(self, **changes) -> "RunConfig":
        """The same run with some training knobs changed (a restart's learning rate, a check period): the request
        records them too."""
        return dataclasses.replace(self, request=dataclasses.replace(self.request, **changes),
                                   training=dataclasses.replace(self.training, **changes))


def plan_run(settings: Settings, mesh: Mesh, resumed: bool = False) -> RunConfig:
    """The run `settings` asks for on `mesh`: a byte budget or a target MSE turned into sizes (`sizing.resolve`;
    the grid's finest resolution chosen for the mesh when `settings.n_max` is None), and the time budget split
    between the geometry and, for an asset with a look, the appearance head (`appearance_share` of it; the request
    keeps the budget asked). resumed: the sizes are the checkpoint's (fixed; the grid is not re-chosen). Raises
    ValueError (one line) for settings no run can use."""
    grid = grid_measures(mesh) if settings.n_max is None and not resumed else None
    sized = size_request(settings, mesh, grid, resumed)
    s = sized.settings
    look_s = s.time_limit_s * s.appearance_share if mesh.look is not None and s.time_limit_s else None
    look = LookConfig(AppearanceConfig(target=s.appearance_target, log2_table=s.appearance_log2_table),
                      s.appearance_share, look_s, s.texture_on_screen_px)
    # The one place the flat request becomes the parts (the training's budget less the look's share).
    training = s.train_config()
    if s.rays_per_step is None:  # the device's own: a card takes larger steps (card_batch)
        training = dataclasses.replace(training, rays_per_step=card_rays_per_step(s.device))
    if look_s is not None:
        training = dataclasses.replace(training, time_limit_s=s.time_limit_s - look_s)
    model, storage = s.model_config(), s.storage()
    run = RunConfig(request=s, nodes=s.nodes, model=model, training=training, storage=storage,
                    decision=DecisionConfig(target_mse=s.target_mse, mesh_layout=s.mesh_layout,
                                            size_search=s.size_search, check_every_s=s.target_check_every_s,
                                            force=s.force),
                    metric=MetricConfig(s.eval_views, s.eval_resolution), look=look,
                    file_bytes=estimate_file_bytes(s), grid=grid, notes=sized.notes)
    if resumed or s.target_mse is None:  # a fixed size: the run trains the one planned table
        return run
    sizes = _sizes(s, sized.resolutions)
    fc = forecast(sized, range(min(LOG2_RANGE[0], run.log2_table), max(LOG2_RANGE[-1], run.log2_table) + 1),
                  range(SMALLEST_START, LOG2_RANGE[-1] + 2),  # every start of a growth and the size above its largest
                  run.nodes, training.time_limit_s, growth_clock(training.time_limit_s))
    growth = (plan_growth(run.log2_table, LOG2_RANGE[-1], training.time_limit_s, run.decision.check_every_s,
                          fc.budget_slopes, fc.growth_log_mse) if run.decision.size_search == "grow" else None)
    return dataclasses.replace(run, expected_log2_table=sized.expected_log2_table, sizes=sizes, growth=growth,
                               predicted_log_mse=fc.log_mse)


def _sizes(s: Settings, resolutions: dict) -> dict:
    """{(log2 T, grid re-chosen): SizePlan} for every size a run with a target may train: a growing training's
    start (from 2^SMALLEST_START) up to the predictor's largest size, with the planned grid resolution and, when the
    grid follows the mesh, with the one chosen for each size (`resolutions`: the retrain search's)."""
    sizes = {}
    for log2_table in range(SMALLEST_START, LOG2_RANGE[-1] + 1):
        for regrid in (False, True) if resolutions else (False,):
            n_max = resolutions[log2_table] if regrid else s.n_max
            sized = dataclasses.replace(s, log2_table=log2_table, n_max=n_max)
            sizes[(log2_table, regrid)] = SizePlan(sized.model_config(), n_max, estimate_file_bytes(sized))
    return sizes
